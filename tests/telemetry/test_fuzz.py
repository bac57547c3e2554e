"""Fuzz the edge: 100,000 datagrams of valid packets mixed with junk (start markers,
truncated and corrupted packets) lose no valid packet and take none that is not; a tlog
with garbage between its records keeps every record after it."""

from __future__ import annotations

import random
from pathlib import Path

import pytest

from gcs_estimator.ingest.telemetry.mavlink import (
    STX_V1,
    STX_V2,
    Codec,
    Decoder,
    TlogStats,
    is_unknown,
    read_tlog,
    scan,
    tlog_record,
)

CASES = 100_000
SEED = 20261122


def _pool() -> list[bytes]:
    """Valid packets of every kind the vehicle sends, MAVLink 2 and 1, of varied lengths."""
    v = Codec(1, 1)
    m = v.mav
    out = []
    for k in range(40):
        t = 5_000_000 + 20_000 * k
        out += [
            v.heartbeat(1),
            v.pack(m.attitude_encode(t // 1000, 0.01 * k, 0.05, 0.0, 0.0, 0.1, 0.0)),
            v.pack(m.highres_imu_encode(t, 0.1, 0, -9.8, 0, 0.01 * k, 0, *(0.0,) * 7, 31)),
            v.pack(m.servo_output_raw_encode(t, 0, *([1500 + k] * 16))),
            v.pack(m.aoa_ssa_encode(t, 2.0 + 0.1 * k, 0.0)),
            v.pack(m.vfr_hud_encode(24.0 + k, 24.0, 0, 50, 100.0, 0.0)),
            v.pack(m.named_value_float_encode(t // 1000, b"QDOT", 0.01 * k)),
        ]
    v1 = Codec(2, 1)
    v1.mav.WIRE_PROTOCOL_VERSION = "1.0"
    out += [v1.pack(v1.mav.attitude_encode(k, 0, 0.01 * k, 0, 0, 0, 0)) for k in range(20)]
    return out


def _junk(rng: random.Random, pool: list[bytes]) -> bytes:
    kind = rng.randrange(5)
    if kind == 0:  # random bytes, a third of them start markers
        return bytes(
            rng.choice((STX_V2, STX_V1, rng.randrange(256))) for _ in range(rng.randint(1, 40))
        )
    if kind == 1:  # a packet cut short
        p = rng.choice(pool)
        return p[: rng.randint(1, len(p) - 1)]
    if kind == 2:  # a packet with one byte changed (the CRC fails)
        changed = bytearray(rng.choice(pool))
        i = rng.randrange(1, len(changed))
        changed[i] ^= rng.randint(1, 255)
        return bytes(changed)
    if kind == 3:  # a run of start markers
        return bytes([STX_V2]) * rng.randint(1, 300)
    return bytes(rng.randrange(256) for _ in range(rng.randint(1, 12)))


def test_fuzzed_datagrams_lose_no_valid_packet() -> None:
    """Every valid packet comes out, in order, and no known message that was not sent.
    (Junk that happens to frame an unknown message id cannot be checked: it comes out as
    an unknown message, which the link counts and skips.)"""
    rng = random.Random(SEED)
    pool = _pool()
    decoder = Decoder()
    lost = invented = unknown = 0
    for _ in range(CASES):
        parts: list[bytes] = []
        sent: list[bytes] = []
        for _ in range(rng.randint(1, 3)):
            if rng.random() < 0.6:
                parts.append(_junk(rng, pool))
            p = rng.choice(pool)
            parts.append(p)
            sent.append(p)
        if rng.random() < 0.5:
            parts.append(_junk(rng, pool))
        found = [item for item in scan(b"".join(parts), decoder) if not isinstance(item, int)]
        got = [p for p, msg in found if not is_unknown(msg)]
        unknown += len(found) - len(got)
        if got != sent:
            remaining = iter(got)
            missing = sum(1 for p in sent if p not in remaining)
            lost += missing
            invented += len(got) - (len(sent) - missing)
    assert (lost, invented) == (0, 0)
    assert unknown < 0.05 * CASES


@pytest.mark.parametrize("garbage", [b"\xfd" * 300, b"\xfe\x00\xfd" * 100, bytes(range(256))])
def test_a_tlog_keeps_every_record_after_garbage(tmp_path: Path, garbage: bytes) -> None:
    pool = _pool()
    path = tmp_path / "g.tlog"
    data = bytearray()
    for i, p in enumerate(pool):
        data += tlog_record(1_700_000_000_000_000 + 3_000 * i, p)
        if i == 100:
            data += garbage
    path.write_bytes(bytes(data))
    stats = TlogStats()
    records = list(read_tlog(path, stats))
    assert [r.packet for r in records] == pool
    assert stats.junk_bytes == len(garbage) and not stats.truncated_tail


@pytest.mark.parametrize("junk", [b"\x00\x11\x22", b"\xfd\x05", b"\xfe" * 7, bytes(range(40))])
def test_a_tlog_record_keeps_its_packet_after_junk_before_it(tmp_path: Path, junk: bytes) -> None:
    """Junk between a record's time and its packet: the packet is kept with that time (as
    a live link's scan skips junk before a packet), the junk counted."""
    pool = _pool()
    path = tmp_path / "j.tlog"
    data = bytearray()
    damaged = 0
    for i, p in enumerate(pool):
        record = tlog_record(1_700_000_000_000_000 + 3_000 * i, p)
        if i % 20 == 10:
            record = record[:8] + junk + record[8:]
            damaged += 1
        data += record
    path.write_bytes(bytes(data))
    stats = TlogStats()
    records = list(read_tlog(path, stats))
    assert [r.packet for r in records] == pool
    assert [r.t_recv_us for r in records] == [
        1_700_000_000_000_000 + 3_000 * i for i in range(len(pool))
    ]
    assert stats.junk_bytes == damaged * len(junk) and damaged == 15
