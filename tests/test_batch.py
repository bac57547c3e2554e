"""`replay --each`: several recorded flights in parallel processes, each file's results
the same as its own replay's, merged into one summary; a bad file fails alone; a stop
starts no more files."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from gcs_estimator.cli import build_parser, main, tlog_paths
from gcs_estimator.config import load_config
from gcs_estimator.ingest.flightdata import Recording
from gcs_estimator.runtime.batch import child_command
from sim.truth import simulate
from sim.vehicle import SimulatedVehicle

NOC = ("--config", "noc_uav")
"""A simulated NOC UAV's log names its airframe file (a real log without one is refused)."""

ROOT = Path(__file__).resolve().parent.parent
SHORT = ["simulation.manoeuvre.duration_s=12"]


def _tlog(path: Path, seed: int) -> Path:
    config = load_config(ROOT / "configs/noc_uav.toml", SHORT)
    fl = simulate(config, seed=seed)
    rec = Recording(fl.t_s, fl.inputs, fl.measurements, "throttle")
    SimulatedVehicle(rec, config.link, ("127.0.0.1", 9), speed=0.0, tlog=path).run()
    return path


def _gcs(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "gcs_estimator", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )


def _estimates(results: dict) -> dict[str, float]:  # type: ignore[type-arg]
    return {
        f"{kind} {name}": c["estimate"]
        for kind, f in results["filters"].items()
        for name, c in f["estimates"].items()
    }


@pytest.fixture(scope="module")
def flights(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    d = tmp_path_factory.mktemp("flights")
    # Two files of the same name in different folders: each gets a folder of its own.
    (d / "a").mkdir()
    (d / "b").mkdir()
    return [_tlog(d / "a" / "flight.tlog", 3), _tlog(d / "b" / "flight.tlog", 4)]


def test_each_file_is_replayed_on_its_own_the_results_merged_and_a_bad_file_fails_alone(
    tmp_path: Path, flights: list[Path]
) -> None:
    """One batch of two flights and a file of junk (decision 0066: one batch run serves
    what two did): each flight's results are its replay's alone, the junk's replay fails
    alone and says why."""
    junk = tmp_path / "junk.tlog"
    junk.write_bytes(os.urandom(4000))
    out = tmp_path / "batch"
    done = _gcs("replay", "--each", "--jobs", "2", *map(str, flights), str(junk), *NOC,
                "--out", str(out), "--view", "off")  # fmt: skip
    assert done.returncode != 0
    assert "replaying 3 files as separate flights, 2 at a time" in done.stderr
    assert f"started {flights[1]} -> {out / 'flight_2'}" in done.stderr
    summary = json.loads((out / "replays.json").read_text())
    *files, bad = summary["files"]
    assert [f["file"] for f in files] == [str(p) for p in flights]
    assert [Path(f["folder"]).name for f in files] == ["flight", "flight_2"]
    assert all(f["exit_status"] == 0 and len(f["vehicles"]) == 1 for f in files)
    assert bad["file"] == str(junk) and bad["exit_status"] == done.returncode
    assert bad["vehicles"] == []
    # The failing replay's own message, from its log, in the batch's output.
    assert f"{junk}: exit {done.returncode}" in done.stderr
    assert "no usable frame" in done.stderr or "error:" in done.stderr
    # Each file's results are exactly those of a replay of that file alone (here, in
    # this process: the batch's replays are processes of their own).
    for f, path in zip(files, flights, strict=True):
        alone = tmp_path / f"alone_{Path(f['folder']).name}"
        assert main(["replay", str(path), *NOC, "--out", str(alone), "--view", "off"]) == 0
        own = json.loads((alone / "results_sys1.json").read_text())
        assert _estimates(f["vehicles"][0]) == _estimates(own)
        assert (Path(f["folder"]) / "results_sys1_history.parquet").is_file()
    # The two flights differ (other noise seeds): the merge kept them apart.
    assert _estimates(files[0]["vehicles"][0]) != _estimates(files[1]["vehicles"][0])
    table = (out / "replays.md").read_text()
    assert table.count("| flight.tlog | 0 |") == 2
    assert (
        "| file | exit | s | vehicle | frames | CLa | Cma | Cmq | Cmde | warnings |" in done.stdout
    )


def test_each_files_replay_gets_the_batchs_options(tmp_path: Path) -> None:
    """What a file's replay is given: the batch's options (filter workers too), its own
    folder."""
    argv = ["replay", "--each", "a.tlog", "--filter-workers", "2", "--set", "filter.x=1"]
    args = build_parser().parse_args([*argv, "--refine", "output-error", "--view", "off"])
    cmd = child_command(args, Path("a.tlog"), tmp_path / "a")
    assert cmd[cmd.index("--filter-workers") + 1] == "2"
    assert cmd[cmd.index("--set") + 1] == "filter.x=1"
    assert cmd[cmd.index("--refine") + 1] == "output-error"
    assert cmd[cmd.index("--out") + 1] == str(tmp_path / "a")
    assert "--each" not in cmd


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (["--each", "--view", "spawn"], "the view can only be save or off"),
        (["--each", "--rrd", "x.rrd"], "--rrd: not with --each"),
        (["--each", "--jobs", "0"], "--jobs 0: must be at least 1"),
        (["--jobs", "2"], "--jobs: only with --each"),
        (["--each", "--speed", "2"], "--speed: not with --each"),
    ],
)
def test_options_a_batch_cannot_pass_on_are_refused(
    tmp_path: Path,
    flights: list[Path],
    options: list[str],
    message: str,
    capsys: pytest.CaptureFixture[str],
) -> None:
    status = main(["replay", *map(str, flights), "--out", str(tmp_path / "o"), *options])
    assert status == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "o").exists()  # refused before anything was written


