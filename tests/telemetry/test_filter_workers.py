"""`--filter-workers K`: the vehicles' filters in worker processes, end to end (real
vehicle process, real UDP, real .tlog and .rrd, real worker processes), against a station
in one process and against a replay of its recording."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import pytest

from gcs_estimator import cli
from gcs_estimator.cli import main as gcs_main
from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.estimation.estimator import Estimator, FilterKind, StepOutput
from gcs_estimator.frames import Frame
from gcs_estimator.outputs.view import layout as lay
from gcs_estimator.runtime.filter_worker import ShardedSession, output_row, read_row
from gcs_estimator.runtime.session import Session
from gcs_estimator.stop import Stop
from gcs_estimator.uncertainty.result import VehicleResult
from sim.cli import command as vehicle_command
from sim.truth import simulate
from tests.telemetry.station import bound_port, start_listen
from tests.view.test_rerun import read_scalars

ROOT = Path(__file__).resolve().parents[2]
SHORT = ["simulation.manoeuvre.duration_s=12"]
QUICK = ["--set", "filter.structure_check=off", "--view", "off"]


def _results(folder: Path, sid: int) -> dict[str, Any]:
    out: dict[str, Any] = json.loads((folder / f"results_sys{sid}.json").read_text())
    return out


def _estimates(result: dict[str, Any]) -> dict[str, list[float]]:
    return {
        kind: [c["estimate"] for c in f["estimates"].values()]
        for kind, f in result["filters"].items()
    }


def _fly(port: int, vehicles: int) -> None:
    """Simulated vehicles (system ids 1..N) fly a short flight at 4x to the port."""
    done = subprocess.run(
        vehicle_command(ROOT / "configs/noc_uav.toml", f"127.0.0.1:{port}", 4.0, SHORT, vehicles),
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr


def test_a_station_with_its_filters_in_workers_gives_what_its_recording_replays_to(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Three vehicles -> UDP -> `listen --filter-workers 2` (its link in a worker too):
    every frame of every vehicle is estimated and in the view; the tables come in the
    order the vehicles were heard, each once; a replay of the recording with the same
    workers ends with the same results and history, value for value, and a replay in one
    process with the same estimates. A whole-record fit that fails in a worker sets the
    run's exit status as in one process."""
    live = tmp_path / "live"
    listen = ["udpin:127.0.0.1:0", "--filter-workers", "2", "--link-worker", "--idle-exit", "1.5"]
    station, line = start_listen(
        *listen, "--out", str(live), "--set", "filter.structure_check=off", "--view", "save"
    )
    assert "the filters in 2 processes" in line, line
    _fly(bound_port(line), 3)
    out, err = station.communicate(timeout=120)
    assert station.returncode == 0, err
    headings = [ln.split(" in ")[0] for ln in out.splitlines() if ln.startswith("vehicle ")]
    assert sorted(headings) == [f"vehicle {sid}: 601 frames" for sid in (1, 2, 3)], out
    assert out.rstrip().splitlines()[-1].startswith("link: ")

    config = load_config(ROOT / "configs/noc_uav.toml")
    axis = config.structure.axes[config.coefficient_names.index("Cma")]
    again = tmp_path / "again"
    one = tmp_path / "one"
    tlog = str(live / "telemetry.tlog")
    assert gcs_main(["replay", tlog, "--filter-workers", "2", "--out", str(again), *QUICK]) == 0
    assert gcs_main(["replay", tlog, "--out", str(one), *QUICK]) == 0
    for sid in (1, 2, 3):
        got = _results(live, sid)
        assert got["diagnostics"]["frames"] == 601  # 12 s at 50 Hz, every frame
        assert got["link"]["lost"] == 0 and got["link"]["received"] > 9000
        assert "--filter-workers" in got["run"]["command_line"]
        # The view has each vehicle's estimates from its first frame to its last (at
        # the view's estimate rate).
        t_flight, cma = read_scalars(live / "view.rrd", lay.coefficient_path(sid, "Cma", axis))
        history = f"results_sys{sid}_history.parquet"
        t_history = pq.read_table(live / history, columns=["t_s"]).column("t_s").to_numpy()
        assert len(t_history) == 601
        assert t_flight[0] == t_history[0] and t_flight[-1] == t_history[-1]
        assert len(t_flight) > 250 and np.all(np.isfinite(cma))

        want = _results(again, sid)
        assert got["filters"] == want["filters"]
        assert got["diagnostics"] == want["diagnostics"]
        assert pq.read_table(live / history).equals(pq.read_table(again / history))
        # In one process the vehicles' restarts take turns among all three, not among
        # the vehicles of one worker: the swaps come at other frames, the estimates
        # the same.
        assert _estimates(got) == _estimates(_results(one, sid))

    # --refine over a window the flights do not reach fails in each worker.
    capsys.readouterr()
    fit = ["--refine", "output-error", "--window", "70:80"]
    code = gcs_main(
        ["replay", tlog, "--filter-workers", "2", "--out", str(tmp_path / "fit"), *QUICK, *fit]
    )
    assert code == cli.EXIT_REFINE_FAILED
    err = capsys.readouterr().err
    assert "error: the whole-record fit failed (vehicle " in err
    for sid in (1, 2, 3):
        assert f"vehicle {sid}: only 0 frames in the window" in err
        assert _results(tmp_path / "fit", sid)["refined"] is None


