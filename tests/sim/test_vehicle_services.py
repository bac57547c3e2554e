"""The simulated vehicle speaks to a ground station as an ArduPlane does, over real UDP on
loopback: its heartbeat names a real mode, every command is acknowledged to its sender,
REQUEST_MESSAGE and REQUEST_DATA_STREAM are served, and its stream rates are parameters
that can be listed, read and set."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
from pymavlink import mavutil

from gcs_estimator.config import load_config
from gcs_estimator.ingest.flightdata import Recording
from gcs_estimator.ingest.telemetry import mavlink
from gcs_estimator.model.channels import Channel
from sim.truth import simulate
from sim.vehicle import STREAM_PARAMS, SimulatedVehicle
from tests.telemetry.test_link import SHORT
from tests.udp import Ground


@pytest.fixture
def pair() -> tuple[Ground, SimulatedVehicle]:
    config = load_config("noc_uav", SHORT)
    fl = simulate(config, seed=1)
    rec = Recording(fl.t_s, fl.inputs, fl.measurements, "throttle")
    ground = Ground()
    vehicle = SimulatedVehicle(rec, config.link, ground.sock.getsockname(), speed=0.0)
    return ground, vehicle


def _ack(cmd: int) -> Callable[[Any], bool]:
    return lambda m: m.get_type() == "COMMAND_ACK" and m.command == cmd


def test_heartbeat_names_an_arduplane_mode() -> None:
    codec = mavlink.Codec(1, 1)
    (hb,) = mavlink.Codec(9, 9).parse(codec.heartbeat(mavlink.MAV_TYPE_FIXED_WING))
    assert hb.base_mode & mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert mavutil.mode_string_v10(hb) == "MANUAL"


def test_every_command_is_acknowledged_to_its_sender(pair: tuple[Ground, SimulatedVehicle]) -> None:
    ground, vehicle = pair
    mav = ground.codec.mav
    arm = mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM
    ground.send(vehicle, mav.command_long_encode(1, 1, arm, 0, 1, 0, 0, 0, 0, 0, 0))
    (ack,) = [m for m in ground.until(vehicle, _ack(arm)) if m.get_type() == "COMMAND_ACK"]
    assert ack.result == mavlink.MAV_RESULT_UNSUPPORTED
    assert (ack.target_system, ack.target_component) == (255, 190)
    home = mavutil.mavlink.MAV_CMD_GET_HOME_POSITION
    ground.send(vehicle, mav.command_int_encode(1, 1, 0, home, 0, 0, 0, 0, 0, 0, 0, 0, 0))
    ground.until(vehicle, _ack(home))
    ground.send(vehicle, mav.command_long_encode(7, 1, arm, 0, 1, 0, 0, 0, 0, 0, 0))  # not us
    vehicle._serve()
    with pytest.raises(TimeoutError):
        ground.sock.recv(65535)


def test_request_message_and_data_streams(pair: tuple[Ground, SimulatedVehicle]) -> None:
    ground, vehicle = pair
    mav = ground.codec.mav
    req = mavlink.MAV_CMD_REQUEST_MESSAGE
    attitude = mavlink.MSG_ID["ATTITUDE"]
    ground.send(vehicle, mav.command_long_encode(1, 1, req, 0, attitude, 0, 0, 0, 0, 0, 0))
    got = ground.until(vehicle, _ack(req))
    assert [m.result for m in got if m.get_type() == "COMMAND_ACK"] == [0]
    assert vehicle.requested == {"ATTITUDE"}  # sent with the next sample
    ground.send(vehicle, mav.command_long_encode(1, 1, req, 0, 0, 0, 0, 0, 0, 0, 0))
    got = ground.until(vehicle, _ack(req))
    assert "HEARTBEAT" in [m.get_type() for m in got]
    extra1 = mavlink.MAV_DATA_STREAM_EXTRA1
    ground.send(vehicle, mav.request_data_stream_encode(1, 1, extra1, 5, 1))
    ground.send(vehicle, mav.request_data_stream_encode(1, 1, mavlink.MAV_DATA_STREAM_EXTRA2, 0, 0))
    vehicle.requested.clear()
    ground.send(vehicle, mav.param_request_read_encode(1, 1, b"SR0_EXTRA1", -1))
    (value,) = [
        m for m in ground.until(vehicle, lambda m: m.get_type() == "PARAM_VALUE")
        if m.get_type() == "PARAM_VALUE"
    ]  # fmt: skip
    assert value.param_value == 5.0 and vehicle.rates["ATTITUDE"] == 5.0
    assert vehicle.rates["VFR_HUD"] == 0.0


def test_parameters_list_read_and_set(pair: tuple[Ground, SimulatedVehicle]) -> None:
    ground, vehicle = pair
    mav = ground.codec.mav
    ground.send(vehicle, mav.param_request_list_encode(1, 1))
    n = len(STREAM_PARAMS)
    values: dict[str, Any] = {}

    def all_listed(m: Any) -> bool:
        if m.get_type() == "PARAM_VALUE":
            values[m.param_id] = m
        return len(values) == n

    ground.until(vehicle, all_listed)
    assert sorted(values) == sorted(p for p, _ in STREAM_PARAMS)
    assert {m.param_count for m in values.values()} == {n}
    assert sorted(m.param_index for m in values.values()) == list(range(n))
    ground.send(vehicle, mav.param_set_encode(1, 1, b"SR0_RAW_SENS", 10.0, 9))
    got = ground.until(vehicle, lambda m: m.get_type() == "PARAM_VALUE")
    echo = [m for m in got if m.get_type() == "PARAM_VALUE"][-1]
    assert (echo.param_id, echo.param_value) == ("SR0_RAW_SENS", 10.0)
    assert vehicle.rates["HIGHRES_IMU"] == 10.0


def test_the_climb_rate_is_sent_true_and_as_the_sensor_reads_it() -> None:
    """VFR_HUD.climb carries the flight's true climb rate (not 0); a vehicle with a
    climb-rate sensor (simulation.climb_rate) also sends its h_dot as
    GLOBAL_POSITION_INT.vz (cm/s, down positive), one without sends none."""
    for sensor in (False, True):
        config = load_config("noc_uav", [*SHORT, f"simulation.climb_rate={str(sensor).lower()}"])
        fl = simulate(config, seed=1)
        truth = fl.clean[:, Channel.HDOT]
        rec = replace(Recording(fl.t_s, fl.inputs, fl.measurements, "throttle"), aux={"vz": -truth})
        ground = Ground()
        vehicle = SimulatedVehicle(rec, config.link, ground.sock.getsockname(), speed=0.0)
        vehicle.run(stop_after_s=1.0)
        ground.sock.setblocking(False)  # all sent on loopback before run returned
        got: list[Any] = []
        while True:
            try:
                data = ground.sock.recv(65535)
            except BlockingIOError:
                break
            got += [m for m in ground.codec.parse(data) if m.get_type() != "BAD_DATA"]
        climbs = [m.climb for m in got if m.get_type() == "VFR_HUD"]
        assert len(climbs) >= 10 and np.any(np.abs(climbs) > 0.0)
        np.testing.assert_allclose(climbs, truth[: len(climbs)], atol=1e-5)  # float32
        vz = [m.vz for m in got if m.get_type() == "GLOBAL_POSITION_INT"]
        if sensor:
            assert len(vz) == len(climbs)
            h_dot = fl.measurements[: len(vz), Channel.HDOT]
            np.testing.assert_allclose(vz, np.round(-100.0 * h_dot), atol=0.0)
        else:
            assert vz == []