def test_a_stop_starts_no_more_files_and_keeps_what_ended(
    tmp_path: Path, flights: list[Path]
) -> None:
    out = tmp_path / "batch"
    three = [*map(str, flights), str(flights[0])]
    proc = subprocess.Popen(
        [sys.executable, "-m", "gcs_estimator", "replay", "--each", "--jobs", "1", *three,
         *NOC, "--out", str(out), "--view", "off"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert proc.stderr is not None
    for line in proc.stderr:
        if line.startswith("[1/3]"):  # the first file done
            proc.send_signal(signal.SIGINT)
            break
    stdout, _ = proc.communicate(timeout=120)
    summary = json.loads((out / "replays.json").read_text())
    first, second, third = summary["files"]
    assert first["exit_status"] == 0 and len(first["vehicles"]) == 1
    # The second was started before the stop came, or not: either way the third never.
    assert third["exit_status"] is None and third["vehicles"] == []
    assert "| flight.tlog | not run |" in stdout
    # A replay stopped before its first frame estimated nothing, and says so in its status.
    assert proc.returncode == (second["exit_status"] or 0)


def test_a_folder_stands_for_its_tlog_files(
    tmp_path: Path, flights: list[Path], capsys: pytest.CaptureFixture[str]
) -> None:
    logs = tmp_path / "logs"
    logs.mkdir()
    for name, src in (("b.tlog", flights[1]), ("a.tlog", flights[0])):
        (logs / name).write_bytes(src.read_bytes())
    (logs / "notes.txt").write_text("not a log")
    (logs / "old.tlog").mkdir()  # a folder named like a log is not one
    assert tlog_paths([str(logs), str(flights[0])]) == [
        str(logs / "a.tlog"),
        str(logs / "b.tlog"),
        str(flights[0]),
    ]
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["replay", "--each", str(empty), "--out", str(tmp_path / "o")]) == 2
    assert f"{empty}: a folder with no .tlog file in it" in capsys.readouterr().err
