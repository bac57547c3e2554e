"""The compiled tlog reader (tlog_kernel, tlog_fast) against the Python one it speeds up:
the same records and reading statistics as mavlink.read_tlog, the same fields as
SampleReader, and a replay with bit for bit the same frames, link counters and notes as
TlogSource's, on the simulator's own tlogs (its native message set and ArduPlane's, two
vehicles, a 32-bit clock wrapping) and on damaged ones (junk, corrupt CRCs, truncation,
copies, reordered and lost packets, corrupt receive times, a clock jump, unknown ids,
MAVLink 1)."""

from __future__ import annotations

import io
import random
from pathlib import Path
from typing import Any

import pytest

from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.frames import Frame
from gcs_estimator.ingest.sources import TlogSource
from gcs_estimator.ingest.telemetry.decode import WRAP_US32_S, Decoded, DecodeStats, SampleReader
from gcs_estimator.ingest.telemetry.link import MavlinkLink
from gcs_estimator.ingest.telemetry.mavlink import (
    Codec,
    TlogError,
    TlogStats,
    read_tlog,
    tlog_record,
)
from gcs_estimator.ingest.telemetry.tlog_fast import (
    CompiledTlogSource,
    Run,
    _with_text,
    read_runs,
    table_of,
)
from gcs_estimator.ingest.telemetry.tlog_kernel import BAD_CRC, OTHER
from gcs_estimator.stop import Stop
from sim import cli as sim_cli
from tests.telemetry.test_fast_decode import _packets

SHORT = ["simulation.manoeuvre.duration_s=12"]
T0_US = 1_700_000_000_000_000
PACKETS = 60
"""Random packets of each message and version."""

Records = list[tuple[int, bytes]]


def _records(path: Path) -> Records:
    return [(r.t_recv_us, r.packet) for r in read_tlog(path)]


def _write(path: Path, records: Records | list[bytes]) -> Path:
    path.write_bytes(b"".join(r if isinstance(r, bytes) else tlog_record(*r) for r in records))
    return path


@pytest.fixture(scope="module")
def flights(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Records]:
    """The simulator's tlogs: two native vehicles up for 4,290 s (their 32-bit servo
    clocks wrap 5 s in) and one ArduPlane vehicle streaming what a station asks for."""
    folder = tmp_path_factory.mktemp("flights")
    common = ["--speed", "0", "--target", "127.0.0.1:9", *[f"--set={s}" for s in SHORT]]
    wrap = str(WRAP_US32_S - 5.0)
    assert (
        sim_cli.main([*common, "--tlog", str(folder / "n"), "--vehicles", "2", "--boot-s", wrap])
        == 0
    )
    assert (
        sim_cli.main([*common, "--tlog", str(folder / "a"), "--autopilot", "arduplane", "--asked"])
        == 0
    )
    return {
        "native1": _records(folder / "n_1.tlog"),
        "native2": _records(folder / "n_2.tlog"),
        "arduplane": _records(folder / "a_1.tlog"),
    }


def _merged(*streams: Records) -> Records:
    return sorted((r for s in streams for r in s), key=lambda r: r[0])


def _v1(packet: bytes) -> bytes | None:
    """The same message as MAVLink 1 (where its id fits), from the same sender."""
    codec = Codec(packet[5], packet[6])
    msgs = codec.parse(packet)
    if not msgs or msgs[0].get_msgId() > 255:
        return None
    codec.mav.seq = packet[4]
    return bytes(msgs[0].pack(codec.mav, force_mavlink1=True))


