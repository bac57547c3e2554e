"""The simulated flight written as ArduPlane and PX4 write theirs: real .bin, .ulg and .tlog
files in tmp_path, read back with pymavlink's DFReader, mavlogdump.py (as a process) and
pyulog; every channel equals what the simulator flew within the format's resolution, at
the autopilot's rates, with the parameters a reader needs to decode the elevator."""

from __future__ import annotations

import csv
import io
import math
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pymavlink import DFReader, mavutil
from pyulog import ULog

from gcs_estimator.config import AircraftConfig, load_config, load_truths
from gcs_estimator.ingest.flightdata import Recording
from gcs_estimator.model import atmosphere
from sim.cli import main as sim_main
from sim.formats import GRAVITY_MSS, FlightRecord, every, flight_record, truth_path
from sim.formats.ardupilot import ArduPlaneVehicle
from sim.formats.dataflash import write_bin
from sim.formats.ulog import write_ulg
from sim.truth import Flight, simulate
from tests.udp import Ground, loopback, port_of

SHORT = ["simulation.manoeuvre.duration_s=12"]


@pytest.fixture(scope="module")
def config() -> AircraftConfig:
    return load_config("noc_uav", SHORT)


@pytest.fixture(scope="module")
def flight(config: AircraftConfig) -> Flight:
    return simulate(config, seed=3)


@pytest.fixture(scope="module")
def record(config: AircraftConfig, flight: Flight) -> FlightRecord:
    rec = Recording(flight.t_s, flight.inputs, flight.measurements, "throttle")
    return flight_record(rec, config.link, config.airframe.air_density_kgpm3)


def _read_bin(path: Path) -> dict[str, list[Any]]:
    log = DFReader.DFReader_binary(str(path))
    out: dict[str, list[Any]] = {}
    while (m := log.recv_msg()) is not None:
        out.setdefault(m.get_type(), []).append(m)
    return out


def _column(msgs: list[Any], field: str) -> np.ndarray:
    return np.array([getattr(m, field) for m in msgs], float)


def _elevator_from_servo(params: dict[str, float], servo: int, pwm: np.ndarray) -> np.ndarray:
    """The elevator [rad, trailing edge down] a reader gets from RCOU / SERVO_OUTPUT_RAW
    with the log's SERVOn_ parameters, ArduPlane's convention (positive output nose-up)
    and the airframe's travel (500 us / elevator_us_per_rad = 30 deg)."""
    trim, hi, lo = (params[f"SERVO{servo}_{k}"] for k in ("TRIM", "MAX", "MIN"))
    sign = -1.0 if params[f"SERVO{servo}_REVERSED"] else 1.0
    span = np.where(pwm >= trim, hi - trim, trim - lo)
    nose_up = sign * (pwm - trim) / span
    return -nose_up * math.radians(30.0)


