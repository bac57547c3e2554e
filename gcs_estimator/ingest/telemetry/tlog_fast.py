"""A tlog read with its common case compiled (tlog_kernel), and replayed through the link
with the channel messages' fields already read (decision 0055).

    read_records(path, stats, table) -> the records of mavlink.read_tlog, the same ones
                                        with the same TlogStats, each with what the
                                        kernel read of its packet
    CompiledTlogSource                  TlogSource over them: the same frames, counters
                                        and notes

mavlink.read_tlog stays the reference (and reads live recordings); read_records is its
loop with the plain records taken by the kernel, many at a time: where the kernel stops,
the loop's own step (the same helpers) takes the next record, and the kernel goes on
after it. A record of a channel message that passed its CRC goes to the link decoded:
in a run of COLUMNS_MIN records or more, each message type's fields as columns
(SampleReader.columns: units and ranges per column, decision 0064), and each stretch
of whole samples to MavlinkLink.samples_common (counted and chosen as a run, decision
0069), which leaves what is anything else to MavlinkLink.sample_packet; a sample with a
value dropped, and shorter runs, by SampleReader.of_fields to
MavlinkLink.decoded_packet. Every other record goes to MavlinkLink.packet (pymavlink's
path for what the kernel does not read), as before.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from gcs_estimator.config import LinkConfig
from gcs_estimator.frames import Frame
from gcs_estimator.ingest.sources import SourceError, TlogSource
from gcs_estimator.ingest.telemetry import tlog_kernel
from gcs_estimator.ingest.telemetry.decode import Columns, DecodeStats, Sample, SampleReader
from gcs_estimator.ingest.telemetry.mavlink import (
    _TIME_US,
    BACK_US,
    LOOKAHEAD,
    READ_CHUNK,
    Decoder,
    TlogError,
    TlogRecord,
    TlogStats,
    _junk_byte,
    _junk_record,
    _taken_time,
    packet_length,
)
from gcs_estimator.ingest.telemetry.tlog_kernel import OTHER, FieldTable, Output
from gcs_estimator.stop import Stop

KERNEL_MAX_T_US = 1 << 62
"""Receive times beyond this are left to read_tlog's own step (the kernel's int64)."""


class Run(NamedTuple):
    """Records one after the other in a piece of the file: the kernel's columns, as flat
    lists (numbers only: a list per record would wake the garbage collector over the
    whole process), or one record read_tlog's own step took (status OTHER)."""

    data: bytes
    starts: list[int]
    ends: list[int]
    """Each record's packet: data[start:end]."""
    times: list[int]
    """Receive times [us]."""
    status: list[int]
    """The table message's slot, tlog_kernel.OTHER or BAD_CRC."""
    seq: list[int]
    system_id: list[int]
    component_id: list[int]
    values: list[float]
    """The fields of the table messages (tlog_kernel.Output.values), `width` a record,
    in a run without columns (empty in one with them: see fields)."""
    width: int
    columns: np.ndarray[Any, np.dtype[np.float64]] | None = None
    """The same fields as a record a row (a copy), for SampleReader.columns."""

    def fields(self, j: int, count: int) -> list[float]:
        """The first `count` fields of record j (as floats: a list of the table's
        numbers is made only for the records that go one by one)."""
        if self.columns is not None:
            values: list[float] = self.columns[j, :count].tolist()
            return values
        return self.values[j * self.width : j * self.width + count]


def _one(data: bytes, t: int, start: int, end: int) -> Run:
    return Run(data, [start], [end], [t], [OTHER], [0], [0], [0], [], 0)


COLUMNS_MIN = 16
"""Runs shorter than this are decoded record by record (columns would cost more)."""


COMMON_RETRY = 16
"""Where MavlinkLink.samples_common took none of the samples from a record on, that many
go by sample_packet before it is asked again (after one it took some of, one goes)."""


FRAMING_ONLY = tlog_kernel.field_table(())
"""A table of no message: the kernel frames records and reads none."""


