"""The message sets real ArduPlane and PX4 vehicles send: each decoded in its units, the
best source of a channel chosen by rate (never two interleaved), and the vehicle's own
servo parameters (PARAM_VALUE) read into the elevator and throttle.

Real pymavlink encoding (MAVLink 2, ardupilotmega) throughout; the link end to end over
UDP with a vehicle that answers the parameter protocol: test_vehicle_requests.py.
"""

from __future__ import annotations

import math
import struct
from pathlib import Path

import pytest

from gcs_estimator.config import LinkConfig
from gcs_estimator.ingest.telemetry import mavlink
from gcs_estimator.ingest.telemetry.channel_sources import ChannelSources, low_rate
from gcs_estimator.ingest.telemetry.decode import (
    PLAUSIBLE,
    DecodeStats,
    Heartbeat,
    ParamValue,
    Sample,
    decode_packet,
)
from gcs_estimator.ingest.telemetry.link import MavlinkLink
from gcs_estimator.ingest.telemetry.mavlink import Codec, Decoder, TlogWriter, read_tlog
from gcs_estimator.ingest.telemetry.vehicle_setup import VehicleSetup
from gcs_estimator.model.channels import Channel

LINK = LinkConfig()
G = 9.80665  # standard gravity [m/s^2], by which ArduPilot scales milli-g


def _event(packet: bytes) -> object:
    decoded = decode_packet(Decoder(), packet, 100.0, LINK, DecodeStats())
    assert decoded is not None
    return decoded.event


def _sample(packet: bytes) -> Sample:
    event = _event(packet)
    assert isinstance(event, Sample), event
    return event


@pytest.fixture
def vehicle() -> Codec:
    return Codec(1, 1)


# ------------------------------------------------------------------ units


@pytest.mark.parametrize("name", ["RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3"])
def test_imus_in_milli_g_and_milli_radians_per_second(vehicle: Codec, name: str) -> None:
    """A level aircraft pitching up at 0.25 rad/s, pushed forward at 0.2 g: ArduPilot
    sends -1000 mg on z (specific force, body axes: gravity reads upward), 200 mg on x
    and 250 mrad/s about y; the channels are SI."""
    mav = vehicle.mav
    mag = (0, 0, 0)
    if name == "RAW_IMU":
        packet = vehicle.pack(mav.raw_imu_encode(7_000_000, 200, 0, -1000, 0, 250, 0, *mag, 0, 0))
        t = 7.0
    else:
        encode = getattr(mav, f"{name.lower()}_encode")
        packet = vehicle.pack(encode(7000, 200, 0, -1000, 0, 250, 0, *mag, 0))
        t = 7.0
    s = _sample(packet)
    assert s.message == name and s.t_vehicle_s == pytest.approx(t)
    assert dict(s.values) == pytest.approx({Channel.AX: 0.2 * G, Channel.AZ: -G, Channel.Q: 0.25})


def test_attitude_gives_theta_and_q_and_the_lateral_signals(vehicle: Codec) -> None:
    s = _sample(vehicle.pack(vehicle.mav.attitude_encode(4200, 0.3, 0.05, 1.0, 0.1, -0.2, 0.4)))
    assert s.t_vehicle_s == pytest.approx(4.2)
    assert dict(s.values) == pytest.approx(
        {
            Channel.THETA: 0.05,
            Channel.Q: -0.2,
            Channel.PHI: 0.3,
            Channel.ROLL_RATE: 0.1,
            Channel.YAW_RATE: 0.4,
        }
    )
    assert dict(s.aux) == pytest.approx({"phi": 0.3, "p": 0.1, "r": 0.4})


def test_highres_imu_is_si_already(vehicle: Codec) -> None:
    imu = vehicle.mav.highres_imu_encode(2_500_000, 0.5, 0, -9.7, 0, 0.1, 0, *[0] * 7, 31)
    s = _sample(vehicle.pack(imu))
    assert dict(s.values) == pytest.approx({Channel.AX: 0.5, Channel.AZ: -9.7, Channel.Q: 0.1})


