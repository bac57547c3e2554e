"""ArduPilot DataFlash logs, binary (.bin) and text (.log), read as arrays per message type.

A binary log is a run of records, each `0xA3 0x95 TYPE` and then the fields of TYPE as
its FMT record says (libraries/AP_Logger/LogStructure.h). The FMT records come in the
log, each before the first record of its type; FMT itself is type 128, 89 bytes.

Reading is two passes over bytes, never a Python object per record:
1. `_scan` (compiled) walks the records once, learning each type's length from the FMT
   records as it meets them, and keeps every record's offset and type. Bytes that do
   not start a record of a known type (a damaged stretch) are skipped one by one and
   counted, as pymavlink's DFReader does; a record cut by the end of the file is dropped.
2. For each message type a reader asks for, `_gather` copies its records' bytes into one
   block that numpy views as a structured array built from the type's format string.

Values come out as pymavlink's DFReader gives them (c, C, e, E scaled by 0.01, L by
1e-7); `si` then applies the log's own units and multipliers (FMTU, UNIT and MULT
records) and turns degrees into radians and Celsius into kelvin.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numba
import numpy as np
from numpy.typing import NDArray

from gcs_estimator.arrays import FloatArray
from gcs_estimator.ingest.flightdata import FlightDataError

HEAD = (0xA3, 0x95)
FMT_TYPE = 128
FMT_LENGTH = 89

TYPE_CODES: dict[str, str | tuple[str, tuple[int]]] = {
    "a": ("<i2", (32,)),
    "b": "i1",
    "B": "u1",
    "h": "<i2",
    "H": "<u2",
    "i": "<i4",
    "I": "<u4",
    "f": "<f4",
    "d": "<f8",
    "g": "<f2",
    "n": "S4",
    "N": "S16",
    "Z": "S64",
    "c": "<i2",
    "C": "<u2",
    "e": "<i4",
    "E": "<u4",
    "L": "<i4",
    "M": "u1",
    "q": "<i8",
    "Q": "<u8",
}
"""Format characters (LogStructure.h) as numpy types: records are packed, little-endian."""

IMPLIED_SCALE = {"c": 0.01, "C": 0.01, "e": 0.01, "E": 0.01, "L": 1e-7}
"""The scale a format character itself implies (pymavlink applies it; so do we)."""

PLAIN_INTEGERS = set("bBhHiIqQ")
"""Integer fields whose multiplier (FMTU) scales the raw value."""

MULTIPLIERS = {
    "2": 1e2,
    "1": 1e1,
    "0": 1.0,
    "A": 1e-1,
    "B": 1e-2,
    "C": 1e-3,
    "D": 1e-4,
    "E": 1e-5,
    "F": 1e-6,
    "G": 1e-7,
    "I": 1e-9,
    "!": 3.6,
    "/": 3600.0,
}
"""ArduPilot's multiplier ids, for a log without MULT records."""

UNITS = {
    "d": "deg",
    "h": "degheading",
    "k": "deg/s",
    "e": "deg/s/s",
    "E": "rad/s",
    "L": "rad/s/s",
    "r": "rad",
    "m": "m",
    "n": "m/s",
    "o": "m/s/s",
    "O": "degC",
    "P": "Pa",
    "s": "s",
    "Y": "us",
    "%": "%",
}
"""ArduPilot's unit ids (the ones the readers use), for a log without UNIT records."""

TO_SI: dict[str, tuple[float, float]] = {
    "deg": (math.pi / 180.0, 0.0),
    "degheading": (math.pi / 180.0, 0.0),
    "deg/s": (math.pi / 180.0, 0.0),
    "deg/s/s": (math.pi / 180.0, 0.0),
    "degC": (1.0, 273.15),
    "%": (0.01, 0.0),
}
"""Unit label -> (factor, offset) to SI (radians, kelvin, fractions); others are SI."""

CHUNK_BYTES = 8 << 20
"""Bytes scanned between two progress reports."""


class DataFlashError(FlightDataError):
    """A file is not a DataFlash log, or a message in it cannot be read."""


