"""The end of a run (outputs.sinks.RunEnd: the whole-record fit, the held-out check, the
advice, the table and the JSON) on the paths that do not end in one process: `listen
--filter-workers` (real simulator process, real UDP on loopback, real worker processes)
and `replay --each` (real .tlog files, a replay process per file). Each vehicle ends as
a single replay's does."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from gcs_estimator.cli import build_parser, main
from gcs_estimator.outputs.checks import Checks
from gcs_estimator.runtime.batch import child_command
from sim.cli import command as vehicle_command
from tests.telemetry.station import bound_port, start_listen
from tests.test_batch import _tlog

ROOT = Path(__file__).resolve().parent.parent
SHORT = ["simulation.manoeuvre.duration_s=12"]
QUICK = ("--set", "filter.structure_check=off", "--view", "off")
HELD = "2:6"
"""The held-out window: seconds 2 to 6 of each 12 s flight."""


def _gcs(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "gcs_estimator", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=900,
    )


def _results(folder: Path, sid: int = 1) -> dict[str, Any]:
    out: dict[str, Any] = json.loads((folder / f"results_sys{sid}.json").read_text())
    return out


def _ending(result: dict[str, Any]) -> tuple[Any, Any]:
    """What the end of the run added to a vehicle's JSON: the held-out check, the advice."""
    return result["holdout"], result["advice"]


def test_listen_with_filter_workers_ends_each_vehicle_as_a_single_replay(tmp_path: Path) -> None:
    """Two simulated vehicles -> UDP -> `listen --filter-workers 2 --validate 2:6`: each
    vehicle's table and JSON have its held-out check and what to fly next, made in its
    worker; the recording replayed in one process with the same workers' path gives the
    same, and a single replay of it (one process, no workers) the same advice."""
    live = tmp_path / "live"
    station, line = start_listen(
        "udpin:127.0.0.1:0", "--filter-workers", "2", "--idle-exit", "1.5",
        "--validate", HELD, "--out", str(live), *QUICK,
    )  # fmt: skip
    flown = subprocess.run(
        vehicle_command(ROOT / "configs/noc_uav.toml", f"127.0.0.1:{bound_port(line)}", 4.0,
                        SHORT, vehicles=2),
        cwd=ROOT, capture_output=True, text=True, timeout=900,
    )  # fmt: skip
    assert flown.returncode == 0, flown.stderr
    out, err = station.communicate(timeout=900)
    assert station.returncode == 0, err
    for sid in (1, 2):
        holdout, advice = _ending(_results(live, sid))
        assert holdout is not None and holdout["segment"] == "the window 2 s to 6 s of the record"
        assert holdout["in_sample"]  # the workers' filters step every frame
        assert advice is not None
    # The tables on stdout say so too, once per vehicle.
    assert out.count("held-out check on the window 2 s to 6 s") == 2, out
    assert out.count("what to fly next") == 2, out

    # One process, no --validate: the same advice for the same estimates.
    tlog = str(live / "telemetry.tlog")
    alone = tmp_path / "alone"
    workers = tmp_path / "workers"
    # Both replays in this process (decision 0066): the station's run was its own.
    assert main(["replay", tlog, "--config", "noc_uav", "--out", str(alone), *QUICK]) == 0
    assert main(["replay", tlog, "--config", "noc_uav", "--filter-workers", "2",
                 "--out", str(workers), *QUICK]) == 0  # fmt: skip
    for sid in (1, 2):
        one, two = _results(alone, sid), _results(workers, sid)
        assert two["holdout"] is None and one["holdout"] is None
        assert two["advice"] == one["advice"]


@pytest.fixture(scope="module")
def flights(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    d = tmp_path_factory.mktemp("flights")
    return [_tlog(d / "a.tlog", 3), _tlog(d / "b.tlog", 4)]


def test_replay_each_ends_every_file_as_its_single_replay(
    tmp_path: Path, flights: list[Path], capsys: pytest.CaptureFixture[str]
) -> None:
    """`replay --each --validate 2:6`: every file's results have the held-out check (out
    of sample: the filters left the window out, its frames were kept aside) and the
    advice its single replay with the same options gives, value for value, and its table
    in its folder's log says what to fly next as the single replay's does."""
    out = tmp_path / "each"
    done = _gcs("replay", "--each", "--jobs", "2", *map(str, flights), "--config", "noc_uav",
                "--validate", HELD, "--out", str(out), *QUICK)  # fmt: skip
    assert done.returncode == 0, done.stderr
    files = json.loads((out / "replays.json").read_text())["files"]
    for f, path in zip(files, flights, strict=True):
        holdout, advice = _ending(f["vehicles"][0])
        assert holdout is not None and not holdout["in_sample"], f["vehicles"][0]["holdout"]
        assert all(c["samples"] > 150 for c in holdout["channels"].values())  # 4 s at 50 Hz
        assert advice is not None
        alone = tmp_path / f"alone_{path.stem}"
        # The single replay in this process (decision 0066): the batch's are their own.
        capsys.readouterr()
        assert main(["replay", str(path), "--config", "noc_uav", "--validate", HELD,
                     "--out", str(alone), *QUICK]) == 0  # fmt: skip
        assert _ending(f["vehicles"][0]) == _ending(_results(alone))
        log = (Path(f["folder"]) / "replay.log").read_text()
        assert "what to fly next" in log and "what to fly next" in capsys.readouterr().out


def test_offline_checks_a_window_its_segments_left_out(tmp_path: Path) -> None:
    """`offline hfb320 --validate 10:20`: the segments leave the window out of the
    filters; its frames, kept aside as the recording is read, are what the check flies."""
    out = tmp_path / "run"
    done = _gcs("offline", "hfb320", "--validate", "10:20", "--out", str(out), *QUICK)
    assert done.returncode == 0, done.stderr
    holdout = _results(out)["holdout"]
    assert holdout is not None and not holdout["in_sample"]
    assert holdout["segment"] == "the window 10 s to 20 s of the record"
    assert all(c["samples"] > 0 for c in holdout["channels"].values())


def test_each_files_replay_is_given_the_checks_options(tmp_path: Path) -> None:
    args = build_parser().parse_args(
        ["replay", "--each", "a.tlog", "--validate", HELD, "--no-advice"]
    )
    cmd = child_command(args, Path("a.tlog"), tmp_path / "a")
    assert cmd[cmd.index("--validate") + 1] == HELD
    assert "--no-advice" in cmd


def test_the_frames_kept_aside_are_the_held_out_window_of_the_first_flight() -> None:
    """Two flights of one aircraft, 4 s each at 10 Hz: the held-out window 1 s to 2 s is
    the first flight's (seconds after its first frame), every frame of it, in order."""
    checks = Checks(window=(1.0, 2.0))
    for start in (0.0, 100.0):
        for k in range(40):
            t_rel = k / 10
            checks.hold(1, t_rel, start + t_rel, np.full(2, float(k)), np.zeros(7))
    t, u, _y = checks.held[1].arrays()
    assert list(t) == [k / 10 for k in range(10, 21)]
    assert list(u[:, 0]) == list(range(10, 21))
