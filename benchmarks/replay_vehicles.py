"""Replay of a station's recording with many vehicles: one process against the filters
sharded over K worker processes (`replay --filter-workers K`).

    python benchmarks/replay_vehicles.py --vehicles 10 --minutes 2 [--workers 1,2]

Each vehicle flies its own simulated flight (seed = its system id); their packets are
merged by receive time into one .tlog, as `listen` records a link with many vehicles.
That recording is replayed as fast as possible as `replay` does (decoding in its worker
process), with no view and no result files, first with the filters in the replaying
process, then with them in K worker processes for each K given. Each is run --runs times,
alternating, and given as the best with the median beside it. Prints the workers' start
(imports, compiled kernels loaded: a cost per run, not per frame) apart from the replay's
wall time, frames/s, the multiple of real time (all vehicles' flight time over the
replay's wall time), and the CPU of the replaying process and of its worker processes in
the replay; and checks that every run ends with the same estimates.
"""

from __future__ import annotations

import argparse
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import record  # benchmarks/record.py: the script's directory is on sys.path
from flights import repeated_manoeuvre

from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.ingest.flightdata import Recording
from gcs_estimator.ingest.telemetry.link import MavlinkLink
from gcs_estimator.ingest.telemetry.mavlink import TlogWriter, read_tlog
from gcs_estimator.runtime.decode_worker import tlog_source
from gcs_estimator.runtime.filter_worker import ShardedSession
from gcs_estimator.runtime.session import Session, warm_up
from gcs_estimator.uncertainty.result import VehicleResult
from sim.truth import simulate
from sim.vehicle import SimulatedVehicle


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--vehicles", type=int, default=10)
    ap.add_argument("--minutes", type=int, default=2)
    ap.add_argument("--workers", default="1,2", help="filter worker counts to time, e.g. 1,2")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--config", default="noc_uav")
    record.add_argument(ap, "replay_vehicles")
    args = ap.parse_args(argv)
    workers = [int(k) for k in args.workers.split(",") if k.strip()]
    if args.vehicles < 1 or args.runs < 1 or any(k < 1 for k in workers):
        ap.error("--vehicles, --runs and every --workers count: at least 1")
    title = "Replay of many vehicles: filters in one process and in K worker processes"
    with record.recorded("replay_vehicles", args.record, title):
        return run(args, workers)


def _recording(config: AircraftConfig, vehicles: int, tmp: Path) -> tuple[Path, int]:
    """One .tlog holding every vehicle's packets by receive time; (its path, frames)."""
    records: list[tuple[int, int, bytes]] = []
    frames = 0
    for sid in range(1, vehicles + 1):
        fl = simulate(config, seed=sid)
        frames += len(fl.t_s)
        rec = Recording(fl.t_s, fl.inputs, fl.measurements, "throttle")
        own = tmp / f"vehicle{sid}.tlog"
        vehicle = SimulatedVehicle(rec, config.link, ("127.0.0.1", 9), sid, 0.0, own)
        vehicle.run()
        # Sent as fast as possible: the send times, stretched over the flight's length,
        # are when a link would have delivered them.
        own_records = list(read_tlog(own))
        t0, t1 = own_records[0].t_recv_us, own_records[-1].t_recv_us
        stretch = (fl.t_s[-1] - fl.t_s[0]) * 1e6 / max(t1 - t0, 1)
        records += [(int((r.t_recv_us - t0) * stretch), sid, r.packet) for r in own_records]
        own.unlink()
    records.sort(key=lambda r: (r[0], r[1]))
    path = tmp / "fleet.tlog"
    writer = TlogWriter(path)
    start_us = int(time.time() * 1e6)
    for t_us, _sid, packet in records:
        writer.write(start_us + t_us, packet)
    writer.close()
    return path, frames


def _children_cpu() -> float:
    used = resource.getrusage(resource.RUSAGE_CHILDREN)
    return used.ru_utime + used.ru_stime


def _replay(
    config: AircraftConfig, path: Path, workers: int
) -> tuple[float, float, float, float, dict[int, VehicleResult]]:
    """(the filter workers' start [s], the replay's wall time [s], this process's CPU [s],
    its workers' CPU in the replay [s], results) of one replay."""
    link = MavlinkLink(config.link)
    source = tlog_source([str(path)], link)
    session: Session | ShardedSession
    start = 0.0
    if workers:
        t0 = time.perf_counter()
        session = ShardedSession(config, workers, None)
        session.start()
        start = time.perf_counter() - t0
    else:
        session = Session(config)
    cpu0, child0 = time.process_time(), _children_cpu()
    t0 = time.perf_counter()
    results = session.run(source)
    wall = time.perf_counter() - t0
    children = _children_cpu() - child0
    if isinstance(session, ShardedSession):  # the workers' start is timed apart
        children -= session.workers_start_cpu_s
    return start, wall, time.process_time() - cpu0, children, results


def run(args: argparse.Namespace, workers: list[int]) -> int:
    overrides = [*repeated_manoeuvre(args.minutes), "filter.structure_check=off"]
    overrides.append(f"link.max_vehicles={max(args.vehicles, 1)}")
    config = load_config(args.config, overrides)
    warm_up(config)
    with tempfile.TemporaryDirectory() as tmp_dir:
        path, frames = _recording(config, args.vehicles, Path(tmp_dir))
        size = path.stat().st_size / 1e6
        flight_s = args.vehicles * args.minutes * 60.0
        print(
            f"{args.vehicles} vehicles x {args.minutes} min, {frames} frames, one .tlog of "
            f"{size:.1f} MB; replayed as fast as possible (decoding in its worker process), "
            f"no view, no result files, {args.runs} runs each, alternating"
        )
        counts = [0, *workers]
        walls: dict[int, list[float]] = {k: [] for k in counts}
        cpus: dict[int, list[tuple[float, float, float]]] = {k: [] for k in counts}
        estimates: dict[int, dict[int, np.ndarray]] = {}
        for _ in range(args.runs):
            for k in counts:
                start, wall, cpu, child, results = _replay(config, path, k)
                walls[k].append(wall)
                cpus[k].append((start, cpu, child))
                got = {sid: v.result.filters["IEKF"].coefficients for sid, v in results.items()}
                if sum(v.result.frames for v in results.values()) != frames:
                    print(f"error: {k} workers estimated other frames than flown", file=sys.stderr)
                    return 1
                estimates.setdefault(k, got)
        print(
            "\n| filters in | workers' start s | replay wall s (best / median) | frames/s "
            "(best) | x real time (best) | replaying process CPU s | worker processes CPU s "
            "(decoding, filters) |\n|---|---|---|---|---|---|---|"
        )
        for k in counts:
            best = min(walls[k])
            i = walls[k].index(best)
            start, cpu, child = cpus[k][i]
            where = "the replaying process" if k == 0 else f"{k} worker process{'es' * (k > 1)}"
            print(
                f"| {where} | {start:.2f} | {best:.2f} / {statistics.median(walls[k]):.2f} | "
                f"{frames / best:,.0f} | {flight_s / best:,.0f}x | {cpu:.1f} | {child:.1f} |"
            )
        same = all(
            all(np.array_equal(estimates[k][sid], estimates[0][sid]) for sid in estimates[0])
            for k in workers
        )
        print(f"\nthe same IEKF estimates in every run, every vehicle: {'yes' if same else 'NO'}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
