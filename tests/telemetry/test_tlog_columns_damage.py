"""A replay through the run's columns (CompiledTlogSource, decision 0064) against the
record-by-record one (TlogSource), bit for bit in frames, counters, notes, errors and
records, on recordings damaged at random: flipped bytes, lost, reordered and copied
packets, a vehicle that reboots (its clock starts again), a second system id, junk
between records; and with signing on (where the columns are not taken)."""

from __future__ import annotations

import random
from pathlib import Path

import pytest

from gcs_estimator.config import load_config
from gcs_estimator.ingest.sources import TlogSource
from gcs_estimator.ingest.telemetry.mavlink import Codec, tlog_record
from gcs_estimator.ingest.telemetry.signing import load_key, sign_outgoing
from gcs_estimator.ingest.telemetry.tlog_fast import CompiledTlogSource
from tests.telemetry.test_tlog_compiled import SHORT, Records, _merged, _replay, _write
from tests.telemetry.test_tlog_compiled import flights as flights  # the module's fixture


def _rebooted(records: Records) -> Records:
    """The flight, then the same flight again right after it: the vehicle's clock goes
    back to its boot (a reboot), its sequence numbers start again."""
    span = records[-1][0] - records[0][0] + 1_000_000
    return records + [(t + span, p) for t, p in records]


def _random_damage(records: Records, seed: int) -> list[bytes]:
    rng = random.Random(seed)
    rate = rng.choice((0.002, 0.01, 0.03))
    out: list[bytes] = []
    for t, packet in records:
        r = rng.random
        if r() < rate:  # lost
            continue
        if r() < rate:  # a byte flipped anywhere in the packet (header, payload, CRC)
            bad = bytearray(packet)
            bad[rng.randrange(len(bad))] ^= 1 << rng.randrange(8)
            packet = bytes(bad)
        record = tlog_record(t, packet)
        if r() < rate / 4:  # junk between records
            out.append(bytes(rng.randrange(256) for _ in range(rng.randint(1, 30))))
        out.append(record)
        if r() < rate:  # a copy, now or a little later
            out.insert(len(out) - rng.randint(0, min(5, len(out) - 1)), record)
        if r() < rate and len(out) > 3:  # reordered
            k = rng.randint(2, 3)
            out[-1], out[-k] = out[-k], out[-1]
    return out


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_columns_replay_equals_python_replay_on_random_damage(
    tmp_path: Path, flights: dict[str, Records], seed: int
) -> None:
    config = load_config("noc_uav", SHORT)
    recs = _merged(_rebooted(flights["native1"]), flights["native2"], flights["arduplane"])
    path = _write(tmp_path / "f.tlog", _random_damage(recs, seed))
    python = _replay(TlogSource, path, config)
    columns = _replay(CompiledTlogSource, path, config)
    assert len(python["frames"]) > 1000
    assert columns == python
    stats = python["stats"]
    assert stats["lost"] and stats["duplicates"]
    assert any(v["clock_resets"] for v in stats["vehicles"].values())


def _signed(records: Records, key: bytes) -> Records:
    """The flight as its vehicle would send it signed (each sender its own stream)."""
    codecs: dict[tuple[int, int], Codec] = {}
    reader = Codec(255, 190)
    out: Records = []
    for t, packet in records:
        sender = (packet[5], packet[6])
        codec = codecs.get(sender)
        if codec is None:
            codec = codecs[sender] = Codec(*sender)
            sign_outgoing(codec.mav, key, t * 1e-6)
        codec.mav.seq = packet[4]
        out.append((t, bytes(reader.parse(packet)[0].pack(codec.mav))))
    return out


def test_a_signed_replay_takes_no_columns_and_equals_the_python_replay(
    tmp_path: Path, flights: dict[str, Records]
) -> None:
    key_file = tmp_path / "key.txt"
    key_file.write_text("5e" * 32)
    config = load_config("noc_uav", [*SHORT, f'link.signing_key_file="{key_file.as_posix()}"'])
    recs = _signed(flights["native1"], load_key(key_file))
    recs[100] = (recs[100][0], flights["native1"][100][1])  # one unsigned among them
    path = _write(tmp_path / "f.tlog", _random_damage(recs, 4))
    python = _replay(TlogSource, path, config)
    columns = _replay(CompiledTlogSource, path, config)
    assert columns == python
    assert len(python["frames"]) > 500 and python["stats"]["unsigned"] == 1