@numba.njit(cache=True, nogil=True)
def _scan(
    buf: NDArray[np.uint8],
    pos: int,
    stop: int,
    lengths: NDArray[np.int64],
    offsets: NDArray[np.int64],
    types: NDArray[np.uint8],
    n: int,
) -> tuple[int, int, int]:
    """Walk the records from pos until stop (or offsets is full): (next position, records
    kept, bytes skipped). A FMT record sets the length of the type it defines."""
    size = buf.shape[0]
    skipped = 0
    while pos < stop and n < offsets.shape[0]:
        if pos + 3 > size:
            break
        if buf[pos] != 0xA3 or buf[pos + 1] != 0x95:
            pos += 1
            skipped += 1
            continue
        t = buf[pos + 2]
        length = lengths[t]
        if length == 0:
            pos += 1
            skipped += 1
            continue
        if pos + length > size:
            break
        if t == FMT_TYPE and buf[pos + 4] >= 3:
            lengths[buf[pos + 3]] = buf[pos + 4]
        offsets[n] = pos
        types[n] = t
        n += 1
        pos += length
    return pos, n, skipped


@numba.njit(cache=True, nogil=True)
def _gather(buf: NDArray[np.uint8], offsets: NDArray[np.int64], length: int) -> NDArray[np.uint8]:
    """The payloads (header dropped) of the records at offsets, one row each."""
    width = length - 3
    out = np.empty((offsets.shape[0], width), np.uint8)
    for i in range(offsets.shape[0]):
        start = offsets[i] + 3
        out[i, :] = buf[start : start + width]
    return out


@dataclass(frozen=True)
class Format:
    """A message type as its FMT record defines it."""

    type: int
    length: int
    name: str
    format: str
    columns: tuple[str, ...]
    units: str = ""
    multipliers: str = ""

    def dtype(self) -> np.dtype[np.void]:
        names, formats = [], []
        for i, (char, col) in enumerate(zip(self.format, self.columns, strict=False)):
            if char not in TYPE_CODES:
                raise DataFlashError(f"{self.name}: format character {char!r} is not known")
            names.append(col if col not in names else f"{col}_{i}")
            formats.append(TYPE_CODES[char])
        return np.dtype({"names": names, "formats": formats})


def _text(raw: bytes) -> str:
    return raw.split(b"\0", 1)[0].decode("ascii", "replace")