def _damaged(records: Records) -> list[bytes]:  # noqa: C901 - one kind of damage a branch
    """Every kind of damage a recording meets, each several times over the flight."""
    rng = random.Random(20261127)
    out: list[bytes] = []
    jump = 0
    n = len(records)
    for k, (t, packet) in enumerate(records):
        if k == n // 2:
            jump = 2 * 3600 * 1_000_000  # recordings joined: the clock jumps 2 h
        t += jump
        if k % 97 == 13:  # a corrupt CRC
            bad = bytearray(packet)
            bad[rng.randrange(10, len(bad))] ^= 0x10
            packet = bytes(bad)
        elif k % 211 == 7:  # a packet cut short
            packet = packet[: len(packet) - 3]
        elif k % 173 == 5:  # an id unknown to the dialect
            bad = bytearray(packet)
            bad[7:10] = (60_000).to_bytes(3, "little")
            packet = bytes(bad)
        elif k % 151 == 3:
            packet = _v1(packet) or packet
        record = tlog_record(t, packet)
        if k % 89 == 11:  # a corrupt receive time
            record = tlog_record(t + 36 * 60 * 1_000_000, packet)
        if k % 131 == 17:  # junk between the time and the packet
            record = record[:8] + bytes(rng.randrange(256) for _ in range(7)) + record[8:]
        if k % 229 == 19:  # garbage between records, start markers in it
            out.append(bytes(rng.choice((0xFD, 0xFE, rng.randrange(256))) for _ in range(41)))
        if k % 313 == 23:  # lost
            continue
        out.append(record)
        if k % 257 == 29:  # a copy
            out.append(record)
        if k % 181 == 31 and len(out) > 2:  # reordered
            out[-1], out[-2] = out[-2], out[-1]
    last = out.pop()
    out.append(last[: len(last) // 2])  # a truncated tail
    return out


def _cases(flights: dict[str, Records]) -> dict[str, Records | list[bytes]]:
    two = _merged(flights["native1"], flights["native2"])
    return {
        "native": flights["native1"],
        "arduplane": flights["arduplane"],
        "two vehicles, clocks wrapping": two,
        "damaged native and arduplane": _damaged(_merged(flights["native2"], flights["arduplane"])),
        "damaged two vehicles": _damaged(two),
    }


CASES = [
    "native",
    "arduplane",
    "two vehicles, clocks wrapping",
    "damaged native and arduplane",
    "damaged two vehicles",
]


def _frame(f: Frame) -> tuple[Any, ...]:
    return (
        f.system_id,
        f.t_vehicle_s,
        f.t_recv_s,
        f.inputs.tobytes(),
        f.y.tobytes(),
        f.clock_reset,
        f.inputs_known,
    )


def _replay(cls: type[TlogSource], path: Path, config: AircraftConfig) -> dict[str, Any]:
    link = MavlinkLink(config.link, log=io.StringIO())
    log = io.StringIO()
    source = cls([path], link, log=log)
    frames = [_frame(f) for f in source.frames(Stop()) if f is not None]
    assert isinstance(link.log, io.StringIO)
    return {
        "frames": frames,
        "stats": source.link_stats(),
        "notes": link.log.getvalue() + log.getvalue(),
        "errors": source.errors,
        "records": source.done,
    }


@pytest.mark.parametrize("case", CASES)
def test_a_compiled_replay_is_the_python_replay_bit_for_bit(
    tmp_path: Path, flights: dict[str, Records], case: str
) -> None:
    config = load_config("noc_uav", SHORT)
    path = _write(tmp_path / "f.tlog", _cases(flights)[case])
    python = _replay(TlogSource, path, config)
    compiled = _replay(CompiledTlogSource, path, config)
    assert len(python["frames"]) > 500
    assert compiled == python
    if case.startswith("damaged"):
        counts = python["stats"]
        assert counts["corrupt"] and counts["duplicates"] and counts["unknown"]
        assert counts["lost"] and counts["out_of_order"]
        for note in ("garbage bytes", "corrupt receive time", "clock jumped", "truncated"):
            assert note in python["notes"], note
    if case == "two vehicles, clocks wrapping":
        assert [v["clock_wraps"] for v in python["stats"]["vehicles"].values()] == [1, 1]


def _runs_records(path: Path, stats: TlogStats) -> Records:
    out: Records = []
    for run in read_runs(path, stats, table_of(load_config("noc_uav").link)):
        for start, end, t in zip(run.starts, run.ends, run.times, strict=True):
            out.append((t, run.data[start:end]))
    return out


@pytest.mark.parametrize("case", CASES)
def test_the_records_and_their_statistics_are_read_tlogs(
    tmp_path: Path, flights: dict[str, Records], case: str
) -> None:
    path = _write(tmp_path / "f.tlog", _cases(flights)[case])
    ref_stats, stats = TlogStats(), TlogStats()
    assert _runs_records(path, stats) == [
        (r.t_recv_us, r.packet) for r in read_tlog(path, ref_stats)
    ]
    assert stats == ref_stats


@pytest.mark.parametrize(
    "garbage", [b"\xfd" * 300, b"\xfe\x00\xfd" * 100, bytes(range(256)), b"\x00" * 5000]
)
def test_garbage_before_between_and_instead_of_records(tmp_path: Path, garbage: bytes) -> None:
    """Garbage at the start, between records and as the whole file: the same records,
    statistics and refusal as read_tlog."""
    codec = Codec(1, 1)
    packets = [
        codec.pack(codec.mav.attitude_encode(k, 0, 0.01 * k, 0, 0, 0, 0)) for k in range(300)
    ]
    records = [tlog_record(T0_US + 20_000 * k, p) for k, p in enumerate(packets)]
    for name, parts in (
        ("middle", [*records[:100], garbage, *records[100:]]),
        ("start", [garbage, *records]),
        ("only", [garbage]),
    ):
        path = _write(tmp_path / f"{name}.tlog", parts)
        ref_stats, stats = TlogStats(), TlogStats()
        try:
            ref: Records | str = [(r.t_recv_us, r.packet) for r in read_tlog(path, ref_stats)]
        except TlogError as exc:
            ref = str(exc)
        try:
            got: Records | str = _runs_records(path, stats)
        except TlogError as exc:
            got = str(exc)
        assert got == ref and stats == ref_stats, name


def _decoded(reader: SampleReader, run: Run, table: Any) -> Decoded | bool | None:
    status = run.status[0]
    if status == BAD_CRC:
        return False
    if status == OTHER:
        return None
    msg = table.messages[status]
    packet = run.data[run.starts[0] : run.ends[0]]
    fields: Any = run.fields(0, msg.count)
    if msg.texts:
        fields = _with_text(packet, msg, fields)
    return reader.of_fields(
        msg.msgid, run.seq[0], run.system_id[0], run.component_id[0], fields, 1.0
    )


def test_the_kernel_reads_every_channel_message_as_sample_reader_does(tmp_path: Path) -> None:
    """Random values in every field of every message the link reads channels from,
    MAVLink 2 (payloads trimmed of trailing zeros) and 1, and each with a bit flipped:
    the kernel's fields give what SampleReader gives of the packet (its CRC refused
    alike; what it leaves to pymavlink left alike)."""
    config = load_config("noc_uav")
    table = table_of(config.link)
    rng = random.Random(5)
    checked = expected = 0
    for msg in table.messages:
        versions = (False, True) if msg.msgid <= 255 else (False,)
        for v1 in versions:
            expected += 2 * PACKETS
            for packet in _packets(msg.name, v1)[:PACKETS]:
                bad = bytearray(packet)
                bad[rng.randrange(1, len(bad))] ^= 1 << rng.randrange(8)
                for p in (packet, bytes(bad)):
                    path = _write(tmp_path / "one.tlog", [(T0_US, p)])
                    try:
                        runs = list(read_runs(path, TlogStats(), table))
                    except TlogError:  # the flipped bit changed the length: no record
                        continue
                    if len(runs) != 1 or len(runs[0].status) != 1:
                        continue  # the flipped bit changed the length: not one record
                    ref = SampleReader(config.link, DecodeStats())(p, 1.0)
                    got = _decoded(SampleReader(config.link, DecodeStats()), runs[0], table)
                    assert got == ref, (msg.name, v1, p.hex())
                    checked += 1
    assert checked > 0.9 * expected