@functools.lru_cache(maxsize=16)
def table_of(link: LinkConfig) -> FieldTable:
    """The kernel's table of the messages SampleReader reads for this link."""
    readers = SampleReader(link, DecodeStats()).readers
    return tlog_kernel.field_table(
        tuple(tlog_kernel.message(r.msgname, r.fields) for r in readers.values())
    )


class _Reader:
    """read_tlog's state over one file (see read_tlog for the rules)."""

    def __init__(self, path: str | Path, stats: TlogStats, table: FieldTable) -> None:
        self.path = path
        self.st = stats
        self.table = table
        self.out = Output()
        self.decoder = Decoder()
        self.first = True
        self.resyncing = False
        self.last_t: int | None = None
        self.data = b""
        self.array = np.frombuffer(self.data, np.uint8)
        self.offset = 0
        self.i = 0
        self.eof = False
        self.width = int(table.count.max(initial=0))

    def refill(self, fh: Any) -> None:
        chunk = fh.read(READ_CHUNK)
        self.eof = not chunk
        self.offset += self.i
        self.data = self.data[self.i :] + chunk
        self.array = np.frombuffer(self.data, np.uint8)
        self.i = 0

    def compiled(self) -> Iterator[Run]:
        """The plain records from i on, taken by the kernel (none while resyncing)."""
        last = self.last_t
        if self.resyncing or (last is not None and last > KERNEL_MAX_T_US):
            return
        out = self.out
        taken, end = tlog_kernel.run(
            self.array, self.i, self.eof, last is not None, last or 0, self.table, out
        )
        if not taken:
            return
        self.first = False
        self.st.records += taken
        t, status, seq, sysid, compid = out.header[:taken].T.tolist()
        values = out.values[:taken, : self.width]
        columns = taken >= COLUMNS_MIN
        yield Run(
            self.data,
            out.bounds[:taken, 0].tolist(),
            out.bounds[:taken, 1].tolist(),
            t,
            status,
            seq,
            sysid,
            compid,
            [] if columns else values.ravel().tolist(),
            self.width,
            values.copy() if columns else None,
        )
        self.last_t = int(out.header[taken - 1, 0])
        self.i = end

    def step(self) -> Iterator[Run]:
        """One turn of read_tlog's loop at i (a record not plainly framed, or junk)."""
        data, i, st = self.data, self.i, self.st
        n = packet_length(data, i + 8)
        end = i + 8 + n
        if n and end <= len(data):
            (t_us,) = _TIME_US(data, i)
            following = packet_length(data, end + 8) if end < len(data) else 0
            framed = end == len(data) or following > 0
            last_t = self.last_t
            plain = (
                framed
                and not self.resyncing
                and (last_t is None or last_t - BACK_US <= t_us <= last_t + BACK_US)
            )
            t_taken = (
                t_us
                if plain
                else _taken_time(data, i, end, following, last_t, self.resyncing, self.decoder, st)
            )
            if t_taken is not None:
                self.first = self.resyncing = False
                self.last_t = t_taken
                st.records += 1
                self.i = end
                yield _one(data, t_taken, i + 8, end)
                return
        elif n:  # the record runs past the end of the file
            st.truncated_tail = True
            self.i = -1
            return
        got = _junk_record(data, i, None if self.resyncing else self.last_t, self.decoder, st)
        if got is not None:
            self.last_t, self.i = got[0].t_recv_us, got[1]
            yield _one(got[0].packet, self.last_t, 0, len(got[0].packet))
        else:
            _junk_byte(self.path, st, self.first, self.offset + i)
            self.resyncing = True
            self.i = i + 1


def read_runs(path: str | Path, stats: TlogStats, table: FieldTable) -> Iterator[Run]:
    """mavlink.read_tlog's records and stats, in runs: the plain ones read by the kernel
    (stats.position is where the run ends: read_tlog's, record by record, is where each
    starts)."""
    r = _Reader(path, stats, table)
    with open(path, "rb") as fh:
        while True:
            stats.position = r.offset + r.i
            if not r.eof and len(r.data) - r.i < LOOKAHEAD:
                r.refill(fh)
                continue
            if r.i + 8 >= len(r.data):
                break
            start = r.i
            yield from r.compiled()
            if r.i != start:
                continue
            yield from r.step()
            if r.i < 0:
                return  # a truncated tail
    if r.first and len(r.data) > 0:
        raise TlogError(f"{path}: not a tlog (no MAVLink record found)")
    if r.i < len(r.data):
        stats.truncated_tail = True