def test_vertical_speed_and_wind_in_si(vehicle: Codec) -> None:
    """Vertical speed down positive from all three messages: GLOBAL_POSITION_INT.vz in
    cm/s (with its north and east velocity), LOCAL_POSITION_NED.vz in m/s, VFR_HUD.climb up
    positive; WIND's direction in degrees (where it blows from)."""
    mav = vehicle.mav
    gpi = _sample(vehicle.pack(mav.global_position_int_encode(1500, 0, 0, 0, 0, 100, 0, -150, 0)))
    assert dict(gpi.values) == pytest.approx({Channel.HDOT: 1.5})
    assert dict(gpi.aux) == pytest.approx({"vz": -1.5, "vn": 1.0, "ve": 0.0, "vd": -1.5})
    assert gpi.t_vehicle_s == pytest.approx(1.5)
    lpn = _sample(vehicle.pack(mav.local_position_ned_encode(1500, 0, 0, 0, 20.0, 0, 0.75)))
    assert dict(lpn.values) == pytest.approx({Channel.HDOT: -0.75})
    assert dict(lpn.aux) == pytest.approx({"vz": 0.75})
    hud = _sample(vehicle.pack(mav.vfr_hud_encode(18.0, 17.0, 90, 40, 100.0, 2.0)))
    assert dict(hud.values) == pytest.approx({Channel.V: 18.0})
    assert dict(hud.aux) == pytest.approx({"vz": -2.0}) and hud.t_vehicle_s is None
    wind = _sample(vehicle.pack(mav.wind_encode(270.0, 4.0, 0.5)))
    assert dict(wind.aux) == pytest.approx(
        {"wind_dir": math.radians(270.0), "wind_speed": 4.0, "wind_vz": 0.5}
    )


def test_servo_outputs_all_sixteen_and_px4s_actuator_output_status(vehicle: Codec) -> None:
    """SERVO_OUTPUT_RAW keeps every output for the vehicle's parameters to map, and gives
    [link]'s elevator and throttle until they are known; ACTUATOR_OUTPUT_STATUS (PX4,
    float outputs, an array pymavlink reads) the same."""
    mav = vehicle.mav
    servos = [1000 + 10 * i for i in range(16)]
    s = _sample(vehicle.pack(mav.servo_output_raw_encode(3_000_000, 0, *servos)))
    assert s.outputs == tuple(float(v) for v in servos) and s.t_vehicle_s == pytest.approx(3.0)
    expected = (servos[LINK.elevator_servo - 1] - 1500.0) / LINK.elevator_us_per_rad
    assert dict(s.values)[Channel.ELEVATOR] == pytest.approx(expected)
    actuators = [0.0] * 32
    actuators[LINK.elevator_servo - 1] = 1600.0
    actuators[LINK.throttle_servo - 1] = 1250.0
    a = _sample(vehicle.pack(mav.actuator_output_status_encode(5_000_000, 0b111, actuators)))
    assert a.message == "ACTUATOR_OUTPUT_STATUS" and a.t_vehicle_s == pytest.approx(5.0)
    assert dict(a.values) == pytest.approx(
        {Channel.ELEVATOR: 100.0 / LINK.elevator_us_per_rad, Channel.POWER: 0.25}
    )


def test_heartbeat_says_which_autopilot_and_param_value_is_an_event(vehicle: Codec) -> None:
    hb = _event(vehicle.heartbeat(mavlink.MAV_TYPE_FIXED_WING))
    assert isinstance(hb, Heartbeat) and hb.autopilot_kind == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    px4 = vehicle.mav.heartbeat_encode(
        mavlink.MAV_TYPE_FIXED_WING, mavlink.MAV_AUTOPILOT_PX4, 0, 0, 0
    )
    assert _event(vehicle.pack(px4)) == Heartbeat(
        False, mavlink.MAV_TYPE_FIXED_WING, True, mavlink.MAV_AUTOPILOT_PX4
    )
    pv = vehicle.mav.param_value_encode(b"SERVO2_FUNCTION", 19.0, 2, 900, 17)
    assert _event(vehicle.pack(pv)) == ParamValue("SERVO2_FUNCTION", 19.0, 2)


# ------------------------------------------------------------------ source choice


def _imu_packets(codec: Codec, name: str, t: float, q_mrad: int) -> bytes:
    mav = codec.mav
    if name == "RAW_IMU":
        return codec.pack(
            mav.raw_imu_encode(int(t * 1e6), 0, 0, -1000, 0, q_mrad, 0, 0, 0, 0, 0, 0)
        )
    if name == "ATTITUDE":
        return codec.pack(mav.attitude_encode(int(t * 1e3), 0, 0.02, 0, 0, q_mrad * 1e-3, 0))
    if name == "HIGHRES_IMU":
        imu = (0.0, 0.0, -G, 0.0, q_mrad * 1e-3, 0.0) + (0.0,) * 7
        return codec.pack(mav.highres_imu_encode(int(t * 1e6), *imu, 0xFFFF))
    encode = getattr(mav, f"{name.lower()}_encode")
    return codec.pack(encode(int(t * 1e3), 0, 0, -1000, 0, q_mrad, 0, 0, 0, 0, 0))


