"""Binary logs of fixed-size records, built as numpy structured arrays (one per message
type, every field at once) and interleaved by time in one vectorised pass: a
ten-minute flight's hundred thousand records are written in well under a second."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Block:
    """Records of one type: a structured array (packed, little-endian) and each record's
    time, by which the blocks are interleaved (rank breaks ties: lower first)."""

    records: np.ndarray
    time_us: np.ndarray
    rank: int


def interleave(blocks: list[Block]) -> bytes:
    """Every block's records in time order (stable: equal times keep rank, then block
    order, then record order) as one byte string."""
    blocks = [b for b in blocks if len(b.records)]
    if not blocks:
        return b""
    times = np.concatenate([b.time_us.astype(np.uint64) for b in blocks])
    ranks = np.concatenate([np.full(len(b.records), b.rank, np.int64) for b in blocks])
    sizes = np.concatenate(
        [np.full(len(b.records), b.records.dtype.itemsize, np.int64) for b in blocks]
    )
    order = np.lexsort((np.arange(len(times)), ranks, times))
    start = np.empty(len(times), np.int64)
    ends = np.cumsum(sizes[order])
    start[order] = ends - sizes[order]
    out = np.empty(int(ends[-1]), np.uint8)
    offset = 0
    for b in blocks:
        n, width = len(b.records), b.records.dtype.itemsize
        raw = np.frombuffer(b.records.tobytes(), np.uint8).reshape(n, width)
        where = start[offset : offset + n, None] + np.arange(width)
        out[where] = raw
        offset += n
    return out.tobytes()


def filled(dtype: np.dtype, n: int, **columns: object) -> np.ndarray:
    """A structured array of n records: each named column from a value or an array
    (float columns of an integer field are rounded), the rest zero."""
    out = np.zeros(n, dtype)
    for name, value in columns.items():
        kind = out.dtype.fields[name][0]
        arr = np.asarray(value)
        if kind.kind in "iu" and arr.dtype.kind == "f":
            info = np.iinfo(kind.base if kind.subdtype else kind)
            arr = np.clip(np.round(arr), info.min, info.max)
        out[name] = arr
    return out
