"""A run's channel messages decoded on columns (SampleReader.columns, decision 0064) are
what SampleReader.of_fields makes of each record: the same Sample, bit for bit, where
every value is finite and in range, and where one is not the record goes to of_fields
(which counts what it drops); and a replay through the columns (CompiledTlogSource) is
the record-by-record one (TlogSource) on flights with absurd values, a ground station's
channel messages and a second system id."""

from __future__ import annotations

import math
import random
import struct
from pathlib import Path
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as dialect

from gcs_estimator.config import load_config
from gcs_estimator.ingest.sources import TlogSource
from gcs_estimator.ingest.telemetry.decode import DEG_TO_RAD, DecodeStats, Sample, SampleReader
from gcs_estimator.ingest.telemetry.mavlink import TlogStats
from gcs_estimator.ingest.telemetry.tlog_fast import (
    COLUMNS_MIN,
    CompiledTlogSource,
    _columns,
    _with_text,
    read_runs,
    table_of,
)
from tests.telemetry.test_fast_decode import _value
from tests.telemetry.test_tlog_compiled import T0_US, Records, _replay, _write
from tests.telemetry.test_tlog_compiled import flights as flights  # the module's fixture

PACKETS = 400


def _plausible(rng: random.Random, ftype: str) -> Any:
    """Mostly values a flight has (so that whole samples pass), else any (test_fast_decode's:
    zeros, NaN, infinities, absurd magnitudes)."""
    if ftype == "char" and rng.random() < 0.7:
        return rng.choice((b"QDOT", b"THRUST"))  # the link's names: channels
    if rng.random() < 0.15 or ftype == "char":
        return _value(rng, ftype)
    if ftype == "float":
        return struct.unpack("<f", struct.pack("<f", rng.uniform(-1.0, 1.0)))[0]
    if ftype in ("uint8_t", "int8_t"):
        return rng.randint(0, 1)
    return rng.randint(0, 2000)


def _packets(name: str, seed: int) -> list[bytes]:
    rng = random.Random(f"{seed}-{name}")
    msgtype = dialect.mavlink_map[int(getattr(dialect, f"MAVLINK_MSG_ID_{name}"))]
    out = []
    for k in range(PACKETS):
        mav = dialect.MAVLink(None, srcSystem=rng.choice((1, 2, 255)), srcComponent=1)
        mav.seq = k % 256
        msg = msgtype(*(_plausible(rng, ft) for ft in msgtype.fieldtypes))
        out.append(bytes(msg.pack(mav, force_mavlink1=rng.random() < 0.2 and msgtype.id < 256)))
    return out


def test_columns_give_of_fields_samples_bit_for_bit(tmp_path: Path) -> None:
    config = load_config("noc_uav")
    table = table_of(config.link)
    whole = dropped = 0
    read: set[str] = set()
    for msg in table.messages:
        records = [(T0_US + 1000 * k, p) for k, p in enumerate(_packets(msg.name, 7))]
        path = _write(tmp_path / f"{msg.name}.tlog", records)
        for run in read_runs(path, TlogStats(), table):
            reader = SampleReader(config.link, DecodeStats())
            got = _columns(run, table, reader)
            assert (got is None) == (len(run.status) < COLUMNS_MIN)
            if got is None:
                continue
            which, row = got
            for j, status in enumerate(run.status):
                if status < 0:
                    assert which[j] is None
                    continue
                packet = run.data[run.starts[j] : run.ends[j]]
                fields: Any = run.fields(j, msg.count)
                if msg.texts:
                    fields = _with_text(packet, msg, fields)
                stats = DecodeStats()
                ref = SampleReader(config.link, stats).of_fields(
                    msg.msgid, run.seq[j], run.system_id[j], 1, fields, run.times[j] * 1e-6
                )
                c = which[j]
                sample = None if c is None else c.sample(row[j])
                if sample is not None:
                    whole += 1
                    read.add(msg.name)
                    assert sample == ref.event
                    assert _bits(sample) == _bits(ref.event)
                    assert stats == DecodeStats()
                elif c is not None:  # read on columns, not whole: of_fields drops something
                    dropped += 1
                    assert stats != DecodeStats()
    assert whole > 1000 and dropped > 100
    assert read == {m.name for m in table.messages} - {"SCALED_PRESSURE"}


def _bits(sample: Sample) -> tuple[Any, ...]:
    """A sample with its floats as their bits (-0.0 and 0.0 apart, NaN equal to itself)."""

    def b(x: Any) -> Any:
        return struct.pack("<d", x) if isinstance(x, float) else x

    return (
        *sample[:4],
        tuple((ch, b(v)) for ch, v in sample.values),
        sample.wrap_s,
        tuple((k, b(v)) for k, v in sample.aux),
        tuple(b(v) for v in sample.outputs),
    )


def test_degrees_to_radians_is_math_radians_bit_for_bit() -> None:
    rng = random.Random(3)
    xs = [rng.uniform(-1e6, 1e6) for _ in range(20_000)] + [0.0, -0.0, 1e308, -1e-320]
    assert all(math.radians(x) == x * DEG_TO_RAD for x in xs)
    assert math.isnan(math.nan * DEG_TO_RAD) and math.radians(math.inf) == math.inf * DEG_TO_RAD


def _spoiled(records: Records) -> Records:
    """A flight with absurd and NaN values in channel messages, channel messages from a
    ground station (system id 255) and from a second vehicle (system id 2)."""
    out: Records = []
    names = ("ATTITUDE", "HIGHRES_IMU", "VFR_HUD", "AOA_SSA", "SERVO_OUTPUT_RAW")
    extra = {n: _packets(n, 99) for n in names}
    for k, (t, packet) in enumerate(records):
        out.append((t, packet))
        if k % 7 == 3:
            name = names[k % len(names)]
            out.append((t + 1, extra[name][k % PACKETS]))
    return out


@pytest.mark.parametrize("flight", ["native1", "arduplane"])
def test_a_replay_on_columns_is_the_python_replay_with_spoiled_values(
    tmp_path: Path, flights: dict[str, Records], flight: str
) -> None:
    config = load_config("noc_uav", ["simulation.manoeuvre.duration_s=12"])
    path = _write(tmp_path / "f.tlog", _spoiled(flights[flight]))
    python = _replay(TlogSource, path, config)
    columns = _replay(CompiledTlogSource, path, config)
    assert len(python["frames"]) > 500
    assert python["stats"]["invalid_values"] > 0
    assert columns == python