def _stream(
    codec: Codec, rates: dict[str, float], start: float, end: float
) -> list[tuple[float, bytes]]:
    """Each message at its rate from start to end [s of vehicle time = receive time]; the
    pitch rate each source carries is its own mark (RAW_IMU 100 mrad/s, ...), so a frame
    shows where its q came from. Servo outputs at 10 Hz, airspeed with each ATTITUDE."""
    marks = {"RAW_IMU": 100, "SCALED_IMU2": 200, "ATTITUDE": 300, "HIGHRES_IMU": 400}
    out: list[tuple[float, bytes]] = []
    for name, hz in {**rates, "SERVO_OUTPUT_RAW": 10.0}.items():
        k = 0
        while start + k / hz < end:
            t = start + k / hz
            if name == "SERVO_OUTPUT_RAW":
                pkt = codec.pack(codec.mav.servo_output_raw_encode(int(t * 1e6), 0, *[1500] * 16))
            else:
                pkt = _imu_packets(codec, name, t, marks[name])
            out.append((t, pkt))
            k += 1
    out.sort(key=lambda r: r[0])
    return out


def _q_sources(link: MavlinkLink, packets: list[tuple[float, bytes]]) -> list[float]:
    qs = []
    for t, pkt in packets:
        for frame in link.packet(pkt, 1000.0 + t):
            if not math.isnan(frame.y[Channel.Q]):
                qs.append(round(float(frame.y[Channel.Q]), 3))
    qs += [round(float(f.y[Channel.Q]), 3) for f in link.flush() if not math.isnan(f.y[Channel.Q])]
    return qs


def test_the_fastest_source_is_taken_and_never_mixed_with_another() -> None:
    """ArduPlane's default streams: RAW_IMU and SCALED_IMU2 at 10 Hz, ATTITUDE at 4 Hz
    (its pitchspeed a q too). q comes from RAW_IMU only (first IMU at equal rates); when
    HIGHRES_IMU starts at 50 Hz it takes over, once, and the stream is then HIGHRES_IMU's
    alone; the rates and the switch are reported."""
    codec = Codec(1, 1)
    link = MavlinkLink(LINK, log=open("/dev/null", "w"))  # noqa: SIM115
    link.packet(codec.heartbeat(mavlink.MAV_TYPE_FIXED_WING), 1000.0)
    first = _stream(codec, {"ATTITUDE": 4.0, "SCALED_IMU2": 10.0, "RAW_IMU": 10.0}, 0.0, 10.0)
    later = _stream(
        codec,
        {"ATTITUDE": 4.0, "SCALED_IMU2": 10.0, "RAW_IMU": 10.0, "HIGHRES_IMU": 50.0},
        10.0,
        20.0,
    )
    qs = _q_sources(link, first + later)
    changes = [i for i in range(1, len(qs)) if qs[i] != qs[i - 1]]
    assert qs[0] == 0.1 and qs[-1] == 0.4 and len(changes) == 1, sorted(set(qs))
    report = link.stats()["sources"]["1"]["channels"]
    assert report["q"]["message"] == "HIGHRES_IMU" and report["q"]["switches"] == 1
    assert report["q"]["others_hz"]["RAW_IMU"] == pytest.approx(10.0, rel=0.02)
    assert report["q"]["others_hz"]["ATTITUDE"] == pytest.approx(4.0, rel=0.02)
    assert report["theta"]["message"] == "ATTITUDE" and "warning" in report["theta"]
    assert report["a_z"]["message"] == "HIGHRES_IMU"
    status = link.rates_status(1).split()  # the status line: recent rate, "!" if too slow
    assert status[status.index("q") + 1 : status.index("q") + 3] == ["50", "HIGHRES_IMU"]
    assert status[status.index("theta") + 1 : status.index("theta") + 3] == ["4!", "ATTITUDE"]


def test_a_rate_too_low_is_warned_about() -> None:
    assert low_rate("q", 4.0) and low_rate("theta", 9.9) and not low_rate("q", 10.0)
    assert low_rate("V", 1.0) and not low_rate("V", 2.5) and not low_rate("phi", 0.5)


