"""A tlog's common case compiled (numba): one pass over the bytes that frames records,
checks the channel messages' CRCs and unpacks their fields into columns (decision 0055).

    run(data, i, eof, have_last, last_t, table, out) -> (records, i)

From byte i of data (a piece of the file, numpy uint8), the kernel takes record after
record for as long as each is what mavlink.read_tlog takes "as it is": a packet right
after its 8-byte time, within a minute (BACK_US) of the record before, followed by the
next record's header or the end of the file. It stops where one is not (garbage, a
truncated tail, a time jump), where the lookahead a check needs is not read yet, or when
the output is full; the caller (tlog_fast.py) runs read_tlog's own logic there and
calls the kernel again. The common case thus never leaves compiled code; every other
case is read_tlog's, unchanged.

For each record taken it gives its start, end and time, and for the messages of the
table (decode.SampleReader's: the ones carrying channels) what mavlink.read_fields
would: status OK and the fields the decoder reads (every integer and float as float64,
exactly: a Python int the decoder multiplies by a float is converted the same way), or
status BAD_CRC; every other packet (other messages, signed ones, MAVLink 2 with
incompatibility flags) is status OTHER and goes through pymavlink as before. The
CRC_EXTRA bytes, field offsets and types come from pymavlink's dialect (FieldTable).
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit
from pymavlink.dialects.v20 import ardupilotmega as dialect

from gcs_estimator.ingest.telemetry.mavlink import BACK_US, LOOKAHEAD

OTHER = -1
"""Status of a packet the kernel does not read (pymavlink's path)."""
BAD_CRC = -2
"""Status of a packet of a table message whose CRC fails."""
MAX_FIELDS = 18
"""Most fields one table message has read (SERVO_OUTPUT_RAW: time, port, 16 outputs)."""
ID_SLOTS = 1 << 16
"""Message ids the table can hold (the dialect's channel messages are all below)."""

# Field codes: struct's letters, numbered for the kernel.
CODES = {"b": 0, "B": 1, "h": 2, "H": 3, "i": 4, "I": 5, "q": 6, "Q": 7, "f": 8, "d": 9}
TEXT = 10
"""A char[] field: left to the caller (it slices the packet)."""


@dataclass(frozen=True)
class Message:
    """One table message: which fields are read, in the order the decoder asks."""

    msgid: int
    name: str
    fields: tuple[str, ...]
    offsets: tuple[int, ...]
    codes: tuple[int, ...]
    sizes: tuple[int, ...]
    """Bytes of each field (a char[]'s whole length)."""

    texts: tuple[int, ...] = ()
    """Positions of the char[] fields (the caller reads them from the packet)."""

    @property
    def count(self) -> int:
        return len(self.fields)


def message(name: str, fields: tuple[str, ...]) -> Message:
    """A message's layout on the wire from the dialect: each asked field's offset in the
    payload and its type (arrays other than char[] are refused, as FieldReader does)."""
    t = dialect.mavlink_map[getattr(dialect, f"MAVLINK_MSG_ID_{name}")]
    items = re.findall(r"(\d*)([a-zA-Z?])", t.unpacker.format.lstrip("<"))
    if len(items) != len(t.ordered_fieldnames):
        raise ValueError(f"{name}: array fields are left to pymavlink")
    where: dict[str, tuple[int, int, int]] = {}
    offset = 0
    for fname, (count, code) in zip(t.ordered_fieldnames, items, strict=True):
        size = struct.calcsize("<" + count + code)
        if code == "s":
            where[fname] = (offset, TEXT, size)
        elif count:
            raise ValueError(f"{name}.{fname}: array fields are left to pymavlink")
        else:
            where[fname] = (offset, CODES[code], size)
        offset += size
    missing = sorted(set(fields) - set(where))
    if missing:
        raise ValueError(f"{name} has no field(s) {missing}")
    if len(fields) > MAX_FIELDS:
        raise ValueError(f"{name}: more than {MAX_FIELDS} fields")
    return Message(
        int(t.id),
        name,
        fields,
        tuple(where[f][0] for f in fields),
        tuple(where[f][1] for f in fields),
        tuple(where[f][2] for f in fields),
        tuple(k for k, f in enumerate(fields) if where[f][1] == TEXT),
    )


@dataclass(frozen=True)
class FieldTable:
    """The kernel's view of the table messages (arrays indexed by slot)."""

    messages: tuple[Message, ...]
    slot_of: np.ndarray[Any, np.dtype[np.int16]]
    """Message id -> slot (-1: not in the table)."""
    crc_extra: np.ndarray[Any, np.dtype[np.uint8]]
    payload: np.ndarray[Any, np.dtype[np.int64]]
    """Each message's full payload length [bytes] (MAVLink 2 trims trailing zeros)."""
    count: np.ndarray[Any, np.dtype[np.int64]]
    offsets: np.ndarray[Any, np.dtype[np.int64]]
    codes: np.ndarray[Any, np.dtype[np.int64]]


def field_table(messages: tuple[Message, ...]) -> FieldTable:
    n = len(messages)
    slot_of = np.full(ID_SLOTS, -1, np.int16)
    crc = np.zeros(n, np.uint8)
    payload = np.zeros(n, np.int64)
    count = np.zeros(n, np.int64)
    offsets = np.zeros((n, MAX_FIELDS), np.int64)
    codes = np.full((n, MAX_FIELDS), TEXT, np.int64)
    for k, m in enumerate(messages):
        if m.msgid >= ID_SLOTS:
            raise ValueError(f"{m.name}: message id {m.msgid} beyond the table")
        t = dialect.mavlink_map[m.msgid]
        slot_of[m.msgid] = k
        crc[k] = t.crc_extra
        payload[k] = t.unpacker.size
        count[k] = len(m.fields)
        offsets[k, : len(m.fields)] = m.offsets
        codes[k, : len(m.fields)] = m.codes
    return FieldTable(messages, slot_of, crc, payload, count, offsets, codes)


class Output:
    """The kernel's columns for up to `capacity` records, reused run after run."""

    def __init__(self, capacity: int = 4096) -> None:
        self.capacity = capacity
        self.bounds = np.zeros((capacity, 2), np.int64)
        """[start of the packet, end] in the piece of the file."""
        self.header = np.zeros((capacity, 5), np.int64)
        """[time us, status (slot, OTHER, BAD_CRC), sequence, system id, component id]."""
        self.values = np.zeros((capacity, MAX_FIELDS), np.float64)


def run(
    data: np.ndarray[Any, np.dtype[np.uint8]],
    i: int,
    eof: bool,
    have_last: bool,
    last_t: int,
    table: FieldTable,
    out: Output,
) -> tuple[int, int]:
    """(records taken, where the next record starts): see the module's docstring."""
    got: tuple[int, int] = _run(
        data,
        i,
        eof,
        have_last,
        last_t,
        table.slot_of,
        table.crc_extra,
        table.payload,
        table.count,
        table.offsets,
        table.codes,
        out.bounds,
        out.header,
        out.values,
    )
    return got


@njit(cache=True, inline="always")
def _length(d: Any, s: int, n: int) -> int:
    """mavlink.packet_length."""
    if s >= n:
        return 0
    stx = d[s]
    if stx == 0xFD:
        if s + 3 > n:
            return 0
        return 12 + int(d[s + 1]) + (13 if d[s + 2] & 1 else 0)
    if stx == 0xFE:
        if s + 2 > n:
            return 0
        return 8 + int(d[s + 1])
    return 0


@njit(cache=True, inline="always")
def _time(d: Any, s: int) -> int:
    """A record's big-endian time [us]; -1 beyond 2**63 (left to read_tlog)."""
    if d[s] & 0x80:
        return -1
    t = 0
    for k in range(8):
        t = (t << 8) | int(d[s + k])
    return t


@njit(cache=True)
def _crc_ok(d: Any, p: int, end: int, extra: int) -> bool:
    """MAVLink's X.25 (MCRF4XX) over the packet after its start marker, then CRC_EXTRA."""
    crc = 0xFFFF
    for k in range(p + 1, end - 2 + 1):
        b = int(d[k]) if k < end - 2 else extra
        tmp = (b ^ (crc & 0xFF)) & 0xFF
        tmp = (tmp ^ (tmp << 4)) & 0xFF
        crc = ((crc >> 8) ^ (tmp << 8) ^ (tmp << 3) ^ (tmp >> 4)) & 0xFFFF
    return crc == (int(d[end - 2]) | (int(d[end - 1]) << 8))


@njit(cache=True)
def _unpack(  # noqa: C901 - one branch per wire type (numba cannot index a tuple of views)
    d: Any,
    at: int,
    length: int,
    slot: int,
    count: Any,
    offsets: Any,
    codes: Any,
    scratch: Any,
    row: Any,
) -> None:
    """A table message's fields from its payload (d[at:at+length], zeros beyond: a
    MAVLink 2 payload trimmed of trailing zeros) into row, as float64."""
    i8 = scratch.view(np.int8)
    i16 = scratch.view(np.int16)
    u16 = scratch.view(np.uint16)
    i32 = scratch.view(np.int32)
    u32 = scratch.view(np.uint32)
    i64 = scratch.view(np.int64)
    u64 = scratch.view(np.uint64)
    f32 = scratch.view(np.float32)
    f64 = scratch.view(np.float64)
    for k in range(count[slot]):
        o = offsets[slot, k]
        code = codes[slot, k]
        if code == TEXT:
            row[k] = 0.0
            continue
        for j in range(8):
            scratch[j] = d[at + o + j] if o + j < length else 0
        if code == 0:
            row[k] = i8[0]
        elif code == 1:
            row[k] = scratch[0]
        elif code == 2:
            row[k] = i16[0]
        elif code == 3:
            row[k] = u16[0]
        elif code == 4:
            row[k] = i32[0]
        elif code == 5:
            row[k] = u32[0]
        elif code == 6:
            row[k] = i64[0]
        elif code == 7:
            row[k] = u64[0]
        elif code == 8:
            row[k] = f32[0]
        else:
            row[k] = f64[0]


@njit(cache=True)
def _read(
    d: Any,
    p: int,
    end: int,
    slot_of: Any,
    crc_extra: Any,
    payload: Any,
    count: Any,
    offsets: Any,
    codes: Any,
    scratch: Any,
    header: Any,
    row: Any,
) -> None:
    """One record's packet d[p:end]: its status and header, its fields if a table
    message's (mavlink._checked and FieldReader.read)."""
    if d[p] == 0xFD:
        header[2], header[3], header[4] = d[p + 4], d[p + 5], d[p + 6]
        if d[p + 2] != 0:
            header[1] = OTHER  # signed, or flags pymavlink judges
            return
        msgid = int(d[p + 7]) | (int(d[p + 8]) << 8) | (int(d[p + 9]) << 16)
        head = 10
    else:
        header[2], header[3], header[4] = d[p + 2], d[p + 3], d[p + 4]
        msgid = int(d[p + 5])
        head = 6
    slot = int(slot_of[msgid]) if msgid < slot_of.shape[0] else -1
    if slot < 0:
        header[1] = OTHER
        return
    if not _crc_ok(d, p, end, int(crc_extra[slot])):
        header[1] = BAD_CRC
        return
    header[1] = slot
    length = min(int(d[p + 1]), int(payload[slot]))
    _unpack(d, p + head, length, slot, count, offsets, codes, scratch, row)


@njit(cache=True)
def _run(
    d: Any,
    i: int,
    eof: bool,
    have_last: bool,
    last_t: int,
    slot_of: Any,
    crc_extra: Any,
    payload: Any,
    count: Any,
    offsets: Any,
    codes: Any,
    bounds: Any,
    header: Any,
    values: Any,
) -> tuple[int, int]:
    n = d.shape[0]
    scratch = np.zeros(8, np.uint8)
    taken = 0
    while taken < bounds.shape[0]:
        if (not eof and n - i < LOOKAHEAD) or i + 8 >= n:
            break
        size = _length(d, i + 8, n)
        end = i + 8 + size
        if size == 0 or end > n:
            break
        t = _time(d, i)
        if t < 0 or (have_last and not (last_t - BACK_US <= t <= last_t + BACK_US)):
            break
        if end < n and _length(d, end + 8, n) == 0:
            break  # not followed by a record's header
        bounds[taken, 0] = i + 8
        bounds[taken, 1] = end
        header[taken, 0] = t
        _read(
            d,
            i + 8,
            end,
            slot_of,
            crc_extra,
            payload,
            count,
            offsets,
            codes,
            scratch,
            header[taken],
            values[taken],
        )
        have_last = True
        last_t = t
        i = end
        taken += 1
    return taken, i