@dataclass
class DataFlashLog:
    """A DataFlash log's message types, each readable as arrays (`values`, `si`)."""

    path: Path
    formats: dict[str, Format]
    _tables: dict[str, dict[str, NDArray[np.generic]]]
    _load: Callable[[Format], dict[str, NDArray[np.generic]]]
    unit_labels: dict[str, str] = field(default_factory=lambda: dict(UNITS))
    multipliers: dict[str, float] = field(default_factory=lambda: dict(MULTIPLIERS))
    skipped_bytes: int = 0
    size_bytes: int = 0
    truncated_bytes: int = 0
    """Bytes of a last record cut by the end of the file (not read)."""
    _seconds: dict[tuple[str, str], FloatArray] = field(default_factory=dict)
    memo: dict[tuple[str, str], object] = field(default_factory=dict)
    """What a preset derived from the log once and uses for several channels."""
    bad: dict[str, str] = field(default_factory=dict)
    """Message types whose FMT this reader cannot follow (name -> why); their records are
    walked over (their length is known) but not read."""

    def has(self, name: str, column: str | None = None) -> bool:
        fmt = self.formats.get(name)
        return fmt is not None and (column is None or column in fmt.columns)

    def table(self, name: str) -> dict[str, NDArray[np.generic]]:
        """Every column of a message type (pymavlink's values; strings as bytes)."""
        if name not in self._tables:
            fmt = self.formats.get(name)
            if fmt is None:
                why = self.bad.get(name, f"no {name} message in the log")
                raise DataFlashError(f"{self.path}: {why}")
            self._tables[name] = self._load(fmt)
        return self._tables[name]

    def values(self, name: str, column: str) -> FloatArray:
        """A numeric column as pymavlink's DFReader gives it."""
        return np.asarray(self.table(name)[column], float)

    def strings(self, name: str, column: str) -> list[str]:
        return [_text(bytes(v)) for v in self.table(name)[column]]

    def time_s(self, name: str) -> FloatArray:
        """A message type's TimeUS in seconds."""
        key = (name, "TimeUS")
        if key not in self._seconds:
            self._seconds[key] = self.values(name, "TimeUS") * 1e-6
        return self._seconds[key]

    def unit(self, name: str, column: str) -> str:
        """A column's unit label from the log's FMTU and UNIT records ("" where unknown)."""
        fmt = self.formats[name]
        i = fmt.columns.index(column)
        uid = fmt.units[i] if i < len(fmt.units) else ""
        return self.unit_labels.get(uid, "")

    def si(self, name: str, column: str, default_unit: str = "") -> FloatArray:
        """A column in SI (radians, kelvin, fractions): the log's multiplier applied to a
        plain integer field, its unit (or default_unit where the log gives none)
        converted."""
        fmt = self.formats[name]
        i = fmt.columns.index(column)
        v = self.values(name, column)
        if fmt.format[i] in PLAIN_INTEGERS and i < len(fmt.multipliers):
            mult = self.multipliers.get(fmt.multipliers[i])
            if mult:
                v = v * mult
        unit = self.unit(name, column) or default_unit
        factor, offset = TO_SI.get(unit, (1.0, 0.0))
        return v * factor + offset if (factor, offset) != (1.0, 0.0) else v

    def params(self) -> dict[str, float]:
        """The parameters as the PARM records give them (the last value of each)."""
        if not self.has("PARM"):
            return {}
        names = self.strings("PARM", "Name")
        return dict(zip(names, self.values("PARM", "Value").tolist(), strict=True))

    def messages(self) -> list[str]:
        return self.strings("MSG", "Message") if self.has("MSG") else []

    def _ids(self, name: str) -> list[str]:
        """A UNIT or MULT record's one-character Id (an int8 in a binary log, the character
        itself in a text one)."""
        return [
            i.decode() if isinstance(i, bytes) else chr(int(i) & 0xFF)
            for i in self.table(name)["Id"].tolist()
        ]

    def _read_units(self) -> None:
        """Units and multipliers from the log's UNIT, MULT and FMTU records."""
        if self.has("UNIT"):
            labels = self.strings("UNIT", "Label")
            for i, label in zip(self._ids("UNIT"), labels, strict=True):
                self.unit_labels[i] = label
        if self.has("MULT"):
            mults = self.values("MULT", "Mult").tolist()
            for i, m in zip(self._ids("MULT"), mults, strict=True):
                self.multipliers[i] = m
        if self.has("FMTU"):
            by_type = {f.type: f for f in self.formats.values()}
            fmtu = self.table("FMTU")
            units = self.strings("FMTU", "UnitIds")
            mults = self.strings("FMTU", "MultIds")
            for t, u, m in zip(fmtu["FmtType"].tolist(), units, mults, strict=True):
                f = by_type.get(int(t))
                if f is not None:
                    self.formats[f.name] = Format(
                        f.type, f.length, f.name, f.format, f.columns, u, m
                    )


def _formats(
    buf: NDArray[np.uint8], offsets: NDArray[np.int64]
) -> tuple[dict[str, Format], dict[str, str]]:
    """The message types the FMT records define, and those that cannot be read (name ->
    why: an unknown format character, a length the format does not add up to)."""
    out: dict[str, Format] = {}
    bad: dict[str, str] = {}
    for pos in offsets.tolist():
        raw = bytes(buf[pos + 3 : pos + FMT_LENGTH])
        name = _text(raw[2:6])
        fmt = _text(raw[6:22])
        cols = tuple(_text(raw[22:86]).split(","))
        f = Format(raw[0], raw[1], name, fmt, cols)
        try:
            size = f.dtype().itemsize
        except DataFlashError as exc:
            bad[name] = str(exc)
            continue
        if size != f.length - 3:
            bad[name] = (
                f"{name}: its format {fmt!r} holds {size} bytes, its FMT says {f.length - 3}"
            )
            continue
        out[name] = f
    return out, bad


