"""The DataFlash reader against pymavlink's DFReader, on logs written here byte by byte."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from pymavlink import DFReader

from gcs_estimator.ingest.logs import dataflash
from tests.logs.dataflash_files import (
    IMU,
    DataFlashWriter,
    MessageType,
    arduplane_log,
    flight,
    text_log,
)

EVERY_TYPE = (
    MessageType(90, "ALL", "QbBhHiIfdnNZ", "TimeUS,b,B,h,H,i,I,f,d,n,N,Z"),
    MessageType(93, "ALL2", "QcCeELMq", "TimeUS,c,C,e,E,L,M,q"),
)


def _dfreader(path: Path, text: bool = False) -> dict[str, list[dict[str, object]]]:
    reader = DFReader.DFReader_text(str(path)) if text else DFReader.DFReader_binary(str(path))
    out: dict[str, list[dict[str, object]]] = {}
    while (m := reader.recv_msg()) is not None:
        out.setdefault(m.get_type(), []).append(m.to_dict())
    return out


def _same(log: dataflash.DataFlashLog, theirs: dict[str, list[dict[str, object]]]) -> int:
    """Assert every column of every type equals DFReader's; the values compared."""
    compared = 0
    for name, rows in theirs.items():
        if name == "FMT":
            continue
        table = log.table(name)
        for col in log.formats[name].columns:
            mine = table[col]
            want = [r[col] for r in rows]
            assert len(mine) == len(want), (name, col)
            if mine.dtype.kind == "S":
                assert [dataflash._text(bytes(v)) for v in mine] == [str(w) for w in want]
            else:
                np.testing.assert_allclose(
                    np.asarray(mine, float),
                    np.asarray(want, float),
                    rtol=1e-12,
                    err_msg=f"{name}.{col}",
                )
            compared += len(want)
    return compared


def test_every_format_character_reads_as_dfreader_reads_it(tmp_path: Path) -> None:
    w = DataFlashWriter()
    for t in EVERY_TYPE:
        w.define(t, units=False)
    rng = np.random.default_rng(3)
    for k in range(50):
        w.add(
            "ALL",
            [
                1000 * k, -5 + k, 200, -3000 + k, 60000, -(2**30) + k, 2**31 + k,
                float(rng.normal()), float(rng.normal()) * 1e6, "abcd", "sixteen chars ok",
                "a longer text " * 4,
            ],
        )  # fmt: skip
        w.add(
            "ALL2",
            [1000 * k, -12.34, 600.5, -123456.78, 98765.43, -35.1234567, k % 100, -(2**40) - k],
        )
    path = w.write(tmp_path / "all.bin")
    log = dataflash.read_bin(path)
    assert _same(log, _dfreader(path)) >= 50 * 20


def test_a_flight_log_with_damage_reads_as_dfreader_reads_it(tmp_path: Path) -> None:
    junk = b"\xa3\x95\xfe\x01\x02 damaged stretch \xa3"
    path = arduplane_log(tmp_path / "f.bin", flight(10.0), junk=junk)
    cut = b"\xa3\x95" + bytes([IMU.type]) + bytes(10)  # a record cut by the end of the file
    path.write_bytes(path.read_bytes() + cut)
    log = dataflash.read_bin(path)
    theirs = _dfreader(path)
    assert _same(log, theirs) > 10_000
    assert log.skipped_bytes == len(junk)
    assert log.truncated_bytes == len(cut)
    assert sorted(n for n in theirs if n != "FMT") == sorted(
        n for n in log.formats if n != "FMT" and len(log.table(n)["TimeUS"])
    )


def test_units_and_multipliers_come_from_the_log(tmp_path: Path) -> None:
    fl = flight(4.0)
    log = dataflash.read_bin(arduplane_log(tmp_path / "f.bin", fl))
    assert log.unit("ATT", "Pitch") == "deg"
    pitch = log.si("ATT", "Pitch")
    np.testing.assert_allclose(pitch, fl.theta, atol=math.radians(0.005))
    # a plain integer with a multiplier: XKF2's MN is int16 in milligauss (C = 1e-3)
    assert log.formats["XKF2"].multipliers[7] == "C"
    temp = log.si("ARSP", "Temp")  # 'c' in centi-degrees Celsius -> kelvin
    np.testing.assert_allclose(temp, 288.15, atol=1e-9)
    assert log.si("ATT", "TimeUS")[0] == pytest.approx(1.0)
    assert log.params()["SERVO2_FUNCTION"] == 19


def test_a_text_log_reads_as_the_binary_one(tmp_path: Path) -> None:
    path = arduplane_log(tmp_path / "f.bin", flight(2.0))
    binary = dataflash.read_bin(path)
    records: list[tuple[str, list[object]]] = []
    reader = DFReader.DFReader_binary(str(path))
    while (m := reader.recv_msg()) is not None:
        if m.get_type() != "FMT":
            d = m.to_dict()
            records.append((m.get_type(), [d[c] for c in binary.formats[m.get_type()].columns]))
    formats = [
        MessageType(f.type, f.name, f.format, ",".join(f.columns))
        for f in binary.formats.values()
        if f.name != "FMT"
    ]
    text = dataflash.read_text(text_log(tmp_path / "f.log", records, formats))
    for name in ("ATT", "IMU", "ARSP", "RCOU", "PARM"):
        for col in binary.formats[name].columns:
            a, b = binary.table(name)[col], text.table(name)[col]
            if a.dtype.kind == "S":
                assert [dataflash._text(bytes(v)) for v in a] == [v.decode() for v in b]
            else:
                np.testing.assert_allclose(np.asarray(a, float), np.asarray(b, float), rtol=1e-6)
    np.testing.assert_allclose(text.si("ATT", "Pitch"), binary.si("ATT", "Pitch"), rtol=1e-6)
    assert text.params() == pytest.approx(binary.params())


def test_a_file_without_fmt_is_refused_with_its_name(tmp_path: Path) -> None:
    path = tmp_path / "x.bin"
    path.write_bytes(b"\x00" * 1000)
    with pytest.raises(dataflash.DataFlashError, match=r"x\.bin: not a DataFlash log"):
        dataflash.read_bin(path)


def test_progress_reaches_the_end(tmp_path: Path) -> None:
    path = arduplane_log(tmp_path / "f.bin", flight(2.0))
    seen: list[float] = []
    dataflash.read_bin(path, seen.append)
    assert seen and seen[-1] == 1.0 and seen == sorted(seen)


def test_the_terminals_progress_line_ends_at_100(capsys: pytest.CaptureFixture[str]) -> None:
    from gcs_estimator.ingest.logs.reader import stderr_progress

    report = stderr_progress("reading f.bin")
    for fraction in (0.0, 0.004, 0.5, 0.5, 1.0):
        report(fraction)
    err = capsys.readouterr().err
    assert err == "\rreading f.bin:   0%\rreading f.bin:  50%\rreading f.bin: 100%\n"