class _Fleet:
    """Frames of simulated vehicles, interleaved as a link gives them (a None after every
    round, as a live source's idle ticks), and one repeated frame, which the estimator
    does not admit."""

    def __init__(self, config: AircraftConfig, vehicles: int) -> None:
        self.flights = [simulate(config, seed=sid) for sid in range(1, vehicles + 1)]

    def frames(self, stop: Stop) -> Iterator[Frame | None]:
        n = len(self.flights[0].t_s)
        for i in range(n):
            for sid, fl in enumerate(self.flights, start=1):
                t = float(fl.t_s[i])
                frame = Frame(sid, t, t, fl.inputs[i], fl.measurements[i])
                yield frame
                if i == 40 and sid == 1:
                    yield frame  # again: not admitted
            if i % 7 == 0:
                yield None

    def link_stats(self) -> dict[str, Any] | None:
        return None

    def close(self) -> None:
        pass


class _Outputs:
    """Every frame's outputs a sink was given, in order, per vehicle."""

    def __init__(self) -> None:
        self.seen: dict[int, list[tuple[float, dict[FilterKind, StepOutput]]]] = {}
        self.finished: Mapping[int, VehicleResult] | None = None

    def on_frame(self, frame: Frame, outs: Mapping[FilterKind, StepOutput]) -> None:
        self.seen.setdefault(frame.system_id, []).append((frame.t_vehicle_s, dict(outs)))

    def tick(self) -> None:
        pass

    def finish(self, results: Mapping[int, VehicleResult], link: Mapping[str, Any] | None) -> None:
        self.finished = results


def _same_outputs(a: dict[FilterKind, StepOutput], b: dict[FilterKind, StepOutput]) -> None:
    assert a.keys() == b.keys()
    for kind in a:
        assert np.array_equal(a[kind].x, b[kind].x)
        for field, value in a[kind].info._asdict().items():
            other = getattr(b[kind].info, field)
            assert np.array_equal(value, other, equal_nan=True), field


def test_the_sinks_see_what_a_station_in_one_process_gives_them() -> None:
    """One worker with both vehicles (so their restarts take the same turns): the view's
    and the status line's sink gets every admitted frame's outputs, equal to the float,
    and the final results and summaries are the same."""
    config = load_config(ROOT / "configs/noc_uav.toml", SHORT)
    fleet = _Fleet(config, 2)
    alone, sharded = _Outputs(), _Outputs()
    want = Session(config, sinks=[alone]).run(fleet)
    session = ShardedSession(config, 1, None, sinks=[sharded])
    got = session.run(fleet)
    assert session.errors == []
    assert list(got) == list(want) == [1, 2]
    for sid in (1, 2):
        assert len(sharded.seen[sid]) == len(alone.seen[sid]) == 601
        for (t_a, a), (t_b, b) in zip(sharded.seen[sid], alone.seen[sid], strict=True):
            assert t_a == t_b
            _same_outputs(a, b)
        g, w = got[sid], want[sid]
        assert repr(g.summaries) == repr(w.summaries)  # (NaN where no truth: == fails)
        for kind, f in w.result.filters.items():
            assert np.array_equal(g.result.filters[kind].coefficients, f.coefficients)
            assert np.array_equal(g.result.filters[kind].covariance, f.covariance)
            assert g.result.filters[kind].track is None  # left in the worker's CSV
        assert g.any_update() and g.result.frames == w.result.frames
        # What the status line and the live table read: where the run ended.
        remote = session.estimators[sid]
        assert remote.frames == w.result.frames
        for kind, snap in remote.snapshot().items():
            assert np.array_equal(snap.coefficients, w.result.filters[kind].coefficients)
            assert np.array_equal(snap.sigma, w.result.filters[kind].sigma)
    assert sharded.finished is not None and list(sharded.finished) == [1, 2]


