"""Logs to Recordings: every channel a generated ArduPlane log carries comes back in SI
within the log's resolution; a log with no fixed-wing flight says so and exits 1."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from gcs_estimator.cli import main
from gcs_estimator.config import AircraftConfig
from gcs_estimator.ingest.flightdata import FlightDataError
from gcs_estimator.ingest.logs import detect
from gcs_estimator.ingest.logs.reader import NotAFlightError, read_log
from gcs_estimator.ingest.telemetry.mavlink import Codec, TlogWriter
from gcs_estimator.model.channels import LEGACY_OBS, Channel
from tests.logs.dataflash_files import TRAVEL_DEG, arduplane_log, flight
from tests.logs.ulog_files import px4_log

ULOG = Path(__file__).resolve().parent / "data" / "sample_log_small.ulg"
BOOT_S = 1.0
"""The generated logs' clock at the flight's t = 0."""


def _with_travel(
    config: AircraftConfig, travel: float = TRAVEL_DEG, hold: str = "linear"
) -> AircraftConfig:
    return replace(
        config,
        airframe=replace(config.airframe, elevator_travel_deg=travel),
        data=replace(config.data, input_hold=hold),
    )


@pytest.mark.parametrize("reversed_", [True, False])
def test_every_channel_comes_back_within_the_logs_resolution(
    tmp_path: Path, noc_config: AircraftConfig, reversed_: bool
) -> None:
    fl = flight(30.0)
    path = arduplane_log(tmp_path / "f.bin", fl, reversed_=reversed_)
    rec, account = read_log(path, _with_travel(noc_config))
    t = rec.t_s - BOOT_S

    def truth(x: np.ndarray) -> np.ndarray:
        return np.asarray(np.interp(t, fl.t_s, x))

    # frames: the first IMU's samples (50 Hz) while STAT says flying
    assert t[0] == pytest.approx(fl.takeoff_s) and t[-1] <= fl.landing_s
    assert np.allclose(np.diff(t), 0.02)
    v, alpha, theta, q, qdot, a_x, a_z = rec.measurements[:, :LEGACY_OBS].T
    np.testing.assert_allclose(theta, truth(fl.theta), atol=math.radians(0.006))
    np.testing.assert_allclose(q, truth(fl.q), atol=1e-6)  # the first IMU, not the second
    np.testing.assert_allclose(a_x, truth(fl.a_x), atol=1e-5)
    np.testing.assert_allclose(a_z, truth(fl.a_z), atol=1e-5)
    # ARSP and AOA at 25 Hz: on every other frame only, none made up between (0045)
    for slow in (v, alpha):
        assert np.isfinite(slow[::2]).all() and np.isnan(slow[1::2]).all()
    np.testing.assert_allclose(v[::2], truth(fl.tas)[::2], atol=2e-3)  # EAS back to TAS
    np.testing.assert_allclose(alpha[::2], truth(fl.alpha)[::2], atol=1e-4)
    assert np.isnan(qdot).all()
    de, throttle, rho = rec.inputs[:, :3].T  # then the turn inputs
    pwm_step = math.radians(TRAVEL_DEG) / 380.0  # one microsecond of the shorter half
    np.testing.assert_allclose(de, truth(fl.elevator_rad), atol=1.2 * pwm_step)
    np.testing.assert_allclose(throttle, truth(fl.throttle), atol=1.1e-3)
    np.testing.assert_allclose(rho, truth(fl.rho), rtol=1e-5)
    np.testing.assert_allclose(rec.aux["phi"], truth(fl.phi), atol=math.radians(0.006))
    assert rec.aux["vz"][::2] == pytest.approx(0.5)  # GPS and XKF2 at 25 Hz too
    # the climb rate channel: the vertical speed, up positive, where it was sampled
    h_dot = rec.measurements[:, Channel.HDOT]
    np.testing.assert_array_equal(h_dot, -rec.aux["vz"])
    assert rec.aux["wind_n"][::2] == pytest.approx(3.0)
    # GPS velocity from GPS.Spd 20 m/s along GCrs 90 deg, VZ; the heading from ATT.Yaw 90
    for name, value in (("vn", 0.0), ("ve", 20.0), ("vd", 0.5), ("psi", math.pi / 2)):
        np.testing.assert_allclose(rec.aux[name][::2], value, atol=1e-4, err_msg=name)
    assert rec.power == "throttle"
    assert "ArduPlane V4.5.0" in account and "airborne 20.0 s" in account
    assert "not a vane" in account and "q 50 Hz (IMU.GyrY)" in account
    assert any("no qdot" in n for n in rec.notes)
    held, _ = read_log(path, _with_travel(noc_config, hold="previous"))
    # RCOU comes with every other frame: held, the frame between repeats the one before
    np.testing.assert_array_equal(held.inputs[1::2, 0], held.inputs[0:-1:2, 0])
    np.testing.assert_allclose(held.inputs[::2, 0], de[::2], atol=1e-12)


def test_an_elevator_without_its_travel_names_the_key(
    tmp_path: Path, noc_config: AircraftConfig, capsys: pytest.CaptureFixture[str]
) -> None:
    path = arduplane_log(tmp_path / "f.bin", flight(20.0))
    with pytest.raises(FlightDataError, match=r"\[airframe\] elevator_travel_deg"):
        read_log(path, _with_travel(noc_config, 0.0))
    # (noc_uav sets its travel since 30 deg; an airframe file without it is meant here)
    unset = ["--set", "airframe.elevator_travel_deg=0"]
    args = ["offline", str(path), "--config", "noc_uav", *unset, "--out", str(tmp_path / "out")]
    assert main(args) == 2  # a setting the user must give: the config is not complete
    err = capsys.readouterr().err
    assert err.startswith("log f.bin: ArduPlane V4.5.0, fixed-wing")
    assert "set [airframe] elevator_travel_deg" in err


def test_a_vehicle_that_never_flew_exits_1_with_its_account(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = arduplane_log(tmp_path / "ground.bin", flight(12.0), flying=False)
    out = tmp_path / "out"
    assert main(["offline", str(path), "--config", "noc_uav", "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "log ground.bin: ArduPlane V4.5.0, fixed-wing, 12.0 s, airborne 0.0 s" in err
    assert "never flew" in err
    renamed = path.rename(tmp_path / "ground.dat")  # refine and replay know it by content
    for command in ("refine", "replay"):
        args = [command, str(renamed), "--config", "noc_uav", "--out", str(tmp_path / command)]
        assert main(args) == 1
        assert "log ground.dat: ArduPlane V4.5.0" in capsys.readouterr().err


def test_a_multirotor_is_no_fixed_wing_aircraft(tmp_path: Path, noc_config: AircraftConfig) -> None:
    path = arduplane_log(tmp_path / "copter.bin", flight(12.0), firmware="ArduCopter V4.5.0")
    with pytest.raises(NotAFlightError, match="multirotor") as err:
        read_log(path, _with_travel(noc_config))
    assert err.value.account.startswith("log copter.bin: ArduCopter V4.5.0, multirotor")


def test_a_quadplane_that_only_hovered(tmp_path: Path, noc_config: AircraftConfig) -> None:
    path = arduplane_log(tmp_path / "q.bin", flight(20.0), hover_mode=18)  # QHOVER
    with pytest.raises(NotAFlightError, match=r"hovered as a multirotor for 10\.0 s") as err:
        read_log(path, _with_travel(noc_config))
    assert "QuadPlane (VTOL)" in err.value.account and "(10.0 s hovering)" in err.value.account


def test_the_px4_vtol_that_only_hovered(
    noc_config: AircraftConfig, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(NotAFlightError, match="hovered as a multirotor") as err:
        read_log(ULOG, _with_travel(noc_config))
    account = err.value.account
    assert "PX4" in account and "VTOL (MAV_TYPE 22)" in account and "hovering" in account
    assert "theta 200 Hz (vehicle_attitude.q)" in account
    assert "q 279 Hz (vehicle_angular_velocity.xyz[1])" in account
    out = tmp_path / "out"
    assert main(["replay", str(ULOG), "--config", "noc_uav", "--out", str(out)]) == 1
    assert "hovered as a multirotor" in capsys.readouterr().err


def test_formats_are_told_by_content_not_by_name(tmp_path: Path, hfb_data_path: Path) -> None:
    named = tmp_path / "flight.txt"  # every file here has a name that says nothing
    arduplane_log(named, flight(2.0))
    assert detect.kind(named) == "dataflash"
    named.write_bytes(ULOG.read_bytes()[:10_000])
    assert detect.kind(named) == "ulog"
    named.write_text("FMT, 128, 89, FMT, BBnNZ, Type,Length,Name,Format,Columns\n")
    assert detect.kind(named) == "dataflash-text"
    named.write_text("time_s,airspeed_mps\n0.0,20.0\n")
    assert detect.kind(named) == "csv"
    named.write_bytes(hfb_data_path.read_bytes())
    assert detect.kind(named) == "hfb320"
    writer = TlogWriter(named)
    codec = Codec(1, 1)
    for i in range(5):
        writer.write(1_000_000 * i, codec.heartbeat(1))
    writer.close()
    assert detect.kind(named) == "tlog"
    named.write_bytes(b"neither a log nor a table\n" * 200)
    with pytest.raises(FlightDataError, match="not a flight file this tool reads"):
        detect.kind(named)


def test_a_px4_fixed_wing_ulog_comes_back_channel_by_channel(
    tmp_path: Path, noc_config: AircraftConfig
) -> None:
    fl = flight(30.0)
    rec, account = read_log(px4_log(tmp_path / "f.ulg", fl), _with_travel(noc_config))
    t = rec.t_s - BOOT_S

    def truth(x: np.ndarray) -> np.ndarray:
        return np.asarray(np.interp(t, fl.t_s, x))

    assert t[0] == pytest.approx(fl.takeoff_s) and t[-1] <= fl.landing_s
    v, alpha, theta, q, qdot, a_x, a_z = rec.measurements[:, :LEGACY_OBS].T
    np.testing.assert_allclose(theta, truth(fl.theta), atol=1e-6)  # from the quaternion
    np.testing.assert_allclose(q, truth(fl.q), atol=1e-6)
    np.testing.assert_allclose(qdot, 0.3, atol=1e-6)
    np.testing.assert_allclose(a_x, truth(fl.a_x), atol=1e-5)
    np.testing.assert_allclose(a_z, truth(fl.a_z), atol=1e-5)
    # airspeed at 25 Hz: on every other frame only, none made up between (decision 0045)
    assert np.isfinite(v[::2]).all() and np.isnan(v[1::2]).all()
    np.testing.assert_allclose(v[::2], truth(fl.tas)[::2], atol=2e-3)
    assert np.isnan(alpha).all()  # PX4 logs none
    de, throttle, rho = rec.inputs[:, :3].T  # then the turn inputs
    # the servo's torque sign (CA_SV_CS1_TRQ_P < 0) turned into nose-up, then the model's
    # sign; between two 25 Hz samples a sine interpolated linearly (A w^2 dt^2 / 8)
    bend = 0.04**2 / 8
    np.testing.assert_allclose(de, truth(fl.elevator_rad), atol=math.radians(5) * 1.3**2 * bend)
    np.testing.assert_allclose(throttle, truth(fl.throttle), atol=0.2 * 0.7**2 * bend + 1e-7)
    np.testing.assert_allclose(rho, truth(fl.rho), rtol=1e-4)
    np.testing.assert_allclose(rec.aux["phi"], truth(fl.phi), atol=1e-6)
    assert rec.aux["wind_e"][::2] == pytest.approx(-1.5)  # at 25 Hz too
    np.testing.assert_allclose(rec.aux["psi"], 0.3, atol=1e-6)  # the fixture's heading
    np.testing.assert_allclose(rec.aux["vd"][::2], 0.5)  # no GPS topic: the estimator's vz
    assert (
        account.startswith("log f.ulg: PX4 v1.14.0, fixed-wing, ") and "airborne 20.0 s" in account
    )