def read_records(path: str | Path, stats: TlogStats | None = None) -> Iterator[TlogRecord]:
    """read_tlog's records (and stats), the plain ones framed by the kernel (no message
    read: a scan for one message type, as runtime/logs.py's for the autopilot's UID)."""
    for run in read_runs(path, TlogStats() if stats is None else stats, FRAMING_ONLY):
        data = run.data
        for start, end, t in zip(run.starts, run.ends, run.times, strict=True):
            yield TlogRecord(t, data[start:end])


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernel now, for the types every read
    calls it with: a worker's first log then waits for nothing."""
    # A read-only buffer, as every read passes (np.frombuffer): numba compiles the
    # writable array type apart, and warming that one left the first read compiling.
    tlog_kernel.run(np.frombuffer(b"", np.uint8), 0, True, False, 0, FRAMING_ONLY, Output(1))


READER_VARIABLE = "GCS_ESTIMATOR_TLOG_READER"
"""`python`: replay and batch read tlogs with TlogSource (read_tlog and SampleReader,
record by record), not the compiled reader: to compare the two, or to rule one out."""


def tlog_source_class() -> type[TlogSource]:
    """The source a replay or a batch reads a tlog with (READER_VARIABLE)."""
    if os.environ.get(READER_VARIABLE, "").strip().lower() == "python":
        return TlogSource
    return CompiledTlogSource


class CompiledTlogSource(TlogSource):
    """TlogSource with its files read by read_runs: the same frames, counters and
    notes, the channel messages decoded by the kernel. Paced (speed > 0): TlogSource."""

    def frames(self, stop: Stop) -> Iterator[Frame | None]:
        if self.speed > 0:
            yield from super().frames(stop)
            return
        table = table_of(self.link.config)
        for path in self.paths:
            self._stats = stats = TlogStats()
            try:
                for run in self._records(path, stats, functools.partial(read_runs, table=table)):
                    if stop.requested:
                        break
                    yield from self._run_frames(run, table)
            except SourceError as exc:
                self.errors.append(str(exc))
                print(f"error: {exc}; skipped", file=self.log)
        yield from self.link.flush()

    def _run_frames(self, run: Run, table: FieldTable) -> Iterator[Frame]:
        """The frames a run's records let go, record by record as MavlinkLink.packet
        would (a channel message read by the kernel: MavlinkLink.decoded_packet; one
        read whole from columns: sample_packet, or with the records after it that are
        too, MavlinkLink.samples_common)."""
        link = self.link
        packet_frames = link.packet
        decoded_frames = link.decoded_packet
        of_fields = link.samples.of_fields
        messages = table.messages
        data = run.data
        starts, ends, times = run.starts, run.ends, run.times
        seqs, sysids, compids = run.seq, run.system_id, run.component_id
        signed = link.signing is not None
        columns = None if signed else _columns(run, table, link.samples)
        which, row = columns or (_NO_COLUMNS, run.status)
        status = run.status
        j, n = 0, len(status)
        while j < n:
            got = which[j]
            sample = None if got is None else got.sample(row[j])
            if sample is not None:
                samples = _whole(which, row, j + 1, n, sample)
                yield from self._samples(run, j, samples)
                j += len(samples)
                continue
            t = times[j] * 1e-6
            packet = data[starts[j] : ends[j]]
            if status[j] < 0 or signed:
                out = packet_frames(packet, t)
            else:
                msg = messages[status[j]]
                fields = run.fields(j, msg.count)
                if msg.texts:
                    fields = _with_text(packet, msg, fields)
                decoded = of_fields(msg.msgid, seqs[j], sysids[j], compids[j], fields, t)
                out = decoded_frames(packet, t, decoded)
            if out:
                yield from out
            j += 1

    def _samples(self, run: Run, j: int, samples: list[Sample]) -> Iterator[Frame]:
        """The frames of a run's records j, j + 1, ... read whole from columns (samples):
        MavlinkLink.samples_common for as many as it takes, sample_packet for the first
        it does not (COMMON_RETRY where it took none), and so on."""
        link = self.link
        data, starts, ends = run.data, run.starts, run.ends
        e = j + len(samples)
        packets = [data[starts[k] : ends[k]] for k in range(j, e)]
        t = [run.times[k] * 1e-6 for k in range(j, e)]
        compids, seqs = run.component_id[j:e], run.seq[j:e]
        k, m = 0, len(samples)
        while k < m:
            taken, out = link.samples_common(packets, t, compids, seqs, samples, k)
            if out:
                yield from out
            k += taken
            end = min(k + (1 if taken else COMMON_RETRY), m)
            while k < end:
                out = link.sample_packet(packets[k], t[k], compids[k], seqs[k], samples[k])
                if out:
                    yield from out
                k += 1


