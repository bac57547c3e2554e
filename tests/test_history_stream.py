"""The history CSV written as the run goes: on disk before the end, and at the end the
same rows, per filter and in order, as the whole history written at once."""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.estimation.estimator import FilterKind, StepOutput
from gcs_estimator.frames import Frame
from gcs_estimator.outputs.history_csv import write_history_csv
from gcs_estimator.outputs.sinks import ResultsSink
from gcs_estimator.runtime.session import RecordingSource, Session
from gcs_estimator.uncertainty.result import VehicleResult
from sim.truth import simulate
from tests.conftest import CONFIGS

BLOCK = 64


class LineCounter:
    """A sink after the results writer: how many lines its CSV holds at each frame."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.lines: list[int] = []

    def on_frame(self, frame: Frame, outs: Mapping[FilterKind, StepOutput]) -> None:
        text = self.path.read_text() if self.path.exists() else ""
        self.lines.append(len(text.splitlines()))

    def tick(self) -> None:
        pass

    def finish(self, results: Mapping[int, VehicleResult], link: Mapping[str, Any] | None) -> None:
        pass


def _rows_by_filter(path: Path) -> tuple[str, dict[str, list[str]]]:
    header, *rows = path.read_text().splitlines()
    out: dict[str, list[str]] = defaultdict(list)
    for row in rows:
        out[row.split(",", 1)[0]].append(row)
    return header, dict(out)


def _run(config: AircraftConfig, out: Path) -> tuple[Session, LineCounter]:
    flight = simulate(config, seed=4)
    session = Session(config)
    sink = ResultsSink(
        out,
        lambda v, e: "",
        lambda sid: f"results_sys{sid}",
        lambda: session.elapsed_s,
        out=open(out / "stdout.txt", "w"),  # noqa: SIM115 (the test's folder)
        estimators=lambda: session.estimators,
        history_block_frames=BLOCK,
        history_format="csv",
    )
    counter = LineCounter(out / "results_sys1_history.csv")
    session.add_sink(sink)
    session.add_sink(counter)
    session.run(RecordingSource(flight.t_s, flight.inputs, flight.measurements))
    return session, counter


def test_history_streams_to_disk_and_ends_equal_to_the_whole(tmp_path: Path) -> None:
    """A flight with two restarts, the second still re-running when the data end (its
    swap replaces the newest row at the end): the rows streamed in blocks plus the rest
    written at the stop are the rows of the final history, filter by filter."""
    config = load_config(
        CONFIGS / "noc_uav.toml",
        ["simulation.manoeuvre.duration_s=12", "filter.restart_times_s=[5.0, 11.9]"],
    )
    session, counter = _run(config, tmp_path)
    est = session.estimators[1]
    assert est.restarts.done == 2
    frames = est.history_rows
    # During the run: a block of both filters on disk once a block of rows is final.
    first = counter.lines.index(1 + 2 * BLOCK)
    assert counter.lines[:first] == [1] * first
    assert max(counter.lines) < 1 + 2 * frames  # the rest came at the stop

    whole = tmp_path / "whole.csv"
    write_history_csv(whole, session.results()[1].result)
    header, streamed = _rows_by_filter(tmp_path / "results_sys1_history.csv")
    whole_header, expected = _rows_by_filter(whole)
    assert header == whole_header
    assert set(streamed) == {"EKF", "IEKF"}
    for kind in ("EKF", "IEKF"):
        assert len(streamed[kind]) == frames
        assert streamed[kind] == expected[kind]
