"""What a flight file is, judged by its content, never by its name.

A user's .BIN may be called .log, a ULog may have lost its suffix, a CSV may be a .txt:
the first bytes say which reader to use.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Literal

from gcs_estimator.ingest.flightdata import FlightDataError
from gcs_estimator.ingest.telemetry.mavlink import TlogError, read_tlog

Kind = Literal["dataflash", "dataflash-text", "ulog", "tlog", "csv", "hfb320"]

ULOG_MAGIC = b"ULog\x01\x12\x35"
DATAFLASH_FMT = b"\xa3\x95\x80"
"""A DataFlash record header of type 128 (FMT): a binary log starts with its FMT records."""
HEAD_BYTES = 4096
LOGS: tuple[Kind, ...] = ("dataflash", "dataflash-text", "ulog")
"""The autopilots' own logs (read by ingest.logs.reader)."""

_NUMBER_ROW = re.compile(rb"^\s*[-+0-9.eE]+(\s+[-+0-9.eE]+)+\s*$")


def kind(path: str | Path) -> Kind:
    """The format of the file at path; a FlightDataError names what it could be when it is
    none of them."""
    p = Path(path)
    try:
        with open(p, "rb") as fh:
            head = fh.read(HEAD_BYTES)
    except OSError as exc:
        raise FlightDataError(f"{p}: cannot read: {exc.strerror}") from exc
    if head.startswith(ULOG_MAGIC):
        return "ulog"
    if DATAFLASH_FMT in head[:256]:
        return "dataflash"
    text = head.lstrip(b"\xef\xbb\xbf").lstrip()
    if text[:4].upper() == b"FMT,":
        return "dataflash-text"
    if _is_tlog(p):
        return "tlog"
    first = text.split(b"\n", 1)[0]
    if _NUMBER_ROW.match(first):
        return "hfb320"
    if any(d in first for d in (b",", b";", b"\t")):
        return "csv"
    # text the content does not settle (a one-column table, a record with a title line):
    # its name decides, and that reader says what is wrong with it
    if p.suffix.lower() in (".csv", ".asc"):
        return "csv" if p.suffix.lower() == ".csv" else "hfb320"
    raise FlightDataError(
        f"{p}: not a flight file this tool reads (an ArduPilot DataFlash .bin or .log, a PX4 "
        ".ulg, a MAVLink .tlog, a CSV with a header row, or the HFB-320 ASCII record)"
    )


def is_log(path: str | Path) -> bool:
    """Whether the file is an autopilot's own log (LOGS); False for anything else, and for
    a file that cannot be read (its reader says why)."""
    try:
        return kind(path) in LOGS
    except FlightDataError:
        return False


def _is_tlog(path: Path) -> bool:
    try:
        next(read_tlog(path), None)
    except TlogError:
        return False
    return True