class _KillShard:
    """A sink that kills the worker of vehicle `sid` at its `frames`-th output."""

    def __init__(self, session: ShardedSession, sid: int, frames: int) -> None:
        self.session = session
        self.sid = sid
        self.frames = frames
        self.seen = 0

    def on_frame(self, frame: Frame, outs: Mapping[FilterKind, StepOutput]) -> None:
        if frame.system_id == self.sid:
            self.seen += 1
            if self.seen == self.frames:
                pid = self.session.shard_of[self.sid]._process.pid
                os.kill(pid, signal.SIGKILL)

    def tick(self) -> None:
        pass

    def finish(self, results: Mapping[int, VehicleResult], link: Mapping[str, Any] | None) -> None:
        pass


@pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="needs SIGKILL")
def test_a_filter_worker_that_dies_is_reported_and_the_others_go_on(
    capsys: pytest.CaptureFixture[str],
) -> None:
    config = load_config(ROOT / "configs/noc_uav.toml", SHORT)
    session = ShardedSession(config, 2, None)
    session.add_sink(_KillShard(session, 2, 100))
    results = session.run(_Fleet(config, 2))
    err = capsys.readouterr().err
    assert "filter process 1 ended early" in err
    assert "frames were not estimated: their filter process had ended" in err
    assert len(session.errors) == 2
    # The other worker's vehicle went on to the end; the dead one's has no result.
    assert list(results) == [1] and results[1].result.frames == 601
    assert session.estimators[2].frames >= 100


def test_output_rows_carry_a_steps_outputs_exactly() -> None:
    config = load_config(ROOT / "configs/noc_uav.toml", SHORT)
    fl = simulate(config, seed=3)
    est = Estimator(config)
    n = est.model.n
    for i in range(30):
        t = float(fl.t_s[i])
        outs = est.step(t, fl.inputs[i], fl.measurements[i])
        gusts = {k: est.gust_level(k) for k in outs}
        only: dict[FilterKind, StepOutput] = {k: v for k, v in outs.items() if k == "IEKF"}
        for given in (dict(outs), only):
            seq, frames, back, back_gusts = read_row(output_row(i, est.frames, given, gusts, n), n)
            assert (seq, frames) == (i, est.frames)
            _same_outputs(back, dict(given))
            assert back_gusts == {k: gusts[k] for k in given}


def test_ctrl_c_ends_a_station_and_its_workers_with_every_result(tmp_path: Path) -> None:
    """Ctrl-C in a terminal reaches the station and its workers alike: the workers go on
    until the station has told them the run is over, so every vehicle's results are
    written."""
    out = tmp_path / "out"
    station, line = start_listen(
        "udpin:127.0.0.1:0", "--filter-workers", "2", "--out", str(out), *QUICK, own_group=True
    )
    _fly(bound_port(line), 2)
    os.killpg(station.pid, signal.SIGINT)
    _out, err = station.communicate(timeout=120)
    assert station.returncode == 0, err
    assert "Traceback" not in err
    for sid in (1, 2):
        got = _results(out, sid)
        assert got["diagnostics"]["frames"] == 601
        # The link's counts come with the station's word that the run is over.
        assert got["link"]["received"] > 3000


def test_sigterm_stops_a_station_and_its_filter_workers_cleanly(tmp_path: Path) -> None:
    proc, line = start_listen(
        "udpin:127.0.0.1:0", "--filter-workers", "2", "--out", str(tmp_path), *QUICK
    )
    assert "the filters in 2 processes" in line
    proc.terminate()
    _out, err = proc.communicate(timeout=60)
    assert proc.returncode == 1, err
    assert "no vehicle data received" in err and "no usable frame arrived" in err
    assert "Traceback" not in err


def test_filter_workers_must_be_a_positive_count(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        gcs_main(["replay", "x.tlog", "--filter-workers", "0"])
    assert exc.value.code == 2
    assert "argument --filter-workers: 0: at least 1" in capsys.readouterr().err


def test_a_workers_python_warnings_name_it() -> None:
    """A warning raised in a worker process reaches the shared stderr with the worker's
    number in front, the warning's own text after it."""
    code = (
        "import warnings\n"
        "from gcs_estimator.runtime.filter_worker import name_warnings\n"
        "name_warnings(3)\n"
        "warnings.warn('the gust level overflowed', RuntimeWarning)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True
    )
    first = done.stderr.splitlines()[0]
    assert first.startswith("filter worker 3: ")
    assert first.endswith("RuntimeWarning: the gust level overflowed")
