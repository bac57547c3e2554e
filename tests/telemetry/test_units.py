"""The telemetry edge piece by piece: decode and tlog framing (the synchroniser:
test_sync.py; link health: test_counters.py).

Real pymavlink encoding (MAVLink 2, ardupilotmega) throughout; no sockets here (the link
end to end is test_link.py).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from gcs_estimator.config import LinkConfig
from gcs_estimator.ingest.telemetry import mavlink, pwm
from gcs_estimator.ingest.telemetry.decode import (
    CommandAck,
    DecodeStats,
    Heartbeat,
    Ignored,
    Sample,
    decode_packet,
)
from gcs_estimator.ingest.telemetry.mavlink import (
    Codec,
    Decoder,
    TlogError,
    TlogStats,
    read_tlog,
    scan,
    tlog_record,
)
from gcs_estimator.ingest.telemetry.sync import Synchronizer
from gcs_estimator.model import atmosphere
from gcs_estimator.model.channels import Channel

LINK = LinkConfig()
OBS = ("v", "alpha", "theta", "q", "qdot", "ax", "az")


def _sample(t: float, t_recv: float, **values: float) -> Sample:
    return Sample(1, "test", t, t_recv, tuple((Channel[k.upper()], v) for k, v in values.items()))


def _decode(packet: bytes, stats: DecodeStats | None = None) -> object:
    decoded = decode_packet(Decoder(), packet, 100.0, LINK, stats or DecodeStats())
    return None if decoded is None else decoded.event


@pytest.fixture
def vehicle() -> Codec:
    return Codec(1, 1)


# ------------------------------------------------------------------ decode


def test_each_message_decodes_to_its_channels_in_si_units(vehicle: Codec) -> None:
    mav = vehicle.mav
    imu = _decode(
        vehicle.pack(mav.highres_imu_encode(2_500_000, 0.5, 0, -9.7, 0, 0.1, 0, *[0] * 7, 31))
    )
    assert isinstance(imu, Sample) and imu.t_vehicle_s == pytest.approx(2.5)
    assert dict(imu.values) == pytest.approx({Channel.AX: 0.5, Channel.AZ: -9.7, Channel.Q: 0.1})
    att = _decode(vehicle.pack(mav.attitude_encode(2500, 0, 0.05, 0, 0, 0, 0)))
    assert isinstance(att, Sample) and att.t_vehicle_s == pytest.approx(2.5)
    assert dict(att.values) == pytest.approx(
        {
            Channel.THETA: 0.05,
            Channel.Q: 0.0,
            Channel.PHI: 0.0,
            Channel.ROLL_RATE: 0.0,
            Channel.YAW_RATE: 0.0,
        }
    )
    aoa = _decode(vehicle.pack(mav.aoa_ssa_encode(2_500_000, 3.0, 0)))  # degrees on the wire
    assert isinstance(aoa, Sample) and dict(aoa.values) == pytest.approx(
        {Channel.ALPHA: math.radians(3.0)}
    )
    hud = _decode(vehicle.pack(mav.vfr_hud_encode(24.0, 24.0, 0, 30, 100, 0)))
    assert isinstance(hud, Sample) and hud.t_vehicle_s is None  # VFR_HUD has no timestamp
    assert dict(hud.values) == pytest.approx({Channel.V: 24.0})
    servos = [0] * 16
    servos[LINK.elevator_servo - 1] = round(pwm.elevator_pwm(LINK, 0.05))
    servos[LINK.throttle_servo - 1] = round(pwm.throttle_pwm(LINK, 0.3))
    servo = _decode(vehicle.pack(mav.servo_output_raw_encode(2_500_000, 0, *servos)))
    assert isinstance(servo, Sample)
    values = dict(servo.values)
    assert values[Channel.ELEVATOR] == pytest.approx(0.05, abs=pwm.elevator_rad(LINK, 1501.0))
    assert values[Channel.POWER] == pytest.approx(0.3, abs=1e-3)  # 1 us of PWM
    qdot = _decode(vehicle.pack(mav.named_value_float_encode(2500, b"QDOT", 1.5)))
    assert isinstance(qdot, Sample) and dict(qdot.values) == pytest.approx({Channel.QDOT: 1.5})


def test_static_pressure_gives_the_air_density_where_asked_for(vehicle: Codec) -> None:
    """SCALED_PRESSURE at 850 hPa: the standard atmosphere's density at that pressure when
    link.density_from_pressure is set (its temperature field, the sensor's own, unused);
    ignored otherwise, and the frame then carries no density."""
    packet = vehicle.pack(vehicle.mav.scaled_pressure_encode(2500, 850.0, 0.1, 4000))
    assert _decode(packet) == Ignored()
    link = LinkConfig(density_from_pressure=True)
    decoded = decode_packet(Decoder(), packet, 100.0, link, DecodeStats())
    assert decoded is not None and isinstance(decoded.event, Sample)
    assert decoded.event.t_vehicle_s == pytest.approx(2.5)
    expected = float(atmosphere.density(85000.0))
    assert dict(decoded.event.values) == pytest.approx({Channel.DENSITY: expected})
    sync = Synchronizer(1, link)
    sync.add(decoded.event)
    sync.add(_sample(2.5, 10.0, elevator=0.01, power=0.3))
    frames = [f for ch in OBS for f in sync.add(_sample(2.5, 10.0, **{ch: 1.0}))]
    assert len(frames) == 1
    np.testing.assert_allclose(frames[0].inputs[:3], [0.01, 0.3, expected])  # then the turn's


def test_link_events_and_what_carries_nothing(vehicle: Codec) -> None:
    mav = vehicle.mav
    stats = DecodeStats()
    assert _decode(vehicle.heartbeat(mavlink.MAV_TYPE_FIXED_WING)) == Heartbeat(False)
    assert _decode(Codec(255, 190).heartbeat(mavlink.MAV_TYPE_GCS)) == Heartbeat(
        True, mavlink.MAV_TYPE_GCS, autopilot=False, autopilot_kind=mavlink.MAV_AUTOPILOT_INVALID
    )
    ack = vehicle.command_ack(
        mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAV_RESULT_ACCEPTED, 255, 190
    )
    assert _decode(ack) == CommandAck(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, 255)
    assert _decode(vehicle.pack(mav.named_value_float_encode(1, b"OTHER", 1.0)), stats) == Ignored()
    assert _decode(vehicle.pack(mav.system_time_encode(1, 1)), stats) == Ignored()
    assert stats.ignored_messages == 2


def test_bad_values_are_counted_and_dropped_bad_packets_are_none(vehicle: Codec) -> None:
    mav = vehicle.mav
    stats = DecodeStats()
    hud = vehicle.pack(mav.vfr_hud_encode(math.nan, 0, 0, 0, 0, math.inf))
    assert _decode(hud, stats) == Ignored()  # neither airspeed nor climb
    half = _decode(vehicle.pack(mav.vfr_hud_encode(math.nan, 0, 0, 0, 0, 1.0)), stats)
    assert isinstance(half, Sample) and half.values == () and half.aux == (("vz", -1.0),)
    assert _decode(vehicle.pack(mav.aoa_ssa_encode(1, 500.0, 0)), stats) == Ignored()
    assert stats.invalid_values == 4
    packet = bytearray(vehicle.pack(mav.attitude_encode(1, 0, 0.05, 0, 0, 0, 0)))
    packet[-1] ^= 0xFF  # CRC
    assert _decode(bytes(packet)) is None
    assert _decode(bytes(packet[:-4])) is None  # truncated


# ------------------------------------------------------------------ synchroniser


# ------------------------------------------------------------------ tlog framing


def test_a_datagram_splits_into_packets_skipping_junk(vehicle: Codec) -> None:
    a = vehicle.heartbeat(mavlink.MAV_TYPE_FIXED_WING)
    b = vehicle.pack(vehicle.mav.attitude_encode(1, 0, 0.05, 0, 0, 0, 0))
    items = list(scan(a + b"\x01\xfd\x03" + b, Decoder()))
    assert [x if isinstance(x, int) else x[0] for x in items] == [a, 3, b]


def test_tlog_resynchronises_over_garbage_and_stops_at_a_cut(
    tmp_path: Path, vehicle: Codec
) -> None:
    packets = [
        vehicle.pack(vehicle.mav.attitude_encode(i, 0, 0.01 * i, 0, 0, 0, 0)) for i in range(50)
    ]
    path = tmp_path / "f.tlog"
    data = b""
    for i, p in enumerate(packets):
        data += tlog_record(1_700_000_000_000_000 + 20_000 * i, p)
        if i == 20:
            data += b"\xfd\xfe\x00" * 30  # garbage full of start markers between records
    path.write_bytes(data[:-5])  # cut inside the last record
    stats = TlogStats()
    records = list(read_tlog(path, stats))
    assert [r.packet for r in records] == packets[:-1]
    assert stats.junk_bytes == 90 and stats.truncated_tail
    times = [r.t_recv_us for r in records]
    assert times == sorted(times)

    (tmp_path / "text.tlog").write_bytes(b"not a tlog at all\n" * 400)
    with pytest.raises(TlogError):
        list(read_tlog(tmp_path / "text.tlog"))


def test_a_corrupt_receive_time_loses_no_record(tmp_path: Path, vehicle: Codec) -> None:
    """A flipped byte in a record's 8-byte receive time: 36 minutes later (within the day a
    recording may pause), 36 minutes earlier, years later. Each record's packet is kept,
    its time taken from the record before; every record after it is kept with its own
    time (a time 36 minutes ahead once made the next minutes of records look out of
    order, and all of them were skipped as garbage)."""
    packets = [
        vehicle.pack(vehicle.mav.attitude_encode(i, 0, 0.01 * i, 0, 0, 0, 0)) for i in range(60)
    ]
    times = [1_700_000_000_000_000 + 20_000 * i for i in range(60)]
    written = list(times)
    written[10] += 36 * 60 * 1_000_000
    written[25] -= 36 * 60 * 1_000_000
    written[40] ^= 0x20 << 48  # years later
    path = tmp_path / "t.tlog"
    path.write_bytes(b"".join(tlog_record(t, p) for t, p in zip(written, packets, strict=True)))
    stats = TlogStats()
    records = list(read_tlog(path, stats))
    assert [r.packet for r in records] == packets
    expect = [times[i - 1] if i in (10, 25, 40) else t for i, t in enumerate(times)]
    assert [r.t_recv_us for r in records] == expect
    assert (stats.bad_times, stats.time_jumps, stats.junk_bytes) == (3, 0, 0)


@pytest.mark.parametrize("shift_us", [-86_400_000_000, 2 * 86_400_000_000, -120_000_000])
def test_recordings_joined_into_one_file_are_read_whole(
    tmp_path: Path, vehicle: Codec, shift_us: int
) -> None:
    """Two recordings in one file (`cat` of two tlogs): the second a day earlier, two days
    later, or two minutes earlier than the first ended (the recorder's clock set back).
    The records after the jump agree with one another, so it is a new time base: every
    record kept with the time it was written with, and the jump counted."""
    packets = [
        vehicle.pack(vehicle.mav.attitude_encode(i, 0, 0.01 * i, 0, 0, 0, 0)) for i in range(40)
    ]
    times = [1_700_000_000_000_000 + 20_000 * i for i in range(20)]
    times += [times[-1] + shift_us + 20_000 * i for i in range(20)]
    path = tmp_path / "joined.tlog"
    path.write_bytes(b"".join(tlog_record(t, p) for t, p in zip(times, packets, strict=True)))
    stats = TlogStats()
    records = list(read_tlog(path, stats))
    assert [(r.t_recv_us, r.packet) for r in records] == list(zip(times, packets, strict=True))
    assert (stats.time_jumps, stats.bad_times, stats.junk_bytes) == (1, 0, 0)


def test_in_range_but_absurd_values_are_dropped_by_the_ranges_given(vehicle: Codec) -> None:
    """An 80 deg angle of attack is a number a float holds and no fixed wing flies; the
    decoder drops by the ranges it is given."""
    from gcs_estimator.config import load_config
    from gcs_estimator.ingest.telemetry.decode import ranges_of

    packet = vehicle.pack(vehicle.mav.aoa_ssa_encode(1, 80.0, 0.0))
    stats = DecodeStats()
    assert _decode(packet, stats) == Ignored() and stats.invalid_values == 1
    wide = {**ranges_of(load_config("noc_uav").data), Channel.ALPHA: (-1.5, 1.5)}
    decoded = decode_packet(Decoder(), packet, 1.0, LINK, DecodeStats(), wide)
    assert decoded is not None and isinstance(decoded.event, Sample)


def test_a_quadrotor_is_warned_about_and_system_ids_beyond_the_cap_are_counted() -> None:
    import io

    from gcs_estimator.ingest.telemetry.link import MavlinkLink

    log = io.StringIO()
    link = MavlinkLink(LinkConfig(max_vehicles=2), log=log)
    for sysid, mav_type in ((1, mavlink.MAV_TYPE_FIXED_WING), (2, 2), (3, 1), (4, 1)):
        codec = Codec(sysid, 1)
        assert (
            list(link.datagram(codec.heartbeat(mav_type), 1.0, ("127.0.0.1", 5000 + sysid))) == []
        )
    text = log.getvalue()
    assert "system id 2 says it is MAV_TYPE_QUADROTOR" in text
    assert "system id 1 says" not in text
    assert sorted(link.vehicles) == [1, 2]
    assert link.stats()["refused_vehicles"] == {"3": 1, "4": 1}
