"""The struct fast path of mavlink.Decoder reads every message it handles exactly as
pymavlink does: field by field, header included, MAVLink 1 and 2, payloads trimmed of
trailing zeros, and it refuses what pymavlink refuses (bad CRC, wrong length). So does
decode.SampleReader, which goes from a packet straight to what it means."""

from __future__ import annotations

import math
import random
import struct
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as dialect

from gcs_estimator.config import load_config
from gcs_estimator.ingest.telemetry.decode import (
    Decoded,
    DecodeStats,
    SampleReader,
    decoded_message,
    ranges_of,
)
from gcs_estimator.ingest.telemetry.mavlink import FAST_MESSAGES, Decoder

SEED = 20261123
CASES_PER_MESSAGE = 300

_INT_RANGE = {
    "uint8_t": (0, 2**8 - 1),
    "int8_t": (-(2**7), 2**7 - 1),
    "uint16_t": (0, 2**16 - 1),
    "int16_t": (-(2**15), 2**15 - 1),
    "uint32_t": (0, 2**32 - 1),
    "int32_t": (-(2**31), 2**31 - 1),
    "uint64_t": (0, 2**64 - 1),
}


def _value(rng: random.Random, ftype: str) -> Any:
    """A random value of a field type; zeros often, so MAVLink 2 trims payloads."""
    if rng.random() < 0.3:
        return b"" if ftype == "char" else 0
    if ftype == "char":
        return bytes(rng.choice(b"abcXYZ_09") for _ in range(rng.randint(1, 10)))
    if ftype == "float":
        special = [math.nan, math.inf, -math.inf, 1e38, -0.0]
        x = rng.choice(special) if rng.random() < 0.1 else rng.uniform(-1e4, 1e4)
        return struct.unpack("<f", struct.pack("<f", x))[0]
    lo, hi = _INT_RANGE[ftype]
    return rng.randint(lo, hi)


def _packets(name: str, v1: bool) -> list[bytes]:
    rng = random.Random(f"{SEED}-{name}-{v1}")
    msgtype = dialect.mavlink_map[_id(name)]
    out = []
    for k in range(CASES_PER_MESSAGE):
        mav = dialect.MAVLink(None, srcSystem=rng.randint(1, 255), srcComponent=rng.randint(0, 255))
        mav.seq = k % 256
        msg = msgtype(*(_value(rng, ft) for ft in msgtype.fieldtypes))
        out.append(bytes(msg.pack(mav, force_mavlink1=v1)))
    return out


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a):
        return math.isnan(b)
    return bool(a == b) and type(a) is type(b)


def _reference(packet: bytes) -> Any:
    """pymavlink's own reading of a packet (None where it refuses it)."""
    mav = dialect.MAVLink(None, srcSystem=255, srcComponent=190)
    try:
        return mav.decode(bytearray(packet))
    except Exception:
        return None


def _id(name: str) -> int:
    return int(getattr(dialect, f"MAVLINK_MSG_ID_{name}"))


VERSIONS = [(name, False) for name in FAST_MESSAGES] + [
    (name, True)
    for name in FAST_MESSAGES
    if _id(name) <= 255  # MAVLink 1's ids are 8-bit
]


@pytest.mark.parametrize(("name", "v1"), VERSIONS)
def test_fast_path_reads_what_pymavlink_reads(name: str, v1: bool) -> None:
    msgtype = dialect.mavlink_map[_id(name)]
    decoder = Decoder()
    for packet in _packets(name, v1):
        assert Decoder._fast(packet) not in (None, False), "not taken by the fast path"
        ref, got = _reference(packet), decoder.decode(packet)
        assert ref is not None and got is not None
        assert got.get_type() == ref.get_type() == name
        assert (got.get_seq(), got.get_srcSystem(), got.get_srcComponent()) == (
            ref.get_seq(),
            ref.get_srcSystem(),
            ref.get_srcComponent(),
        )
        for field in msgtype.fieldnames:
            assert _same(getattr(ref, field), getattr(got, field)), (name, field)


@pytest.mark.parametrize("name", FAST_MESSAGES)
def test_fast_path_refuses_what_pymavlink_refuses(name: str) -> None:
    """One flipped bit anywhere after the start marker, or a byte missing: both refuse
    (pymavlink may still frame a changed length as another message; then the fast path
    hands the packet to it, so the two agree whatever it decides)."""
    rng = random.Random(f"{SEED}-bad-{name}")
    decoder = Decoder()
    for packet in _packets(name, v1=False)[:60]:
        bad = bytearray(packet)
        i = rng.randrange(1, len(bad))
        bad[i] ^= 1 << rng.randrange(8)
        for candidate in (bytes(bad), packet[:-1]):
            ref, got = _reference(candidate), decoder.decode(candidate)
            assert (ref is None) == (got is None), (name, candidate.hex())