class _NoColumns:
    """No record of a run read from columns."""

    def __getitem__(self, j: int) -> None:
        return None


_NO_COLUMNS = _NoColumns()


def _whole(which: Any, row: list[int], j: int, n: int, first: Sample) -> list[Sample]:
    """first and the samples of the records from j on read whole from columns, up to the
    first record that is not."""
    out = [first]
    for k in range(j, n):
        got = which[k]
        sample = None if got is None else got.sample(row[k])
        if sample is None:
            break
        out.append(sample)
    return out


def _columns(
    run: Run, table: FieldTable, reader: SampleReader
) -> tuple[list[Columns | None], list[int]] | None:
    """Per record of a run: the Columns of its message where SampleReader.columns reads
    that message (None: record by record), and its row there."""
    cols = run.columns
    if cols is None:
        return None
    status = np.asarray(run.status)
    which: list[Columns | None] = [None] * len(run.status)
    row = [0] * len(run.status)
    sysids, times = run.system_id, run.times
    for slot in np.unique(status[status >= 0]).tolist():
        msg = table.messages[slot]
        for rows, texts in _groups(run, msg, np.flatnonzero(status == slot)):
            at = rows.tolist()
            fields: list[Any] = list(cols[rows, : msg.count].T)
            for k, raw in zip(msg.texts, texts, strict=True):
                fields[k] = raw
            got = reader.columns(
                msg.msgid,
                tuple(fields),
                [sysids[r] for r in at],
                [times[r] * 1e-6 for r in at],
            )
            if got is not None:
                for k, r in enumerate(at):
                    which[r] = got
                    row[r] = k
    return which, row


def _groups(
    run: Run, msg: tlog_kernel.Message, rows: np.ndarray[Any, np.dtype[np.intp]]
) -> Iterator[tuple[np.ndarray[Any, np.dtype[np.intp]], tuple[bytes, ...]]]:
    """A message's records of a run, by the raw bytes of its char[] fields (one group
    with none where it has none: NAMED_VALUE_FLOAT's name is a group's, read as
    _with_text reads it)."""
    if not msg.texts:
        yield rows, ()
        return
    data, starts, ends = run.data, run.starts, run.ends
    by: dict[tuple[bytes, ...], list[int]] = {}
    for r in rows.tolist():
        by.setdefault(_texts(data[starts[r] : ends[r]], msg), []).append(r)
    for key, got in by.items():
        yield np.array(got, np.intp), key


def _with_text(packet: bytes, msg: tlog_kernel.Message, values: list[Any]) -> list[Any]:
    """The fields with each char[] one as struct reads it from the (zero-padded) payload."""
    out = list(values)
    for k, raw in zip(msg.texts, _texts(packet, msg), strict=True):
        out[k] = raw
    return out


def _texts(packet: bytes, msg: tlog_kernel.Message) -> tuple[bytes, ...]:
    """Each char[] field's raw bytes as struct reads them from the (zero-padded) payload."""
    head = 10 if packet[0] == 0xFD else 6
    payload = packet[head:-2]
    out = []
    for k in msg.texts:
        o, size = msg.offsets[k], msg.sizes[k]
        raw = payload[o : o + size]
        out.append(raw + bytes(size - len(raw)))
    return tuple(out)
