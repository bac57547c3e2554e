"""Several flights of one airframe estimated together, segments in a run, and --window on
the filters (runtime/flights.py, estimation/segments.py; decision 0050)."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest

from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.estimation.segments import Window
from gcs_estimator.ingest.flightdata import Recording
from gcs_estimator.runtime.flights import limits_of, source_of
from gcs_estimator.runtime.session import Session
from gcs_estimator.uncertainty.result import VehicleResult

SETTINGS = ["filter.structure_check=off"]


def _flight(seconds: float, seed: int) -> tuple[Recording, AircraftConfig]:
    from sim.truth import simulate

    config = load_config("noc_uav", [*SETTINGS, f"simulation.manoeuvre.duration_s={seconds}"])
    fl = simulate(config, seed=seed)
    return Recording(fl.t_s, fl.inputs, fl.measurements, "throttle"), config


def _part(rec: Recording, a: int, b: int) -> Recording:
    return Recording(rec.t_s[a:b], rec.inputs[a:b], rec.measurements[a:b], rec.power)


def _run(
    config: AircraftConfig, recs: list[Recording], names: list[str], windows: Sequence[Window] = ()
) -> VehicleResult:
    source = source_of(recs, names, limits_of(config, windows))
    session = Session(config)
    return session.run(source)[1]


@pytest.fixture(scope="module")
def long_flight() -> tuple[Recording, AircraftConfig]:
    return _flight(60.0, seed=3)


def test_a_flight_split_in_two_estimated_together(
    long_flight: tuple[Recording, AircraftConfig],
) -> None:
    """Its two halves together: each coefficient's sigma at most that of either half alone,
    the estimate within the sigmas of the single long flight's; each flight's part said."""
    rec, config = long_flight
    half = len(rec) // 2
    first, second = _part(rec, 0, half), _part(rec, half, len(rec))
    both = _run(config, [first, second], ["a", "b"]).result.filters["IEKF"]
    whole = _run(config, [rec], ["whole"]).result.filters["IEKF"]
    alone = [
        _run(config, [r], [n]).result.filters["IEKF"] for r, n in ((first, "a"), (second, "b"))
    ]
    for one in alone:
        assert np.all(both.sigma <= 1.05 * one.sigma)
    z = (both.coefficients - whole.coefficients) / np.hypot(both.sigma, whole.sigma)
    assert np.all(np.abs(z) < 3.0), z
    result = _run(config, [first, second], ["a", "b"]).result
    assert [p["flight"] for p in result.flights] == ["a", "b"]
    assert sum(p["frames"] for p in result.flights) == result.frames == len(rec)
    after = np.array(list(result.flights[-1]["filters"]["IEKF"]["sigma"].values()))
    np.testing.assert_allclose(after, result.filters["IEKF"].sigma, rtol=1e-9)
    removed = result.flights[0]["filters"]["IEKF"]["variance_removed"]
    assert all(0.0 < v <= 1.0 for v in removed.values())


def test_windows_on_the_filters_leave_the_rest_out(
    long_flight: tuple[Recording, AircraftConfig],
) -> None:
    """--window 5:20 --window 35:50: only those frames are stepped, the flight states
    afresh at the second; the frames outside counted."""
    from gcs_estimator.estimation.segments import parse_windows

    rec, config = long_flight
    v = _run(config, [rec], ["f"], parse_windows(["5:20", "35:50"]))
    seg = v.result.segments
    assert seg is not None and len(seg["segments"]) == 2
    rel = rec.t_s - rec.t_s[0]
    inside = int(np.sum(((rel >= 5) & (rel <= 20)) | ((rel >= 35) & (rel <= 50))))
    assert v.result.frames == seg["frames_used"] == inside
    assert seg["left_out_frames"]["window"] == len(rec) - inside
    assert v.result.gaps == 0  # a segment's start is no clock gap
    track = v.result.filters["IEKF"].track
    assert track is not None and float(track.t[0] - rec.t_s[0]) >= 5.0


def test_offline_with_two_logs_and_a_refused_mix(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`offline A.bin B.bin`: one estimate from both flights, each flight's part in the JSON
    and the table; a DataFlash log and a PX4 log together are refused naming both."""
    from gcs_estimator.cli import main
    from sim.cli import main as sim_main

    short = ["--set", "simulation.manoeuvre.duration_s=20", "--set", SETTINGS[0]]
    for name, seed, fmt in (("a", 1, "--bin"), ("b", 2, "--bin"), ("c", 3, "--ulg")):
        suffix = ".bin" if fmt == "--bin" else ".ulg"
        assert sim_main([*short, "--seed", str(seed), fmt, str(tmp_path / f"{name}{suffix}")]) == 0
    out = tmp_path / "out"
    argv = ["offline", str(tmp_path / "a.bin"), str(tmp_path / "b.bin"), "--config", "noc_uav"]
    assert main([*argv, *short, "--view", "off", "--out", str(out)]) == 0
    data = json.loads((out / "results_sys1.json").read_text())
    flights = data["diagnostics"]["flights"]
    assert [f["flight"] for f in flights] == ["a.bin", "b.bin"]
    assert len(data["diagnostics"]["segments"]["segments"]) >= 2
    assert "flight b.bin" in (out / "results_sys1.md").read_text()
    mixed = ["offline", str(tmp_path / "a.bin"), str(tmp_path / "c.ulg"), "--config", "noc_uav"]
    capsys.readouterr()
    assert main([*mixed, *short, "--view", "off", "--out", str(tmp_path / "mixed")]) == 2
    err = capsys.readouterr().err
    assert "different aircraft flew (a.bin: ArduPlane fixed-wing; c.ulg: PX4 " in err