def test_a_slower_source_heard_first_gives_way_at_once() -> None:
    """ATTITUDE's q arrives before the IMU's in the same autopilot loop: the IMU takes the
    channel as soon as it is heard, before the rates can be measured."""
    sources = ChannelSources(1)
    att = Sample(1, "ATTITUDE", 0.0, 10.0, ((Channel.Q, 0.3), (Channel.THETA, 0.1)))
    raw = Sample(1, "RAW_IMU", 0.0, 10.0, ((Channel.Q, 0.1),))
    got = sources.choose(att)
    assert got is not None and dict(got.values) == {Channel.Q: 0.3, Channel.THETA: 0.1}
    assert sources.choose(raw) is not None
    later = sources.choose(att._replace(t_recv_s=10.1))
    assert later is not None and dict(later.values) == {Channel.THETA: 0.1}
    assert sources.source("q") == "RAW_IMU"


# ------------------------------------------------------------------ servo parameters


def _param(codec: Codec, name: str, value: float, kind: int = 9) -> bytes:
    return codec.pack(codec.mav.param_value_encode(name.encode(), value, kind, 900, 0))


ARDUPLANE_PARAMS = {
    **{f"SERVO{n}_FUNCTION": 0.0 for n in range(1, 17)},
    "SERVO4_FUNCTION": 19.0,
    "SERVO4_MIN": 1100.0,
    "SERVO4_MAX": 1900.0,
    "SERVO4_TRIM": 1450.0,
    "SERVO4_REVERSED": 1.0,
    "SERVO3_FUNCTION": 70.0,
    "SERVO3_MIN": 1000.0,
    "SERVO3_MAX": 2000.0,
    "SERVO3_TRIM": 1000.0,
    "SERVO3_REVERSED": 0.0,
}
"""An ArduPlane whose elevator is on output 4, reversed, trimmed off centre."""


def test_arduplane_parameters_map_the_elevator_and_throttle(vehicle: Codec) -> None:
    """SERVO4_FUNCTION 19, reversed, trim 1450 of 1100..1900, travel 20 deg: 1900 us is
    full negative output once reversed (nose down: trailing edge down, +20 deg); 1275 us,
    half way below trim, is half positive output (nose up, -10 deg); SERVO3 (function 70)
    at 1500 us is half throttle. [link] would have read output 2 and 3 instead."""
    setup = VehicleSetup(1, LINK, 20.0, PLAUSIBLE)
    setup.autopilot(mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA)
    for name, value in ARDUPLANE_PARAMS.items():
        p = _event(_param(vehicle, name, value))
        assert isinstance(p, ParamValue)
        setup.param(p)
    assert setup.servo_map is not None and setup.params.wanted() == []
    assert any("vehicle's own parameters" in n for n in setup.notes)
    for us, deg in ((1900, 20.0), (1450, 0.0), (1275, -10.0), (1100, -20.0)):
        servos = [1500] * 16
        servos[3], servos[2] = us, 1500
        raw = _sample(vehicle.pack(vehicle.mav.servo_output_raw_encode(1000, 0, *servos)))
        got = setup.prepare(raw)
        assert got is not None
        assert dict(got.values) == pytest.approx(
            {Channel.ELEVATOR: math.radians(deg), Channel.POWER: 0.5}
        )
    assert str(setup.report()["servos"]).startswith("vehicle parameters: elevator on output 4")


def test_a_tlog_with_the_ground_stations_parameter_fetch(tmp_path: Path, vehicle: Codec) -> None:
    """A recording holding PARAM_VALUEs (a ground station fetched them): the replay reads
    the elevator from output 4 by them, and says so in its notes and its results."""
    path = tmp_path / "params.tlog"
    writer = TlogWriter(path)
    writer.write(1_000_000, vehicle.heartbeat(mavlink.MAV_TYPE_FIXED_WING))
    for name, value in ARDUPLANE_PARAMS.items():
        writer.write(1_000_000, _param(vehicle, name, value))
    servos = [1500] * 16
    servos[3] = 1900
    writer.write(2_000_000, vehicle.pack(vehicle.mav.servo_output_raw_encode(5000, 0, *servos)))
    writer.close()
    log = tmp_path / "notes.txt"
    with open(log, "w") as fh:
        link = MavlinkLink(LINK, log=fh, elevator_travel_deg=20.0)
        for rec in read_tlog(path):
            link.packet(rec.packet, rec.t_recv_us * 1e-6)
    notes = log.read_text()
    assert "servo outputs from the vehicle's own parameters" in notes and "output 4" in notes
    assert link.stats()["sources"]["1"]["servos"].startswith("vehicle parameters")