def test_dataflash_log_reads_back_as_flown(
    tmp_path: Path, config: AircraftConfig, flight: Flight, record: FlightRecord
) -> None:
    msgs = _read_bin(write_bin(record, tmp_path / "flight.bin"))
    n = len(record)
    params = {m.Name: m.Value for m in msgs["PARM"]}
    assert params["SERVO2_FUNCTION"] == 19 and params["SERVO3_FUNCTION"] == 70
    assert params["SERVO2_REVERSED"] == 1 and params["SCHED_LOOP_RATE"] == 50
    assert any("Plane" in m.Message for m in msgs["MSG"])
    # IMU every loop (50 Hz), ATT/CTUN/RCOU/AETR at 25 Hz, AOA/ARSP/BARO at 10, GPS at 5
    counts = {k: len(msgs[k]) for k in ("IMU", "ATT", "RCOU", "AETR", "CTUN", "AOA", "ARSP", "GPS")}
    assert counts == {
        "IMU": n, "ATT": (n + 1) // 2, "RCOU": (n + 1) // 2, "AETR": (n + 1) // 2,
        "CTUN": (n + 1) // 2, "AOA": (n + 4) // 5, "ARSP": (n + 4) // 5, "GPS": (n + 9) // 10,
    }  # fmt: skip
    imu = msgs["IMU"]
    assert np.array_equal(_column(imu, "TimeUS"), record.time_us.astype(float))
    y = flight.measurements
    np.testing.assert_allclose(_column(imu, "GyrY"), y[:, 3], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(_column(imu, "AccX"), y[:, 5], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(_column(imu, "AccZ"), y[:, 6], rtol=1e-6, atol=1e-6)
    half = np.arange(0, n, 2)
    # ATT.Pitch is int16 centidegrees: within 0.005 deg
    pitch = np.radians(_column(msgs["ATT"], "Pitch"))
    np.testing.assert_allclose(pitch, y[half, 2], atol=math.radians(0.0051))
    aoa = np.radians(_column(msgs["AOA"], "AOA"))
    np.testing.assert_allclose(aoa, y[::5, 1], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(_column(msgs["ARSP"], "Airspeed"), y[::5, 0], rtol=1e-6)
    # The elevator from RCOU and the log's own parameters: whole microseconds, as flown
    rcou = _column(msgs["RCOU"], "C2")
    assert np.array_equal(rcou, np.round(rcou))
    # (954.93 us/rad is 30 deg to 4e-7 rad, far inside one microsecond's 1e-3 rad)
    np.testing.assert_allclose(
        _elevator_from_servo(params, 2, rcou), flight.inputs[half, 0], atol=1e-6
    )
    np.testing.assert_allclose(
        _column(msgs["AETR"], "Elev") / 4500.0, record.elevator_out[half], atol=1e-6
    )
    throttle = _column(msgs["RCOU"], "C3")
    np.testing.assert_allclose((throttle - 1000) / 1000, flight.inputs[half, 1], atol=1e-9)
    baro = msgs["BARO"]
    rho = _column(baro, "Press") / ((_column(baro, "Temp") + 273.15) * atmosphere.R_AIR)
    # (Temp in centidegrees: 0.005 K of 290 K)
    np.testing.assert_allclose(rho, config.airframe.air_density_kgpm3, rtol=2e-5)
    gps = msgs["GPS"]
    np.testing.assert_allclose(_column(gps, "Lat"), record.lat_deg[::10], atol=1e-7)
    np.testing.assert_allclose(_column(gps, "Alt"), record.alt_msl_m[::10], atol=0.0051)
    assert set(_column(msgs["XKF2"], "VWN")) == {0.0}
    # FMTU, UNIT and MULT: a reader gets each field's unit from the log itself
    assert imu[0].fmt.get_unit("AccX") == "m/s/s" and imu[0].fmt.get_unit("GyrY") == "rad/s"
    assert msgs["ATT"][0].fmt.get_unit("Pitch") == "deg"


def test_dataflash_fullrate_logs_attitude_every_loop(tmp_path: Path, record: FlightRecord) -> None:
    msgs = _read_bin(write_bin(record, tmp_path / "fast.bin", fullrate=True))
    assert len(msgs["ATT"]) == len(msgs["IMU"]) == len(record)
    bitmask = next(m.Value for m in msgs["PARM"] if m.Name == "LOG_BITMASK")
    assert int(bitmask) & (1 << 20)


def test_mavlogdump_reads_the_dataflash_log(tmp_path: Path, record: FlightRecord) -> None:
    path = write_bin(record, tmp_path / "flight.bin")
    tool = Path(sys.executable).parent / "mavlogdump.py"
    done = subprocess.run(
        [sys.executable, str(tool), "--types", "AOA", "--format", "csv", str(path)],
        capture_output=True,
        text=True,
        check=False,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    rows = list(csv.DictReader(io.StringIO(done.stdout)))
    assert len(rows) == (len(record) + 4) // 5
    aoa = np.array([float(r["AOA"]) for r in rows])
    np.testing.assert_allclose(np.radians(aoa), record.alpha[::5], rtol=1e-5, atol=1e-7)


def test_ulog_reads_back_as_flown(tmp_path: Path, flight: Flight, record: FlightRecord) -> None:
    path = write_ulg(record, tmp_path / "flight.ulg")
    log = ULog(str(path))
    data = {d.name: d.data for d in log.data_list}
    n, y = len(record), flight.measurements
    # PX4's default logger intervals: 50 ms (every third 50 Hz sample), 20, 200, 100, 1000
    sizes = {k: len(v["timestamp"]) for k, v in data.items()}
    assert sizes["vehicle_attitude"] == (n + 2) // 3
    assert sizes["vehicle_angular_velocity"] == sizes["vehicle_acceleration"] == n
    assert sizes["airspeed_validated"] == sizes["vehicle_air_data"] == (n + 9) // 10
    assert sizes["actuator_servos"] == sizes["vehicle_local_position"] == (n + 4) // 5
    assert sizes["wind"] == sizes["vehicle_status"] == (n + 49) // 50
    assert "angle_of_attack" not in str(sorted(data))
    att = data["vehicle_attitude"]
    theta = 2.0 * np.arctan2(att["q[2]"], att["q[0]"])
    np.testing.assert_allclose(theta, y[::3, 2], atol=1e-6)
    rates = data["vehicle_angular_velocity"]
    np.testing.assert_allclose(rates["xyz[1]"], y[:, 3], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(rates["xyz_derivative[1]"], y[:, 4], rtol=1e-6, atol=1e-6)
    acc = data["vehicle_acceleration"]
    np.testing.assert_allclose(acc["xyz[0]"], y[:, 5], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(acc["xyz[2]"], y[:, 6], rtol=1e-6, atol=1e-6)
    airspeed = data["airspeed_validated"]
    np.testing.assert_allclose(airspeed["true_airspeed_m_s"], y[::10, 0], rtol=1e-6)
    params = log.initial_parameters
    assert params["CA_SV_CS0_TYPE"] == 3 and params["CA_SV_CS0_TRQ_P"] == 1.0
    assert params["PWM_MAIN_FUNC2"] == 201 and params["PWM_MAIN_REV"] & 0b10
    # The normalised command with the airframe's travel (30 deg), nose-up positive
    servo = data["actuator_servos"]["control[0]"]
    np.testing.assert_allclose(-servo * math.radians(30.0), flight.inputs[::5, 0], atol=1e-6)
    motor = data["actuator_motors"]["control[0]"]
    np.testing.assert_allclose(motor, flight.inputs[::5, 1], atol=1e-6)
    assert set(data["vehicle_status"]["vehicle_type"]) == {2}
    assert log.msg_info_dict["sys_name"] == "PX4"


def test_ulog_fast_profile_logs_every_sample(tmp_path: Path, record: FlightRecord) -> None:
    log = ULog(str(write_ulg(record, tmp_path / "fast.ulg", fast=True)))
    sizes = {d.name: len(d.data["timestamp"]) for d in log.data_list}
    assert sizes["vehicle_attitude"] == sizes["actuator_servos"] == len(record)


def test_every_keeps_the_logger_interval() -> None:
    t = np.arange(0, 2.0001, 0.02)
    assert list(every(t, 0.1)) == list(range(0, len(t), 5))
    jittered = t + np.where(np.arange(len(t)) % 2, 0.003, 0.0)
    kept = every(jittered, 0.1)
    assert np.all(np.diff(jittered[kept]) >= 0.1 - 1e-9)


def _read_tlog(path: Path) -> dict[str, list[Any]]:
    conn = mavutil.mavlink_connection(str(path))
    out: dict[str, list[Any]] = {}
    while (m := conn.recv_match()) is not None:
        out.setdefault(m.get_type(), []).append(m)
    return out


def _sent(t_s: np.ndarray, hz: float) -> np.ndarray:
    """The samples a message at hz goes out with: each due 1/hz after the last due time
    (a scheduler on the vehicle's loop sends it at the first loop past that)."""
    kept, due = [], float(t_s[0])
    for k, t in enumerate(t_s):
        if t >= due - 1e-6:
            kept.append(k)
            due = max(due + 1.0 / hz, t + 0.5 / hz)
    return np.array(kept)


@pytest.mark.parametrize("asked", [False, True])
def test_arduplane_tlog_has_its_message_set_units_and_rates(
    tmp_path: Path, config: AircraftConfig, flight: Flight, asked: bool
) -> None:
    sink = loopback()
    port = port_of(sink)
    prefix = tmp_path / "ap"
    args = ["--set", SHORT[0], "--seed", "3", "--speed", "0", "--autopilot", "arduplane"]
    args += ["--tlog", str(prefix), "--target", f"127.0.0.1:{port}"]
    try:
        assert sim_main(args + (["--asked"] if asked else [])) == 0
    finally:
        sink.close()
    tlog = Path(f"{prefix}_1.tlog")
    msgs = _read_tlog(tlog)
    hb = msgs["HEARTBEAT"][0]
    assert hb.autopilot == mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    assert hb.type == mavutil.mavlink.MAV_TYPE_FIXED_WING
    params = {m.param_id: m.param_value for m in msgs["PARAM_VALUE"]}
    assert params["SERVO2_FUNCTION"] == 19 and params["SERVO2_TRIM"] == 1500
    assert params["SR0_EXTRA1"] == 4
    y = flight.measurements
    i = _sent(flight.t_s, 50.0 if asked else 4.0)  # asked at 50 Hz, else MAVProxy's 4 Hz
    for name in ("ATTITUDE", "RAW_IMU", "SERVO_OUTPUT_RAW", "AOA_SSA", "VFR_HUD"):
        assert len(msgs[name]) == len(i), name
    assert len(msgs["WIND"]) == len(_sent(flight.t_s, 4.0))  # EXTRA3 stays at 4 Hz
    imu = msgs["RAW_IMU"]
    assert [m.zacc for m in imu] == [int(v) for v in np.trunc(y[i, 6] * 1000 / GRAVITY_MSS)]
    assert [m.ygyro for m in imu] == [int(v) for v in np.trunc(y[i, 3] * 1000)]
    att = msgs["ATTITUDE"]
    np.testing.assert_allclose(_column(att, "pitchspeed"), y[i, 3], rtol=1e-6, atol=1e-9)
    aoa = np.radians(_column(msgs["AOA_SSA"], "AOA"))
    np.testing.assert_allclose(aoa, y[i, 1], rtol=1e-6, atol=1e-9)
    servo = _column(msgs["SERVO_OUTPUT_RAW"], "servo2_raw")
    np.testing.assert_allclose(
        _elevator_from_servo(params, 2, servo), flight.inputs[i, 0], atol=1e-6
    )
    truths = load_truths(truth_path(tlog), config.coefficient_names)
    assert truths == {1: tuple(float(v) for v in flight.truth)}


def test_a_bad_message_rate_is_refused_with_the_names_it_knows(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert sim_main(["--set", SHORT[0], "--autopilot", "arduplane", "--msg-rate", "FOO=5"]) == 2
    err = capsys.readouterr().err
    assert "FOO" in err and "ATTITUDE" in err
    assert sim_main(["--set", SHORT[0], "--asked"]) == 2
    assert "--autopilot arduplane" in capsys.readouterr().err


def test_bin_and_ulg_options_write_the_logs_and_their_truth(
    tmp_path: Path, config: AircraftConfig
) -> None:
    bin_path, ulg_path = tmp_path / "f.bin", tmp_path / "f.ulg"
    args = ["--set", SHORT[0], "--speed", "0", "--vehicles", "2"]
    assert sim_main([*args, "--bin", str(bin_path), "--ulg", str(ulg_path)]) == 0
    for k in (1, 2):
        for p in (tmp_path / f"f_{k}.bin", tmp_path / f"f_{k}.ulg"):
            assert set(load_truths(truth_path(p), config.coefficient_names)) == {k}
    assert {m.Name: m.Value for m in _read_bin(tmp_path / "f_2.bin")["PARM"]}["SYSID_THISMAV"] == 2


@pytest.fixture
def live(config: AircraftConfig, flight: Flight) -> tuple[Ground, ArduPlaneVehicle]:
    rec = Recording(flight.t_s, flight.inputs, flight.measurements, "throttle")
    ground = Ground()
    vehicle = ArduPlaneVehicle(rec, config.link, ground.sock.getsockname(), speed=0.0)
    return ground, vehicle


def _param(name: str) -> Callable[[Any], bool]:
    return lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == name


def test_live_arduplane_answers_the_parameter_protocol(
    live: tuple[Ground, ArduPlaneVehicle],
) -> None:
    ground, vehicle = live
    mav = ground.codec.mav
    ground.send(vehicle, mav.param_request_read_encode(1, 1, b"SERVO2_REVERSED", -1))
    (value,) = [m for m in ground.until(vehicle, _param("SERVO2_REVERSED"))]
    assert value.param_value == 1 and value.param_count == len(vehicle.params())
    ground.send(vehicle, mav.param_request_list_encode(1, 1))
    got = ground.until(vehicle, lambda m: getattr(m, "param_index", -1) == m.param_count - 1)
    names = {m.param_id for m in got if m.get_type() == "PARAM_VALUE"}
    assert {f"SERVO{n}_{k}" for n in (2, 3) for k in ("FUNCTION", "MIN", "MAX")} <= names
    ground.send(vehicle, mav.param_set_encode(1, 1, b"SR0_EXTRA1", 20.0, 4))
    (echo,) = [m for m in ground.until(vehicle, _param("SR0_EXTRA1"))]
    assert echo.param_value == 20.0 and vehicle.message_rate("ATTITUDE") == 20.0


def test_live_arduplane_honours_message_intervals_and_data_streams(
    live: tuple[Ground, ArduPlaneVehicle],
) -> None:
    ground, vehicle = live
    mav = ground.codec.mav
    interval = mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
    raw_imu = mavutil.mavlink.MAVLINK_MSG_ID_RAW_IMU
    ground.send(vehicle, mav.command_long_encode(1, 1, interval, 0, raw_imu, 25_000, 0, 0, 0, 0, 0))
    acks = [m for m in ground.until(vehicle, lambda m: m.get_type() == "COMMAND_ACK")]
    assert acks[-1].result == mavutil.mavlink.MAV_RESULT_ACCEPTED
    assert vehicle.message_rate("RAW_IMU") == 40.0
    assert vehicle.message_rate("SCALED_IMU2") == 4.0  # its stream's rate, unchanged
    all_streams = mavutil.mavlink.MAV_DATA_STREAM_ALL
    ground.send(vehicle, mav.request_data_stream_encode(1, 1, all_streams, 10, 1))
    ground.send(vehicle, mav.param_request_read_encode(1, 1, b"SR0_EXTRA3", -1))
    (extra3,) = [m for m in ground.until(vehicle, _param("SR0_EXTRA3"))]
    assert extra3.param_value == 10.0 and vehicle.message_rate("WIND") == 10.0
    assert vehicle.message_rate("RAW_IMU") == 40.0  # a message's own interval wins
