"""The structure check's threads (docs/decisions/0070): a batch's task replays in its one
thread, each of `replay --each`'s replays in its share of the cores; the check's figures
are the same however many threads ran it."""

from __future__ import annotations

import os
import threading
from pathlib import Path

import numpy as np
import pytest

from gcs_estimator.cli import build_parser, main
from gcs_estimator.config import load_config
from gcs_estimator.runtime.batch import child_command
from gcs_estimator.runtime.session import RecordingSource, Session
from gcs_estimator.uncertainty import weighting
from sim.truth import simulate


@pytest.fixture(scope="module")
def run() -> Session:
    """A short calm flight, run with its history kept."""
    config = load_config("noc_uav", ["simulation.manoeuvre.duration_s=12"])
    fl = simulate(config, seed=2)
    session = Session(config)
    session.run(RecordingSource(fl.t_s, fl.inputs, fl.measurements))
    return session


def _check(
    session: Session, monkeypatch: pytest.MonkeyPatch
) -> tuple[weighting.StructureCheck, set[int]]:
    """The check of the run's vehicle, and the threads its replays ran in."""
    threads: set[int] = set()
    final = weighting._final

    def counted(*args: object) -> weighting.Final:
        threads.add(threading.get_ident())
        return final(*args)  # type: ignore[arg-type]

    monkeypatch.setattr(weighting, "_final", counted)
    est = session.estimators[RecordingSource.SYSTEM_ID]
    return weighting.structure_check(est, *est.frame_history.arrays()), threads


def test_one_thread_gives_the_check_the_threads_would(
    run: Session, monkeypatch: pytest.MonkeyPatch
) -> None:
    with weighting.replay_threads(1):
        assert weighting.check_threads() == 1
        alone, used = _check(run, monkeypatch)
    assert used == {threading.get_ident()}  # every replay in the caller's thread
    with weighting.replay_threads(2):
        shared, used_two = _check(run, monkeypatch)
    assert len(used_two) == 2 and threading.get_ident() not in used_two
    assert not alone.skipped and alone.channels == shared.channels
    for kind, sigma in alone.sigma.items():
        np.testing.assert_array_equal(sigma, shared.sigma[kind])
        np.testing.assert_array_equal(alone.moves[kind], shared.moves[kind])
    assert alone.found == shared.found


def test_the_threads_come_from_the_block_then_the_process_then_the_cores() -> None:
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:
        cores = os.cpu_count() or 1
    assert weighting.check_threads() == cores
    weighting.set_process_threads(3)
    try:
        assert weighting.check_threads() == 3
        with weighting.replay_threads(1):
            assert weighting.check_threads() == 1
        assert weighting.check_threads() == 3
    finally:
        weighting._PROCESS_THREADS.clear()
    assert weighting.check_threads() == cores


def test_each_replay_of_a_batch_gets_its_share_of_the_cores(tmp_path: Path) -> None:
    args = build_parser().parse_args(["replay", "--each", "a.tlog", "b.tlog"])
    cores = os.cpu_count() or 1
    for width in (1, 2, cores, cores + 3):
        cmd = child_command(args, Path("a.tlog"), tmp_path / "a", width)
        assert int(cmd[cmd.index("--check-threads") + 1]) == max(1, cores // width)
    given = build_parser().parse_args(["replay", "--each", "a.tlog", "--check-threads", "5"])
    cmd = child_command(given, Path("a.tlog"), tmp_path / "a", 4)
    assert cmd[cmd.index("--check-threads") + 1] == "5"


def test_no_threads_is_refused_naming_the_option(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as stopped:
        main(["replay", "missing.tlog", "--check-threads", "0"])
    assert stopped.value.code == 2
    assert "--check-threads: 0: at least 1" in capsys.readouterr().err
