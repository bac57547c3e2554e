"""Stop time: how long a station takes to finish its results after a long flight of
many vehicles.

    python benchmarks/stop.py [--vehicles 10] [--minutes 60]

Every vehicle flies the same simulated flight (the work per vehicle is what matters
here), interleaved frame by frame as a station receives them, through one session with
the results writer, as `listen` runs it (view off). The clock starts when the last frame
has been processed and stops when every vehicle's table, JSON, Markdown and history CSV
are written (target: within 2 s for 10 vehicles after an hour). The same results are then
written again with the whole history at the end, as before the history was written
as the run goes, for comparison. --history picks the history's format (Parquet, the
default, or CSV); its size per vehicle-hour is printed (target for Parquet: at most a
fifth of the CSV's).
"""

from __future__ import annotations

import argparse
import io
import sys
import tempfile
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import record  # benchmarks/record.py: the script's directory is on sys.path
from flights import repeated_manoeuvre

from gcs_estimator.config import load_config
from gcs_estimator.estimation.estimator import FilterKind, StepOutput
from gcs_estimator.frames import Frame
from gcs_estimator.outputs.report import write_results
from gcs_estimator.outputs.sinks import ResultsSink
from gcs_estimator.runtime.session import Session, warm_up
from gcs_estimator.stop import Stop
from gcs_estimator.uncertainty.result import VehicleResult
from sim.truth import simulate


class FleetSource:
    """One recorded flight, flown by `vehicles` system ids at once: each frame's
    vehicles in turn. Notes when its last frame has been processed."""

    def __init__(self, t: np.ndarray, u: np.ndarray, y: np.ndarray, vehicles: int) -> None:
        self.t, self.u, self.y, self.vehicles = t, u, y, vehicles
        self.ended = 0.0

    def frames(self, stop: Stop) -> Iterator[Frame | None]:
        for i in range(len(self.t)):
            t = float(self.t[i])
            for sid in range(1, self.vehicles + 1):
                yield Frame(sid, t, t, self.u[i], self.y[i])
        self.ended = time.perf_counter()

    def link_stats(self) -> dict[str, Any] | None:
        return None

    def close(self) -> None:
        pass


class Clock:
    """A sink that notes when the sinks before it have finished."""

    def __init__(self) -> None:
        self.at = 0.0

    def on_frame(self, frame: Frame, outs: Mapping[FilterKind, StepOutput]) -> None:
        pass

    def tick(self) -> None:
        pass

    def finish(self, results: Mapping[int, VehicleResult], link: Mapping[str, Any] | None) -> None:
        self.at = time.perf_counter()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--vehicles", type=int, default=10)
    ap.add_argument("--minutes", type=int, default=60)
    ap.add_argument("--history", choices=("parquet", "csv"), default="parquet")
    record.add_argument(ap, "stop")
    args = ap.parse_args(argv)
    with record.recorded("stop", args.record, "Stop: results after a long flight of many vehicles"):
        return run(args)


def run(args: argparse.Namespace) -> int:
    seconds = args.minutes * 60
    config = load_config("noc_uav", repeated_manoeuvre(args.minutes))
    flight = simulate(config, seed=1)
    warm_up(config)
    source = FleetSource(flight.t_s, flight.inputs, flight.measurements, args.vehicles)
    session = Session(config, check_frames=True)  # as listen: its frames checked at the end
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        summaries, written = Clock(), Clock()
        sink = ResultsSink(
            out / "streamed",
            lambda v, e: f"vehicle {v.system_id}: {v.result.frames} frames",
            lambda sid: f"results_sys{sid}",
            lambda: session.elapsed_s,
            out=io.StringIO(),
            estimators=lambda: session.estimators,
            history_format=args.history,
        )
        for s in (summaries, sink, written):
            session.add_sink(s)
        t0 = time.perf_counter()
        results = session.run(source)
        done = time.perf_counter()
        size = sum(p.stat().st_size for p in (out / "streamed").iterdir())
        name = f"_history.{args.history}"
        history = sum(p.stat().st_size for p in (out / "streamed").glob(f"*{name}"))

        whole = time.perf_counter()
        for sid, vehicle in results.items():
            stem = f"results_sys{sid}"
            extra = {"system_id": sid}
            write_results(out / "whole", vehicle, extra, stem, history_format=args.history)
        t_whole = time.perf_counter() - whole
        same = all(
            _rows(out / "streamed" / f"results_sys{sid}{name}")
            == _rows(out / "whole" / f"results_sys{sid}{name}")
            for sid in results
        )

    frames = sum(v.result.frames for v in results.values())
    print(
        f"{args.vehicles} vehicle(s) x {seconds:.0f} s, {frames} frames (both filters each) "
        f"in {source.ended - t0:.0f} s; results {size / 1e6:.0f} MB"
    )
    print(
        f"stop: {done - source.ended:.2f} s from the last frame to every vehicle's results "
        f"written (target <= 2 s with 10 vehicles after an hour): summaries "
        f"{summaries.at - source.ended:.2f} s, tables and files {written.at - summaries.at:.2f} s"
    )
    print(
        f"history: {args.history}, {history / 1e6 / (args.vehicles * seconds / 3600):.0f} MB "
        "per vehicle-hour"
    )
    print(
        f"the same results with the whole history written at the end: {t_whole:.2f} s "
        f"(history files {'of equal rows' if same else 'DIFFERENT'})"
    )
    return 0


def _rows(path: Path) -> int:
    """Rows of a history file (a CSV's lines, a Parquet file's rows)."""
    if path.suffix == ".csv":
        with open(path, "rb") as fh:
            return sum(1 for _ in fh)
    import pyarrow.parquet as pq

    rows: int = pq.ParquetFile(path).metadata.num_rows
    return rows


if __name__ == "__main__":
    sys.exit(main())
