"""Issue 51's end-to-end target on a short simulated NOC flight written as ArduPlane's
DataFlash .bin and PX4's .ulg (`gcs-sim --bin --ulg`): every channel a format carries
equals the native stream's (the simulator's own samples) within the format's
resolution; the .bin's estimates (it carries alpha: AOA) lie within 1 sigma of the
native stream's and within 3 sigma of truth; the .ulg (no alpha) says alpha is missing
and claims no coefficient that needs it as identified."""

from __future__ import annotations

import contextlib
import io
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from gcs_estimator.cli import main
from gcs_estimator.config import AircraftConfig, load_config, load_truths
from gcs_estimator.frames import Frame
from gcs_estimator.ingest.flightdata import Recording
from gcs_estimator.ingest.logs.reader import read_log
from gcs_estimator.ingest.telemetry.link import MavlinkLink
from gcs_estimator.ingest.telemetry.mavlink import read_tlog
from gcs_estimator.model.channels import Channel
from gcs_estimator.runtime.session import run_recording
from gcs_estimator.uncertainty.metrics import IDENTIFIED, NOT_IDENTIFIED, needs_alpha_level
from sim.cli import main as sim_main
from sim.formats import GRAVITY_MSS, truth_path
from sim.scenario import scenario_of
from sim.truth import Flight, simulate

FLIGHT_S = 50.0
"""Long enough for the standard manoeuvre's every coefficient but CDa to be told."""
SHORT = [f"simulation.manoeuvre.duration_s={FLIGHT_S:g}"]
HDOT = Channel.HDOT
CHANNELS = ("V", "alpha", "theta", "q", "qdot", "a_x", "a_z")
F32 = 2.0**-23
"""A float32's relative resolution (half a unit in the last place: 2^-24, with margin)."""
CENTIDEGREE = math.radians(0.005)
"""Half of ATT's int16 centidegree step [rad]."""
TEMP_C = 0.005 / 280.0
"""Half of ARSP.Temp's centidegree step over the air's ~285 K: the density's relative
resolution, so true airspeed's (EAS * sqrt(rho0/rho)) is half of it."""

# per format and channel: (relative, absolute) tolerance from the field's type
RESOLUTION: dict[str, dict[str, tuple[float, float]]] = {
    "bin": {
        "V": (TEMP_C / 2 + 4 * F32, 0.0),  # ARSP.Airspeed float32 EAS, density via Temp
        "alpha": (4 * F32, 1e-9),  # AOA.AOA float32 degrees
        "theta": (0.0, CENTIDEGREE + 1e-9),  # ATT.Pitch int16 centidegrees
        "q": (4 * F32, 1e-9),  # IMU.GyrY float32 rad/s
        "a_x": (4 * F32, 1e-7),  # IMU.AccX float32 m/s^2
        "a_z": (4 * F32, 1e-7),
        "elevator": (0.0, 1e-7),  # RCOU whole microseconds: the flown PWM itself
        "throttle": (0.0, 1e-9),
        "rho": (TEMP_C + 4 * F32, 0.0),  # BARO.Press float32, ARSP.Temp centidegrees
    },
    "ulg": {
        "V": (4 * F32, 0.0),  # airspeed_validated.true_airspeed_m_s float32
        "theta": (0.0, 4 * F32),  # vehicle_attitude.q float32
        "q": (4 * F32, 1e-9),  # vehicle_angular_velocity float32
        "qdot": (4 * F32, 1e-7),
        "a_x": (4 * F32, 1e-7),  # vehicle_acceleration float32
        "a_z": (4 * F32, 1e-7),
        "elevator": (0.0, 1e-7),  # actuator_servos float32 -1..1 times the travel
        "throttle": (0.0, 1e-7),  # actuator_motors float32 0..1
        # vehicle_air_data's pressure with the probe's temperature, logged once a second
        # (airspeed): interpolated across the second as the aircraft climbs, 5e-5
        "rho": (5e-5, 0.0),
    },
}


@pytest.fixture(scope="module")
def config() -> AircraftConfig:
    return load_config("noc_uav", SHORT)


