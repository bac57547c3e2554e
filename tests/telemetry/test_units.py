"""The telemetry edge piece by piece: decode, synchroniser, link health, tlog framing.

Real pymavlink encoding (MAVLink 2, ardupilotmega) throughout; no sockets here (the link
end to end is test_link.py).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gcs_estimator import atmosphere
from gcs_estimator.config import LinkConfig
from gcs_estimator.model.channels import Channel
from gcs_estimator.telemetry import mavlink, pwm
from gcs_estimator.telemetry.decode import (
    CommandAck,
    DecodeStats,
    Heartbeat,
    Ignored,
    Sample,
    decode_packet,
)
from gcs_estimator.telemetry.mavlink import (
    Codec,
    Decoder,
    TlogError,
    TlogStats,
    read_tlog,
    split_packets,
    tlog_record,
)
from gcs_estimator.telemetry.sync import LinkHealth, Synchronizer

LINK = LinkConfig()


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
    assert dict(att.values) == pytest.approx({Channel.THETA: 0.05})
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
    np.testing.assert_allclose(frames[0].inputs, [0.01, 0.3, expected])


def test_link_events_and_what_carries_nothing(vehicle: Codec) -> None:
    mav = vehicle.mav
    stats = DecodeStats()
    assert _decode(vehicle.heartbeat(mavlink.MAV_TYPE_FIXED_WING)) == Heartbeat(False)
    assert _decode(Codec(255, 190).heartbeat(mavlink.MAV_TYPE_GCS)) == Heartbeat(True)
    ack = vehicle.command_ack(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAV_RESULT_ACCEPTED)
    assert _decode(ack) == CommandAck(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0)
    assert _decode(vehicle.pack(mav.named_value_float_encode(1, b"OTHER", 1.0)), stats) == Ignored()
    assert _decode(vehicle.pack(mav.system_time_encode(1, 1)), stats) == Ignored()
    assert stats.ignored_messages == 2


def test_bad_values_are_counted_and_dropped_bad_packets_are_none(vehicle: Codec) -> None:
    mav = vehicle.mav
    stats = DecodeStats()
    assert _decode(vehicle.pack(mav.vfr_hud_encode(math.nan, 0, 0, 0, 0, 0)), stats) == Ignored()
    assert _decode(vehicle.pack(mav.aoa_ssa_encode(1, 500.0, 0)), stats) == Ignored()
    assert stats.invalid_values == 2
    packet = bytearray(vehicle.pack(mav.attitude_encode(1, 0, 0.05, 0, 0, 0, 0)))
    packet[-1] ^= 0xFF  # CRC
    assert _decode(bytes(packet)) is None
    assert _decode(bytes(packet[:-4])) is None  # truncated


# ------------------------------------------------------------------ synchroniser


def _sample(t: float | None, t_recv: float, **values: float) -> Sample:
    return Sample(1, "test", t, t_recv, tuple((Channel[k.upper()], v) for k, v in values.items()))


OBS = {"v": 24.0, "alpha": 0.05, "theta": 0.05, "q": 0.0, "qdot": 0.0, "ax": 0.1, "az": -9.8}


def test_a_frame_is_emitted_once_complete_with_the_inputs_held() -> None:
    sync = Synchronizer(1, LINK)
    assert sync.add(_sample(1.0, 10.0, elevator=0.01, power=0.3)) == []
    out = []
    for k, v in OBS.items():
        out += sync.add(_sample(1.0, 10.0, **{k: v}))
    assert len(out) == 1
    frame = out[0]
    # No air density came: NaN, and the estimator flies the airframe's constant.
    np.testing.assert_array_equal(frame.inputs, [0.01, 0.3, np.nan])
    np.testing.assert_array_equal(frame.y, list(OBS.values()))
    assert frame.t_vehicle_s == 1.0 and not frame.clock_reset
    assert sync.stats.frames == 1 and sync.stats.partial_frames == 0


def test_partial_frames_close_on_the_next_time_or_after_the_wait() -> None:
    sync = Synchronizer(1, LINK)
    sync.add(_sample(1.0, 10.0, elevator=0.0, power=0.3))
    assert sync.add(_sample(1.0, 10.0, v=24.0)) == []
    closed = sync.add(_sample(1.02, 10.02, theta=0.05))  # a later vehicle time
    assert len(closed) == 1 and np.isnan(closed[0].y[Channel.ALPHA])
    assert sync.poll(10.02 + LINK.max_wait_s / 2) == []
    waited = sync.poll(10.02 + LINK.max_wait_s * 1.01)
    assert len(waited) == 1 and waited[0].y[Channel.THETA] == 0.05
    assert sync.stats.partial_frames == 2


def test_late_untimed_reset_and_frames_before_inputs() -> None:
    sync = Synchronizer(1, LINK)
    assert sync.add(_sample(1.0, 10.0, v=24.0)) == []
    assert sync.flush() == []  # no inputs yet: nothing to estimate with
    assert sync.stats.waiting_for_inputs == 1
    sync.add(_sample(2.0, 11.0, elevator=0.0, power=0.3))
    sync.add(_sample(None, 11.0, v=25.0))  # untimed: joins the open frame
    (frame,) = sync.flush()
    assert frame.y[Channel.V] == 25.0
    assert sync.add(_sample(1.999, 11.1, alpha=0.1)) == []  # older than the last frame
    assert sync.stats.late_samples == 1
    sync.add(_sample(0.1, 12.0, alpha=0.1))  # the clock went back: a reboot
    (after,) = sync.flush()
    assert after.clock_reset and sync.stats.clock_resets == 1


# ------------------------------------------------------------------ link health


def test_sequence_numbers_wrap_at_256() -> None:
    h = LinkHealth()
    for seq in [*range(250, 256), *range(0, 5)]:
        assert h.on_packet(1, 1, seq)
    assert h.lost == 0 and h.received == 11
    assert h.on_packet(1, 1, 8)  # 5, 6, 7 lost
    assert h.lost == 3
    assert not h.on_packet(1, 1, 8)  # duplicate, dropped
    assert h.duplicates == 1 and h.received == 12
    assert h.on_packet(1, 1, 6)  # one counted lost arrived late
    assert h.out_of_order == 1 and h.lost == 2


@settings(max_examples=200, deadline=None)
@given(
    start=st.integers(0, 255),
    gaps=st.lists(st.integers(1, 127), min_size=1, max_size=300),
    other=st.booleans(),
)
def test_losses_counted_exactly_for_any_gaps_below_half_the_sequence_space(
    start: int, gaps: list[int], other: bool
) -> None:
    """Gaps of 1..127 (0..126 packets lost at a time), across any number of wraps, per
    (system, component): the count equals the packets not seen."""
    h = LinkHealth()
    seq = start
    h.on_packet(1, 1, seq)
    if other:
        h.on_packet(2, 1, 0)  # another vehicle's numbering is its own
    for gap in gaps:
        seq = (seq + gap) % 256
        assert h.on_packet(1, 1, seq)
    assert h.lost == sum(g - 1 for g in gaps)
    assert h.received == 1 + len(gaps) + other


# ------------------------------------------------------------------ tlog framing


def test_a_datagram_splits_into_packets_skipping_junk(vehicle: Codec) -> None:
    a = vehicle.heartbeat(mavlink.MAV_TYPE_FIXED_WING)
    b = vehicle.pack(vehicle.mav.attitude_encode(1, 0, 0.05, 0, 0, 0, 0))
    packets, junk = split_packets(a + b"\x01\x02\x03" + b)
    assert packets == [a, b] and junk == 3


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