def test_px4_parameters_come_bytewise_and_name_the_elevator(vehicle: Codec) -> None:
    """PX4 sends integer parameters' bytes in the float: PWM_MAIN_FUNC2 = 203 (servo 3),
    CA_SV_CS2_TYPE = 3 (elevator), PWM_MAIN_REV = 0; ACTUATOR_OUTPUT_STATUS output 2 at
    2000 us of 1000..2000 is full positive output: trailing edge up, -travel."""

    def int_param(name: str, value: int) -> bytes:
        as_float = struct.unpack("<f", struct.pack("<i", value))[0]
        return _param(vehicle, name, as_float, kind=6)

    setup = VehicleSetup(1, LINK, 25.0, PLAUSIBLE)
    setup.autopilot(mavlink.MAV_AUTOPILOT_PX4)
    packets = [int_param(f"PWM_MAIN_FUNC{n}", 0) for n in range(1, 9)]
    packets += [int_param(f"CA_SV_CS{k}_TYPE", 0) for k in range(8)]
    packets += [int_param("PWM_MAIN_FUNC2", 203), int_param("CA_SV_CS2_TYPE", 3)]
    packets += [int_param("PWM_MAIN_MIN2", 1000), int_param("PWM_MAIN_MAX2", 2000)]
    packets += [int_param("PWM_MAIN_REV", 0)]
    for packet in packets:
        p = _event(packet)
        assert isinstance(p, ParamValue)
        setup.param(p)
    assert setup.servo_map is not None and setup.servo_map.elevator is not None
    assert setup.servo_map.elevator.number == 2
    actuators = [0.0] * 32
    actuators[1] = 2000.0
    raw = _sample(vehicle.pack(vehicle.mav.actuator_output_status_encode(1000, 3, actuators)))
    got = setup.prepare(raw)
    assert got is not None
    assert dict(got.values)[Channel.ELEVATOR] == pytest.approx(math.radians(-25.0))


# ------------------------------------------------------------------ AOA_SSA's weight


def test_ardupilots_aoa_ssa_is_weighed_as_an_ahrs_estimate() -> None:
    """[link] aoa_ssa = "ahrs" (the default: ArduPlane's AOA_SSA is its AHRS estimate)
    puts alpha's sigma at 3 deg at least, leaving the others; "vane" (the simulator's
    configs) keeps the [filter] sigma; a sigma already larger is kept."""
    from dataclasses import replace

    from gcs_estimator.config import load_config
    from gcs_estimator.ingest.telemetry.vehicle_setup import weigh_alpha

    vane = load_config("noc_uav")
    assert vane.link.aoa_ssa == "vane" and weigh_alpha(vane) == vane
    ahrs = replace(vane, link=replace(vane.link, aoa_ssa="ahrs"))
    sigma = weigh_alpha(ahrs).filter.measurement_sigma
    before = vane.filter.measurement_sigma
    assert sigma[Channel.ALPHA] == pytest.approx(math.radians(3.0))
    assert sigma[: Channel.ALPHA] == before[: Channel.ALPHA]
    assert sigma[Channel.ALPHA + 1 :] == before[Channel.ALPHA + 1 :]
    assert LinkConfig().aoa_ssa == "ahrs"
    wide = list(before)
    wide[Channel.ALPHA] = math.radians(5.0)
    loose = replace(ahrs, filter=replace(ahrs.filter, measurement_sigma=tuple(wide)))
    assert weigh_alpha(loose) == loose


def test_the_run_says_what_alpha_from_aoa_ssa_is(vehicle: Codec) -> None:
    link = MavlinkLink(LINK, log=open("/dev/null", "w"))  # noqa: SIM115
    link.packet(vehicle.heartbeat(mavlink.MAV_TYPE_FIXED_WING), 1000.0)
    for k in range(6):
        link.packet(vehicle.pack(vehicle.mav.aoa_ssa_encode(k * 100_000, 3.0, 0)), 1000.0 + k)
    sources = link.stats()["sources"]["1"]
    assert sources["channels"]["alpha"]["message"] == "AOA_SSA"
    assert "AHRS" in sources["alpha_note"] and "not a vane" in sources["alpha_note"]
    vane = MavlinkLink(LinkConfig(aoa_ssa="vane"), log=open("/dev/null", "w"))  # noqa: SIM115
    vane.packet(vehicle.pack(vehicle.mav.aoa_ssa_encode(0, 3.0, 0)), 1000.0)
    assert "alpha_note" not in vane.stats()["sources"]["1"]
