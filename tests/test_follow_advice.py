"""`--follow-advice`: a recorded flight run as given, then as its warnings advise, until
they advise nothing new (cli.follow_advice)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gcs_estimator import cli
from gcs_estimator.config import load_config
from gcs_estimator.ingest.flightdata import Recording
from gcs_estimator.outputs.diagnosis import CHANNEL_NIS_LIMIT
from sim.truth import simulate
from sim.vehicle import SimulatedVehicle

MISSED_GUSTS = [
    'simulation.turbulence.preset="light"',
    "simulation.manoeuvre.duration_s=20",
]
"""Light turbulence flown; the replays tell the filters the air is calm (no adaptive
level): a model that misses the gusts, as tests/test_refine.py's advised case."""


@pytest.fixture(scope="module")
def gusty_tlog(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The simulated vehicle's real .tlog of 20 s in light turbulence."""
    config = load_config("noc_uav", MISSED_GUSTS)
    flight = simulate(config, seed=1)
    tlog = tmp_path_factory.mktemp("gusts") / "flight.tlog"
    rec = Recording(flight.t_s, flight.inputs, flight.measurements, "throttle")
    SimulatedVehicle(rec, config.link, ("127.0.0.1", 9), speed=0.0, tlog=tlog).run()
    return tlog


def _replay(tlog: Path, out: Path, *more: str) -> list[str]:
    return [
        "replay",
        str(tlog),
        "--config",
        "noc_uav",
        "--set",
        "filter.turbulence.adaptive=false",
        "--set",
        "filter.structure_check=off",  # each round sooner; the advice does not need it
        "--no-advice",
        "--view",
        "off",
        "--out",
        str(out),
        *more,
    ]


def test_a_replay_follows_its_advice_until_nothing_new_is_advised(
    gusty_tlog: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Round 1 as given: the innovations are far larger than predicted and the warnings ask
    for a filter-error fit. Round 2 runs it, and its warnings advise the process noise it
    finds. Round 3 runs with that noise: every channel's innovations are as large as the
    filters predict, nothing new is advised, and the rounds stop. advice.json says what
    each round applied and read, each from that round's own results. (That the
    coefficients then lie within their sigma of the truth, the structure check's widening
    included, is tests/test_refine.py's, on the same flight; here the check is off.)"""
    tlog = gusty_tlog
    out = tmp_path / "advised"
    assert cli.main(_replay(tlog, out, "--follow-advice")) == 0
    account = json.loads((out / cli.ADVICE_FILE).read_text())
    rounds = account["rounds"]
    assert [r["folder"] for r in rounds] == ["round_1", "round_2", "round_3"]
    assert account["last"] == "round_3"
    results = [json.loads((out / r["folder"] / "results_sys1.json").read_text()) for r in rounds]
    for r, data in zip(rounds, results, strict=True):
        assert r["advised"] == data["diagnostics"]["advised_settings"]
        assert r["advised_refine"] == data["diagnostics"]["advised_refine"]
        for kind, f in data["filters"].items():
            assert r["nis"][kind]["mean_nis"] == f["mean_nis"]
    first, second, third = rounds
    assert first["applied"] == {} and first["refine"] is None
    assert first["advised_refine"] == "filter-error"
    assert (
        max(
            max(v for v in f["innovation_mean_square"].values() if v is not None)
            for f in results[0]["filters"].values()
        )
        > 10 * CHANNEL_NIS_LIMIT
    )
    assert second["refine"] == "filter-error" and results[1]["refined"]["method"] == "filter error"
    noise = {k: v for k, v in second["advised"].items() if k.startswith("filter.process_noise.")}
    assert "filter.process_noise.alpha" in noise
    assert third["refine"] is None and results[2]["refined"] is None
    assert third["applied"] == {**first["advised"], **second["advised"]}
    assert third["advised"] == {} and third["advised_refine"] is None
    assert third["stopped"] == "nothing new advised"
    # The last round ran with what was advised: its command line and its config say so.
    line = results[2]["run"]["command_line"]
    for key, value in noise.items():
        assert f"{key}={value:g}" in line
        assert results[2]["config"]["filter"]["process_noise"][key.rsplit(".", 1)[1]] == value
    for kind, f in results[2]["filters"].items():
        nis = np.array([v for v in f["innovation_mean_square"].values() if v is not None])
        assert np.all((nis > 1 / CHANNEL_NIS_LIMIT) & (nis < CHANNEL_NIS_LIMIT)), (kind, nis)
    err = capsys.readouterr().err
    assert f"the run to read: {out / 'round_3'}" in err

    # The folder holds a run's outputs now: refused again unless --force.
    assert cli.main(_replay(tlog, out, "--follow-advice")) == 2
    assert "--out" in capsys.readouterr().err


def test_follow_advice_is_refused_with_each(
    gusty_tlog: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """--each replays every file as a flight of its own: the advice is each one's."""
    tlog = gusty_tlog
    assert cli.main(_replay(tlog, tmp_path / "each", "--each", "--follow-advice")) == 2
    assert "--follow-advice with --each" in capsys.readouterr().err