def test_refine_fits_two_flights_jointly() -> None:
    """The whole-record fit over two flights, each flown from its own first frame: it
    converges, each flight's flight states its own (the second piece's start is fitted,
    not the first flight's end), its sigma no larger than either flight's alone, and the
    truth within its sigmas. 15 s each: the multisteps and the first pulse, which the
    25 s flights added only a pulse's tail to (decision 0062)."""
    from gcs_estimator.refine import refine_run

    (a, config), (b, _) = _flight(15.0, seed=5), _flight(15.0, seed=6)
    joint = refine_run(_run(config, [a, b], ["a", "b"]), "output-error", threads=1)
    alone = [
        refine_run(_run(config, [r], [n]), "output-error", threads=1)
        for r, n in ((a, "a"), (b, "b"))
    ]
    assert joint.converged and joint.frames == len(a) + len(b)
    for one in alone:
        assert np.all(joint.sigma <= 1.05 * one.sigma), (joint.sigma, one.sigma)
    truth = np.array(config.truth)
    z = (joint.coefficients - truth) / joint.sigma
    assert np.all(np.abs(z) < 3.0), z


def test_replay_flights_takes_each_tlog_as_a_flight(tmp_path: Path) -> None:
    """`replay --flights A.tlog B.tlog`: each tlog a flight of its own (its flight states
    afresh), one estimate from both, each flight's part in the JSON."""
    from gcs_estimator.cli import main
    from sim.cli import main as sim_main

    short = ["--set", "simulation.manoeuvre.duration_s=20", "--set", SETTINGS[0]]
    for name, seed in (("a", 1), ("b", 2)):
        argv = [*short, "--speed", "0", "--seed", str(seed), "--tlog", str(tmp_path / name)]
        assert sim_main(argv) == 0
    out = tmp_path / "out"
    logs = [str(tmp_path / "a_1.tlog"), str(tmp_path / "b_1.tlog")]
    argv = ["replay", *logs, "--flights", "--config", "noc_uav", *short, "--view", "off"]
    assert main([*argv, "--out", str(out)]) == 0
    data = json.loads((out / "results_sys1.json").read_text())
    flights = data["diagnostics"]["flights"]
    assert [f["flight"] for f in flights] == ["a_1.tlog", "b_1.tlog"]
    assert data["diagnostics"]["frames"] == sum(f["frames"] for f in flights)
    assert len(data["diagnostics"]["segments"]["segments"]) == 2


def test_live_gate_skips_counts_and_starts_afresh() -> None:
    """A session with the live gate: frames whose airspeed leaves the range are skipped and
    counted, the next one within starts the flight states afresh (no clock gap, the
    restarts kept); the final pass replayed from the history (as the structure check
    does) ends exactly where the run did."""
    from gcs_estimator.estimation.estimator import Estimator
    from gcs_estimator.runtime.session import RecordingSource

    rec, config = _flight(20.0, seed=4)
    y = rec.measurements.copy()
    slow = (rec.t_s - rec.t_s[0] > 8.0) & (rec.t_s - rec.t_s[0] < 11.0)
    y[slow, 0] = 5.0  # three seconds far below the trim airspeed
    session = Session(config, gate=limits_of(config))
    result = session.run(RecordingSource(rec.t_s, rec.inputs, y))[1].result
    seg = result.segments
    assert seg is not None and seg["left_out_frames"]["airspeed"] == int(slow.sum())
    assert result.frames == len(rec) - int(slow.sum()) and seg["segments_begun"] == 2
    assert len(result.fresh_frames) == 1 and result.gaps == 0
    assert result.restarts_done == len(config.filter.restart_times_s)
    est = session.estimators[1]
    again = Estimator(config, keep_history=False)
    again.replay_final_pass(est, *est.frame_history.arrays())
    for kind, lane in again.states.items():
        run = est.states[kind]
        assert lane is not None and run is not None
        np.testing.assert_array_equal(lane.x, run.x)
        np.testing.assert_array_equal(lane.P, run.P)