@pytest.fixture(scope="module")
def native(config: AircraftConfig) -> Flight:
    """The flight gcs-sim writes (its scenario's seed): the native stream's samples."""
    return simulate(config, seed=scenario_of(config).seed)


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("agreement")
    files = {"bin": folder / "flight.bin", "ulg": folder / "flight.ulg"}
    argv = ["--speed", "0", "--set", SHORT[0], "--bin", str(files["bin"])]
    assert sim_main([*argv, "--ulg", str(files["ulg"])]) == 0
    return files


def _on_native(rec: Recording, flight: Flight) -> np.ndarray:
    """The native sample index of each frame (the log's clock starts at boot_s)."""
    t = rec.t_s - rec.t_s[0] + flight.t_s[0]
    idx = np.asarray(np.searchsorted(flight.t_s, t - 1e-6), dtype=int)
    assert np.allclose(flight.t_s[idx], t, atol=1e-6), "a frame between native samples"
    return idx


@pytest.mark.parametrize("fmt", ["bin", "ulg"])
def test_every_channel_equals_the_native_streams_within_the_formats_resolution(
    config: AircraftConfig, native: Flight, logs: dict[str, Path], fmt: str
) -> None:
    rec, _ = read_log(logs[fmt], config)
    idx = _on_native(rec, native)
    tol = RESOLUTION[fmt]
    carried = [c for c in CHANNELS if np.isfinite(rec.measurements[:, CHANNELS.index(c)]).any()]
    assert sorted(carried) == sorted(c for c in tol if c in CHANNELS), carried
    for c in carried:
        j = CHANNELS.index(c)
        got = rec.measurements[:, j]
        ok = np.isfinite(got)
        rtol, atol = tol[c]
        np.testing.assert_allclose(
            got[ok], native.measurements[idx[ok], j], rtol=rtol, atol=atol, err_msg=f"{fmt} {c}"
        )
    for k, c in enumerate(("elevator", "throttle")):
        rtol, atol = tol[c]
        np.testing.assert_allclose(
            rec.inputs[:, k], native.inputs[idx, k], rtol=rtol, atol=atol, err_msg=f"{fmt} {c}"
        )
    rtol, _ = tol["rho"]
    np.testing.assert_allclose(rec.inputs[:, 2], config.airframe.air_density_kgpm3, rtol=rtol)


def test_a_slower_channel_is_not_made_up_between_its_samples(
    config: AircraftConfig, logs: dict[str, Path]
) -> None:
    """ATT at 25 Hz on 50 Hz frames: a pitch angle on every other frame only (an
    interpolated one in between would be a made-up sample whose smoothness reads the
    sensor's noise five times too low)."""
    rec, _ = read_log(logs["bin"], config)
    theta = rec.measurements[:, CHANNELS.index("theta")]
    assert np.isfinite(theta[::2]).all() and not np.isfinite(theta[1::2]).any()


def _results(folder: Path) -> dict[str, Any]:
    out: dict[str, Any] = json.loads((folder / "results_sys1.json").read_text())
    return out


@pytest.fixture(scope="module")
def runs(
    tmp_path_factory: pytest.TempPathFactory, logs: dict[str, Path]
) -> dict[str, dict[str, Any]]:
    """The results of the native stream (`simulate`, the same seed) and of each log
    (`offline`)."""
    folder = tmp_path_factory.mktemp("runs")
    common = ["--config", "noc_uav", "--set", SHORT[0]]
    assert main(["simulate", *common, "--out", str(folder / "native")]) == 0
    stderr: dict[str, str] = {}
    for fmt, path in logs.items():
        with contextlib.redirect_stderr(io.StringIO()) as err:
            assert main(["offline", str(path), *common, "--out", str(folder / fmt)]) == 0
        stderr[fmt] = err.getvalue()
    out = {name: _results(folder / name) for name in ("native", *logs)}
    for fmt, text in stderr.items():
        out[fmt]["stderr"] = text
    return out