def test_signed_packets_go_through_pymavlink() -> None:
    mav = dialect.MAVLink(None, srcSystem=7, srcComponent=1)
    mav.signing.secret_key = bytes(range(32))
    mav.signing.sign_outgoing = True
    packet = bytes(mav.attitude_encode(1234, 0.1, 0.2, 0.3, 0.0, 0.0, 0.0).pack(mav))
    assert packet[2] & 0x01, "the packet is signed"
    assert Decoder._fast(packet) is None
    msg = Decoder().decode(packet)
    assert msg is not None and msg.get_type() == "ATTITUDE" and msg.time_boot_ms == 1234


CHANNEL_MESSAGES = (
    "HIGHRES_IMU",
    "ATTITUDE",
    "AOA_SSA",
    "VFR_HUD",
    "SERVO_OUTPUT_RAW",
    "SCALED_PRESSURE",
    "NAMED_VALUE_FLOAT",
)
"""The messages decode.SampleReader reads straight from their packets."""

LINKS = {
    "default": (),
    "servo 9, thrust named, density from pressure": (
        "link.elevator_servo=9",
        "link.throttle_servo=0",
        'propulsion.model="measured"',
        "link.density_from_pressure=true",
        'link.qdot_name="a"',
        'link.thrust_name="Z_9"',
    ),
}


def _named_values(rng: random.Random, names: tuple[str, ...]) -> list[bytes]:
    """NAMED_VALUE_FLOATs under the names the link reads (random ones rarely are)."""
    out = []
    for k in range(CASES_PER_MESSAGE):
        mav = dialect.MAVLink(None, srcSystem=rng.randint(1, 255), srcComponent=1)
        mav.seq = k % 256
        value = _value(rng, "float")
        msg = dialect.MAVLink_named_value_float_message(k, rng.choice(names).encode(), value)
        out.append(bytes(msg.pack(mav, force_mavlink1=rng.random() < 0.5)))
    return out


@pytest.mark.parametrize("link_name", LINKS)
def test_sample_reader_means_what_the_decoded_message_means(link_name: str) -> None:
    """Every channel message, MAVLink 1 and 2, NaN, infinite and absurd values, trimmed
    payloads: the reader's meaning and its counts are decoded_message's of pymavlink's
    message (and of the fast path's)."""
    config = load_config("noc_uav", list(LINKS[link_name]))
    ranges = ranges_of(config.data)
    packets = _named_values(random.Random(SEED), ("QDOT", "THRUST", "a", "Z_9", "other"))
    for name in CHANNEL_MESSAGES:
        packets += _packets(name, v1=False) + (_packets(name, v1=True) if _id(name) <= 255 else [])
    ours, theirs, fast = DecodeStats(), DecodeStats(), DecodeStats()
    reader = SampleReader(config.link, ours, ranges)
    decoder = Decoder()
    meanings = set()
    for packet in packets:
        got = reader(packet, 12.5)
        assert isinstance(got, Decoded), packet.hex()
        ref = _reference(packet)
        assert ref is not None
        assert got == decoded_message(ref, packet, 12.5, config.link, theirs, ranges)
        light = decoder.decode(packet)
        assert got == decoded_message(light, packet, 12.5, config.link, fast, ranges)
        meanings.add(type(got.event).__name__)
    assert ours == theirs == fast
    assert meanings == {"Sample", "Ignored"}
    assert ours.invalid_values > 0 and ours.ignored_messages > 0


def test_sample_reader_refuses_what_the_decoder_refuses() -> None:
    """A flipped bit or a missing byte: the reader says False (CRC) only where the
    decoder refuses too, and hands over (None) what it cannot frame; a signed packet and
    a message it does not read go to the decoder."""
    rng = random.Random(f"{SEED}-reader")
    config = load_config("noc_uav")
    reader = SampleReader(config.link, DecodeStats(), ranges_of(config.data))
    decoder = Decoder()
    refused = 0
    for name in CHANNEL_MESSAGES:
        for packet in _packets(name, v1=False)[:60]:
            bad = bytearray(packet)
            bad[rng.randrange(1, len(bad))] ^= 1 << rng.randrange(8)
            for candidate in (bytes(bad), packet[:-1]):
                got = reader(candidate, 1.0)
                if got is False:
                    refused += 1
                    assert decoder.decode(candidate) is None, (name, candidate.hex())
                elif got is not None:
                    msg = decoder.decode(candidate)
                    assert msg is not None and msg.get_type() == name
    assert refused > 0
    mav = dialect.MAVLink(None, srcSystem=7, srcComponent=1)
    assert reader(bytes(mav.heartbeat_encode(1, 3, 0, 0, 4).pack(mav)), 1.0) is None
    mav.signing.secret_key = bytes(range(32))
    mav.signing.sign_outgoing = True
    signed = bytes(mav.attitude_encode(1234, 0.1, 0.2, 0.3, 0.0, 0.0, 0.0).pack(mav))
    assert reader(signed, 1.0) is None