def read_bin(path: str | Path, progress: Callable[[float], None] | None = None) -> DataFlashLog:
    """Index a binary DataFlash log (one pass); message types are read when asked for."""
    p = Path(path)
    try:
        size = p.stat().st_size
        # mapped, not read: the scan touches each page once, and nothing is copied
        buf = np.memmap(p, np.uint8, mode="r") if size else np.zeros(0, np.uint8)
    except OSError as exc:
        raise DataFlashError(f"{p}: cannot read: {exc.strerror}") from exc
    lengths = np.zeros(256, np.int64)
    lengths[FMT_TYPE] = FMT_LENGTH
    offsets = np.empty(max(1024, len(buf) // 24), np.int64)
    types = np.empty(len(offsets), np.uint8)
    pos = n = skipped = 0
    while pos < len(buf):
        stop = min(len(buf), pos + CHUNK_BYTES)
        pos, n, s = _scan(buf, pos, stop, lengths, offsets, types, n)
        skipped += s
        if n == len(offsets):
            offsets = np.concatenate([offsets, np.empty(len(offsets), np.int64)])
            types = np.concatenate([types, np.empty(len(types), np.uint8)])
        elif pos < stop:  # a record cut by the end of the file
            break
        if progress is not None and pos < len(buf):
            progress(pos / len(buf))
    if progress is not None:
        progress(1.0)
    offsets, types = offsets[:n], types[:n]
    if n == 0 or not np.any(types == FMT_TYPE):
        raise DataFlashError(f"{p}: not a DataFlash log (no FMT record)")
    formats, bad = _formats(buf, offsets[types == FMT_TYPE])

    def load(fmt: Format) -> dict[str, NDArray[np.generic]]:
        rows = _gather(buf, offsets[types == fmt.type], fmt.length)
        return _columns(fmt, rows.view(fmt.dtype()).reshape(-1))

    log = DataFlashLog(
        p,
        formats,
        {},
        load,
        skipped_bytes=skipped,
        size_bytes=len(buf),
        truncated_bytes=len(buf) - pos,
        bad=bad,
    )
    log._read_units()
    return log


def _columns(fmt: Format, rec: NDArray[np.void]) -> dict[str, NDArray[np.generic]]:
    """A structured array's columns, with the scale each format character implies."""
    out: dict[str, NDArray[np.generic]] = {}
    for char, col in zip(fmt.format, rec.dtype.names or (), strict=False):
        v = rec[col]
        out[col] = v * IMPLIED_SCALE[char] if char in IMPLIED_SCALE else v
    return out


def read_text(path: str | Path, progress: Callable[[float], None] | None = None) -> DataFlashLog:
    """Read a text DataFlash log (`NAME, v1, v2, ...` per line, FMT lines first), as
    Mission Planner and mavlogdump write it. Its values are already scaled as pymavlink
    gives them; each line is split in Python (text logs are small)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="latin-1")
    except OSError as exc:
        raise DataFlashError(f"{p}: cannot read: {exc.strerror}") from exc
    rows: dict[str, list[list[str]]] = {}
    for line in text.splitlines():
        cells = [c.strip() for c in line.split(",")]
        if len(cells) > 1:
            rows.setdefault(cells[0], []).append(cells[1:])
    formats: dict[str, Format] = {}
    for cells in rows.get("FMT", []):
        if len(cells) >= 4:
            formats[cells[2]] = Format(
                int(cells[0]), int(cells[1]), cells[2], cells[3], tuple(cells[4:])
            )
    if not formats:
        raise DataFlashError(f"{p}: not a DataFlash text log (no FMT line)")

    def load(fmt: Format) -> dict[str, NDArray[np.generic]]:
        return _text_columns(fmt, rows.get(fmt.name, []))

    if progress is not None:
        progress(1.0)
    log = DataFlashLog(p, formats, {}, load, size_bytes=len(text))
    log._read_units()
    return log


def _text_columns(fmt: Format, rows: list[list[str]]) -> dict[str, NDArray[np.generic]]:
    """A text log's lines of one type as columns: numbers, or bytes for text fields (and
    for a character field such as UNIT's Id)."""
    got = [r for r in rows if len(r) == len(fmt.columns)]
    out: dict[str, NDArray[np.generic]] = {}
    for i, (char, col) in enumerate(zip(fmt.format, fmt.columns, strict=False)):
        cells = [r[i] for r in got]
        numbers = np.array([_number(c) for c in cells], float)
        if char in "nNZ" or (cells and np.isnan(numbers).all()):
            out[col] = np.array([c.encode() for c in cells], dtype=bytes)
        else:
            out[col] = numbers
    return out


def _number(cell: str) -> float:
    try:
        return float(cell)
    except ValueError:
        return math.nan