def _final(config: AircraftConfig, t: Any, u: Any, y: Any) -> dict[str, dict[str, Any]]:
    res = run_recording(config, t, u, y)
    return {
        kind: {c.name: (c.estimate, c.sigma) for c in res.summaries[kind].coefficients}
        for kind in ("IEKF", "EKF")
    }


def test_the_dataflash_log_estimates_as_the_native_stream_at_its_logging_rates(
    config: AircraftConfig, native: Flight, logs: dict[str, Path]
) -> None:
    """Reading the .bin adds nothing: its estimates are the native stream's with only the
    samples the .bin logs (AOA and ARSP at 10 Hz, ATT at 25 Hz, no pitch acceleration),
    to a hundredth of a sigma. What differs from the whole native stream is the
    information the autopilot's logging rates leave out."""
    rec, _ = read_log(logs["bin"], config)
    idx = _on_native(rec, native)
    thinned = np.where(np.isfinite(rec.measurements), native.measurements[idx], np.nan)
    # the log's climb rate (from the native stream's own V, theta and alpha) for both
    thinned[:, HDOT] = rec.measurements[:, HDOT]
    ours = _final(config, rec.t_s, rec.inputs, rec.measurements)
    theirs = _final(config, native.t_s[idx], native.inputs[idx], thinned)
    for kind, coefficients in ours.items():
        for name, (est, sigma) in coefficients.items():
            assert abs(est - theirs[kind][name][0]) <= 0.01 * sigma, (kind, name)
            assert sigma == pytest.approx(theirs[kind][name][1], rel=0.01), (kind, name)


def test_the_dataflash_estimates_agree_with_the_native_stream_and_truth(
    runs: dict[str, dict[str, Any]], logs: dict[str, Path]
) -> None:
    """Every coefficient within 3 sigma of truth, and within 1 sigma of the native
    stream's estimate but Cm0: the native stream's pitch acceleration halves Cm0's sigma
    (0.00067 against the .bin's 0.00127), and the two lie 1.1 of the .bin's sigma apart,
    1.3 of their difference's (the .bin's data are the native stream's, thinned: the
    previous test). Cm0 is held to the difference's 1.5 sigma or, where the sigma shown is
    the structure check's more than the covariance's (both runs then share it), to 1 sigma
    as the rest."""
    names = runs["native"]["coefficients"]
    truth = load_truths(truth_path(logs["bin"]), names)[1]
    for kind in ("IEKF", "EKF"):
        ours = runs["bin"]["filters"][kind]["estimates"]
        theirs = runs["native"]["filters"][kind]["estimates"]
        for i, name in enumerate(names):
            est, sigma = ours[name]["estimate"], ours[name]["sigma"]
            apart = abs(est - theirs[name]["estimate"])
            if name == "Cm0":
                difference_sigma = math.sqrt(max(sigma**2 - theirs[name]["sigma"] ** 2, 0.0))
                assert apart <= max(1.5 * difference_sigma, sigma), (kind, name, est, theirs[name])
            else:
                assert apart <= sigma, (kind, name, est, theirs[name])
            assert abs(est - truth[i]) <= 3 * sigma, (kind, name, est, truth[i], sigma)


def test_the_px4_log_says_alpha_is_missing_and_claims_nothing_that_needs_it(
    runs: dict[str, dict[str, Any]], logs: dict[str, Path]
) -> None:
    """PX4 logs no angle of attack: the run says so on stderr and in the results. Its
    vertical speed (vehicle_local_position.vz) is the climb rate that informs alpha in
    this calm air (decision 0049): what the run marks identified lies within 3 sigma of
    the truth, and no alpha-level coefficient is marked identified unless it does."""
    ulg = runs["ulg"]
    assert "no alpha in the log" in ulg["stderr"]
    assert any(w.startswith("no alpha in these data at all") for w in ulg["warnings"])
    names = ulg["coefficients"]
    truth = load_truths(truth_path(logs["ulg"]), names)[1]
    assert [n for n in names if needs_alpha_level(n)] == ["CD0", "CDa", "CL0", "CLa", "Cm0", "Cma"]
    for kind in ("IEKF", "EKF"):
        estimates = ulg["filters"][kind]["estimates"]
        for i, n in enumerate(names):
            e = estimates[n]
            if e["identifiability"] == IDENTIFIED:
                assert abs(e["estimate"] - truth[i]) <= 3 * e["sigma"], (kind, n, e, truth[i])
    # the .bin carries alpha: its marks are the sigmas' own
    assert "no alpha" not in runs["bin"]["stderr"]
    assert IDENTIFIED in {
        e["identifiability"] for e in runs["bin"]["filters"]["IEKF"]["estimates"].values()
    }


# ArduPlane's telemetry at the asked rates (gcs-sim --autopilot arduplane --asked --tlog):
# MAVLink's fields, as the station decodes them (decision 0038)
MILLI_G = GRAVITY_MSS * 1e-3
TLOG_RESOLUTION: dict[str, tuple[float, float]] = {
    "V": (TEMP_C / 2 + 4 * F32, 0.0),  # VFR_HUD.airspeed float32 EAS, SCALED_PRESSURE
    "alpha": (4 * F32, 1e-9),  # AOA_SSA.AOA float32 degrees
    "theta": (4 * F32, 1e-9),  # ATTITUDE.pitch float32 rad
    "q": (0.0, 1e-3 + 1e-9),  # RAW_IMU.ygyro int16 mrad/s, truncated: one unit
    "a_x": (0.0, MILLI_G + 1e-7),  # RAW_IMU.xacc int16 milli-g, truncated: one unit
    "a_z": (0.0, MILLI_G + 1e-7),
    "elevator": (0.0, 1e-7),  # SERVO_OUTPUT_RAW whole microseconds by SERVO2_* params
    "throttle": (0.0, 1e-9),
}


@pytest.fixture(scope="module")
def tlog(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("tlog")
    argv = ["--speed", "0", "--set", SHORT[0], "--autopilot", "arduplane", "--asked"]
    assert sim_main([*argv, "--tlog", str(folder / "flight")]) == 0
    return folder / "flight_1.tlog"


def _tlog_frames(config: AircraftConfig, path: Path) -> list[Frame]:
    """The frames the station assembles from the tlog, as `replay` does."""
    link = MavlinkLink(
        config.link, log=io.StringIO(), elevator_travel_deg=config.airframe.elevator_travel_deg
    )
    frames = [f for rec in read_tlog(path) for f in link.packet(rec.packet, rec.t_recv_us * 1e-6)]
    return [*frames, *link.flush()]


def test_the_arduplane_tlog_carries_the_native_stream_within_mavlinks_resolution(
    config: AircraftConfig, native: Flight, tlog: Path
) -> None:
    """Every channel ArduPlane's asked streams carry, on every frame, equals the native
    stream's within its field's resolution; the elevator through the SERVO2_* parameters
    the tlog holds (the station's [link] servo keys are not the vehicle's)."""
    frames = _tlog_frames(config, tlog)
    t = np.array([f.t_vehicle_s for f in frames])
    y = np.array([f.y for f in frames])
    u = np.array([f.inputs for f in frames])
    idx = np.asarray(np.searchsorted(native.t_s, t - t[0] + native.t_s[0] - 1e-6), dtype=int)
    assert len(frames) == len(native.t_s)
    assert np.allclose(native.t_s[idx], t - t[0] + native.t_s[0], atol=1e-6)
    for c, (rtol, atol) in TLOG_RESOLUTION.items():
        if c in CHANNELS:
            j = CHANNELS.index(c)
            got, want = y[:, j], native.measurements[idx, j]
        else:
            k = ("elevator", "throttle").index(c)
            got, want = u[:, k], native.inputs[idx, k]
        assert np.isfinite(got).all(), c
        np.testing.assert_allclose(got, want, rtol=rtol, atol=atol, err_msg=f"tlog {c}")
    assert not np.isfinite(y[:, CHANNELS.index("qdot")]).any()


def test_the_arduplane_tlog_estimates_as_the_native_stream_in_mavlinks_units(
    config: AircraftConfig, native: Flight, tlog: Path
) -> None:
    """Reading the tlog adds nothing: its estimates are the native stream's without the
    pitch acceleration, with q and the accelerations truncated to whole mrad/s and
    milli-g as ArduPilot's send_raw_imu does, to a hundredth of a sigma. What differs
    from the whole native stream is what MAVLink's integers leave out."""
    frames = _tlog_frames(config, tlog)
    t = np.array([f.t_vehicle_s for f in frames])
    y = np.array([f.y for f in frames])
    u = np.array([f.inputs for f in frames])
    idx = np.asarray(np.searchsorted(native.t_s, t - t[0] + native.t_s[0] - 1e-6), dtype=int)
    theirs_y = np.where(np.isfinite(y), native.measurements[idx], np.nan)
    # The climb rate the autopilot sends (sim.formats: from the native stream's own V,
    # theta and alpha) where the native stream has no climb-rate sensor: the same for both.
    theirs_y[:, HDOT] = np.where(np.isfinite(theirs_y[:, HDOT]), theirs_y[:, HDOT], y[:, HDOT])
    for c, unit in (("q", 1e-3), ("a_x", MILLI_G), ("a_z", MILLI_G)):
        j = CHANNELS.index(c)
        theirs_y[:, j] = np.trunc(theirs_y[:, j] / unit) * unit
    ours = _final(config, t, u, y)
    theirs = _final(config, native.t_s[idx], native.inputs[idx], theirs_y)
    for kind, coefficients in ours.items():
        for name, (est, sigma) in coefficients.items():
            assert abs(est - theirs[kind][name][0]) <= 0.01 * sigma, (kind, name)
            assert sigma == pytest.approx(theirs[kind][name][1], rel=0.01), (kind, name)


@pytest.fixture(scope="module")
def tlog_run(tmp_path_factory: pytest.TempPathFactory, tlog: Path) -> dict[str, Any]:
    """`replay` of the tlog with no --config: the truth file beside it names the airframe."""
    out = tmp_path_factory.mktemp("tlog_run")
    with contextlib.redirect_stderr(io.StringIO()) as err:
        assert main(["replay", str(tlog), "--view", "off", "--out", str(out)]) == 0
    results = _results(out)
    results["stderr"] = err.getvalue()
    return results


def test_the_arduplane_tlog_replays_as_the_native_stream(
    runs: dict[str, dict[str, Any]], tlog: Path, tlog_run: dict[str, Any]
) -> None:
    """lost 0; each channel from the message that carries it at the asked rate, the
    elevator by the vehicle's own parameters; every coefficient within 1 sigma of the
    native stream's estimate (the tlog carries everything at 50 Hz but the pitch
    acceleration) and within 3 sigma of truth; the drag coefficients within 3 sigma of
    truth only: RAW_IMU's whole milli-g widen their sigma 1.6 times and move them 1.2 to
    1.3 of it from the native stream's on this seed (the test above: the tlog's estimates
    are exactly the native stream's with its accelerations truncated to milli-g)."""
    link = tlog_run["link"]
    assert link["lost"] == 0 and link["corrupt"] == 0, link
    sources = link["sources"]["1"]
    assert sources["servos"].startswith("vehicle parameters: elevator on output 2"), sources
    expected = {
        "V": "VFR_HUD",
        "alpha": "AOA_SSA",
        "theta": "ATTITUDE",
        "q": "RAW_IMU",
        "a_x": "RAW_IMU",
        "a_z": "RAW_IMU",
        "elevator": "SERVO_OUTPUT_RAW",
    }
    for c, message in expected.items():
        assert sources["channels"][c]["message"] == message, (c, sources["channels"][c])
        assert sources["channels"][c]["rate_hz"] == pytest.approx(50.0, rel=0.02), c
    names = runs["native"]["coefficients"]
    truth = load_truths(truth_path(tlog), names)[1]
    for kind in ("IEKF", "EKF"):
        ours = tlog_run["filters"][kind]["estimates"]
        theirs = runs["native"]["filters"][kind]["estimates"]
        for i, name in enumerate(names):
            est, sigma = ours[name]["estimate"], ours[name]["sigma"]
            if not name.startswith("CD"):  # drag: RAW_IMU's milli-g (the test above)
                assert abs(est - theirs[name]["estimate"]) <= sigma, (kind, name, est)
            assert abs(est - truth[i]) <= 3 * sigma, (kind, name, est, truth[i], sigma)


def test_arduplanes_default_4_hz_streams_are_warned_about_and_claim_nothing_false(
    tmp_path: Path,
) -> None:
    """What MAVProxy asks by default (every stream at 4 Hz, no --asked): the run warns
    that the short-period channels come too slowly, and whatever it still marks
    identified lies within 3 sigma of truth."""
    argv = ["--speed", "0", "--set", SHORT[0], "--autopilot", "arduplane"]
    assert sim_main([*argv, "--tlog", str(tmp_path / "slow")]) == 0
    tlog = tmp_path / "slow_1.tlog"
    with contextlib.redirect_stdout(io.StringIO()) as out:
        assert main(["replay", str(tlog), "--view", "off", "--out", str(tmp_path / "out")]) == 0
    results = _results(tmp_path / "out")
    channels = results["link"]["sources"]["1"]["channels"]
    for c in ("alpha", "theta", "q", "elevator"):
        assert channels[c]["rate_hz"] == pytest.approx(4.0, rel=0.05), c
        assert "too slow to identify the short period" in channels[c]["warning"], c
    assert "warning: theta from ATTITUDE: 4.0 Hz is below 10 Hz" in out.getvalue()
    names = results["coefficients"]
    truth = load_truths(truth_path(tlog), names)[1]
    for kind in ("IEKF", "EKF"):
        for i, name in enumerate(names):
            e = results["filters"][kind]["estimates"][name]
            if e["identifiability"] == IDENTIFIED:
                assert abs(e["estimate"] - truth[i]) <= 3 * e["sigma"], (kind, name, e)
        # the pitch damping is the short period's: 4 Hz samples cannot tell it
        for name in ("CLq", "Cmq"):
            assert results["filters"][kind]["estimates"][name]["identifiability"] == NOT_IDENTIFIED


def test_servo_outputs_slower_than_the_sensors_are_known_between_their_samples(
    tmp_path: Path,
) -> None:
    """ArduPlane at the asked rates but SERVO_OUTPUT_RAW at a quarter of the sensors'
    (a station that leaves the servo stream slower than the IMU, as real links come):
    the frames between two servo samples take the elevator interpolated and their
    measurements, but for those around the multisteps' steps, whose instants the
    samples do not give (sync.STEP_CHANGES; decision 0084). Every coefficient ends
    within 3 sigma of truth, and none marked identified is beyond it."""
    argv = ["--speed", "0", "--set", SHORT[0], "--autopilot", "arduplane", "--asked"]
    argv += ["--msg-rate", "SERVO_OUTPUT_RAW=12.5"]
    assert sim_main([*argv, "--tlog", str(tmp_path / "servo")]) == 0
    tlog = tmp_path / "servo_1.tlog"
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["replay", str(tlog), "--view", "off", "--out", str(tmp_path / "out")]) == 0
    results = _results(tmp_path / "out")
    link = results["link"]
    channels = link["sources"]["1"]["channels"]
    assert channels["elevator"]["rate_hz"] == pytest.approx(12.5, rel=0.05)
    assert channels["q"]["rate_hz"] == pytest.approx(50.0, rel=0.02)
    vehicle = link["vehicles"]["1"]
    # Three in four frames lie between servo samples; a few around each step are guesses.
    assert 0 < vehicle["inputs_guessed"] < 0.05 * vehicle["frames"], vehicle
    assert vehicle["frames"] > 40 * FLIGHT_S, vehicle
    names = results["coefficients"]
    truth = load_truths(truth_path(tlog), names)[1]
    for kind in ("IEKF", "EKF"):
        summary = results["filters"][kind]
        assert summary["updates"] >= vehicle["frames"] - vehicle["inputs_guessed"], summary
        for i, name in enumerate(names):
            e = summary["estimates"][name]
            assert abs(e["estimate"] - truth[i]) <= 3 * e["sigma"], (kind, name, e, truth[i])
