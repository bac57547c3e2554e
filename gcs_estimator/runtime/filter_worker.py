"""Vehicles sharded over filter processes: `listen --filter-workers K` and
`replay --filter-workers K`.

With many vehicles the filters are the station's work, and one process is one core. Here
the station keeps the link (receiving, decoding, synchronising and recording, in this
process or in a link worker) and the sinks that look at every frame (the view, the status
line); each of K worker processes (`python -m gcs_estimator.runtime.filter_worker`) runs a Session
over its share of the vehicles:

    link -> frames -> ShardedSession --pipe--> K workers: Estimator per vehicle
                          ^                          |  history CSV, results files
                          +--- each frame's outputs -+

- **Which worker:** the n-th vehicle heard goes to worker n mod K, so a replay of the
  link's recording with the same K gives each worker the same vehicles in the same order,
  and the same estimates and history, bit for bit.
- **What a worker does** for its vehicles is what a station in one process does: both
  filters, restarts (with its idle time for their work ahead), the history CSV as the run
  goes, and at the end the structure check and the end of the run (outputs.sinks.RunEnd:
  `--refine`, the held-out check, the advice, the table, JSON, Markdown and history),
  the same value the station would have used in one process. Restarts take turns among
  the vehicles of one worker (decision 0018), which share its core.
- **What comes back:** every frame's outputs (both filters' state, sigmas, innovations and
  step report) as the rows of one float64 matrix per batch, for this process's sinks; at
  the end each vehicle's table and its result as checked, without time histories (they
  are in the history the worker wrote).
- **Bounded:** frames go down in batches; while more than MAX_PENDING_BYTES wait for a
  worker, this process stops reading its source and only moves frames and outputs, so the
  socket's buffer takes the backlog (and the kernel counts what it drops).
"""

from __future__ import annotations

import contextlib
import io
import os
import select
import signal
import sys
import time
import warnings
from collections import deque
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from gcs_estimator import blas
from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import AircraftConfig
from gcs_estimator.estimation.estimator import Backend, FilterKind, Snapshot, StepOutput
from gcs_estimator.estimation.filters.core import FILTER_KINDS
from gcs_estimator.estimation.filters.fast import output_width as step_width
from gcs_estimator.frames import Frame
from gcs_estimator.ingest.sources import SourceError
from gcs_estimator.model.aircraft import build_model
from gcs_estimator.outputs.sinks import ResultsSink, RunEnd, link_line, vehicle_heading
from gcs_estimator.runtime.decode_worker import (
    POLL_S,
    READ_BYTES,
    WorkerProcess,
    _writer,
    read_messages,
)
from gcs_estimator.runtime.link_worker import pack, unpack
from gcs_estimator.runtime.session import Session, Sink, Source, truth_of, warm_up
from gcs_estimator.stop import Stop
from gcs_estimator.uncertainty.result import VehicleResult

BATCH_FRAMES = 64
"""Frames of one worker sent at a time at most (a batch also goes at each turn of the
source's loop)."""
MAX_PENDING_BYTES = 1 << 20
"""Bytes of frames waiting to be written to one worker before this process waits for it."""
READY_S = 120.0
"""Longest wait for the workers to start (imports and compiled kernels, on a cold machine,
all at once) [s]."""


@dataclass(frozen=True)
class ShardJob:
    """What a worker builds its Session and results writer from."""

    index: int
    config: AircraftConfig
    backend: Backend
    keep_history: bool
    truths: dict[int, tuple[float, ...]] | None
    out_dir: str | None
    """Where the vehicles' result files go (None: none written, no tables: a benchmark's)."""
    end: RunEnd = field(default_factory=RunEnd)
    """The end of the run for its vehicles: the station's, as in one process."""


# ---- each frame's outputs as one row of floats ----------------------------------------


def output_width(n: int) -> int:
    """Floats per frame: sequence number, the estimator's frames, then per filter kind:
    present, gust level now, and the step's own output row (filters.core.output_row's
    layout, fast.output_width(n) floats)."""
    return 2 + len(FILTER_KINDS) * _kind_width(n)


def output_row(
    seq: int,
    frames: int,
    outs: Mapping[FilterKind, StepOutput],
    gusts: Mapping[FilterKind, float],
    n: int,
) -> FloatArray:
    parts: list[Any] = [(seq, frames)]
    for kind in FILTER_KINDS:
        out = outs.get(kind)
        if out is None:
            absent = np.full(_kind_width(n), np.nan)
            absent[0] = 0.0
            parts.append(absent)
            continue
        parts += [(1.0, gusts[kind]), out.row]
    return np.concatenate(parts, dtype=np.float64)


def _kind_width(n: int) -> int:
    return 2 + step_width(n)


def read_row(
    row: FloatArray, n: int
) -> tuple[int, int, dict[FilterKind, StepOutput], dict[FilterKind, float]]:
    """output_row's (sequence number, frames, outputs, gust levels now); each output's row
    is a view of the row."""
    outs: dict[FilterKind, StepOutput] = {}
    gusts: dict[FilterKind, float] = {}
    at = 2
    for kind in FILTER_KINDS:
        end = at + _kind_width(n)
        if row[at] == 1.0:
            outs[kind] = StepOutput(row[at + 2 : end], n)
            gusts[kind] = float(row[at + 1])
        at = end
    return int(row[0]), int(row[1]), outs, gusts


# ---- the worker ---------------------------------------------------------------------


class PipeSource:
    """The frames the station sends down the pipe, as a worker's Session source; ends at
    the station's "finish" (with the link's counts and the run's record), at the pipe's
    end, or on SIGTERM."""

    def __init__(self, fd: int, buffer: bytes = b"", messages: Sequence[Any] = ()) -> None:
        self.fd = fd
        self.buffer = buffer
        """What was read of the pipe and is not a whole message yet."""
        self.seq = -1
        """The sequence number of the frame last yielded."""
        self.idle = False
        self.batch_done = False
        """A batch of frames has just been given (their outputs go back now)."""
        self.busy: Any = lambda: False
        """Whether the session has restart work to do (then idle waits are short)."""
        self.link: dict[str, Any] | None = None
        self.run: dict[str, Any] | None = None
        self._messages: deque[Any] = deque(messages)

    def _read(self, timeout_s: float) -> bool:
        """Read what the pipe holds (waiting up to timeout_s); False at its end."""
        if select.select([self.fd], [], [], timeout_s)[0]:
            chunk = os.read(self.fd, READ_BYTES)
            if not chunk:
                return False
            msgs, self.buffer, error = read_messages(self.buffer + chunk)
            self._messages.extend(msgs)
            if error is not None:
                raise RuntimeError(f"unreadable message from the station: {error}")
        return True

    def frames(self, stop: Stop) -> Iterator[Frame | None]:
        while not stop.requested:
            if not self._messages:
                if not self._read(0.0 if self.busy() else POLL_S):
                    return
                if not self._messages:
                    self.idle = True
                    yield None
                    continue
            msg = self._messages.popleft()
            if msg[0] == "finish":
                self.link, self.run = msg[1], msg[2]
                return
            data, n_in, seq0 = msg[1], msg[2], msg[3]
            frames = list(unpack(data, n_in))
            self.batch_done = False
            for i, frame in enumerate(frames):
                self.seq = seq0 + i
                yield frame
            self.idle = False
            self.batch_done = True
            yield None

    def link_stats(self) -> dict[str, Any] | None:
        return self.link

    def close(self) -> None:
        pass


class OutputsSink:
    """Each frame's outputs back to the station, a batch at a time."""

    def __init__(self, source: PipeSource, session: Session, n: int, send: Any) -> None:
        self.source = source
        self.session = session
        self.n = n
        self.send = send
        self.rows: list[FloatArray] = []

    def on_frame(self, frame: Frame, outs: Mapping[FilterKind, StepOutput]) -> None:
        est = self.session.estimators[frame.system_id]
        gusts = {kind: est.gust_level(kind) for kind in outs}
        self.rows.append(output_row(self.source.seq, est.frames, outs, gusts, self.n))

    def flush(self) -> None:
        if self.rows:
            self.send(("outs", np.array(self.rows).tobytes()))
            self.rows = []

    def tick(self) -> None:
        if self.source.batch_done:
            self.flush()

    def finish(self, results: Mapping[int, VehicleResult], link: Mapping[str, Any] | None) -> None:
        self.flush()


class EndSink:
    """At the end, each vehicle's end (ResultsSink.vehicle: fit, checks, files, table),
    sent to the station with the vehicle's result as checked, without its time
    histories, and why a fit or a check failed where one did."""

    def __init__(self, writer: ResultsSink | None, end: RunEnd, send: Any) -> None:
        self.writer = writer
        """None: no files and no tables (ShardJob.out_dir)."""
        self.end = end
        self.send = send
        self.started_cpu_s = time.process_time()
        """The worker's CPU time [s] when it was ready (its start: imports, kernels)."""

    def on_frame(self, frame: Frame, outs: Mapping[FilterKind, StepOutput]) -> None:
        if self.writer is not None:
            self.writer.on_frame(frame, outs)

    def tick(self) -> None:
        pass

    def finish(self, results: Mapping[int, VehicleResult], link: Mapping[str, Any] | None) -> None:
        texts = dict.fromkeys(results, "")
        ended = dict(results)
        if self.writer is not None:
            for sid, vehicle in results.items():
                out = io.StringIO()
                ended[sid] = self.writer.vehicle(vehicle, link, out)
                texts[sid] = out.getvalue()
            for csv in self.writer.histories.values():
                csv.close()
        ended = {sid: v.without_tracks() for sid, v in ended.items()}
        cpu_s = time.process_time() - self.started_cpu_s
        refine, checks = self.end.refine, self.end.checks
        failures = ([] if refine is None else list(refine.failures), list(checks.failures))
        self.send(("end", ended, texts, cpu_s, failures))


def _work(job: ShardJob, source: PipeSource, send: Any) -> None:
    stop = Stop()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the station's Ctrl-C: it says when to end
    signal.signal(signal.SIGTERM, lambda signum, frame: setattr(stop, "requested", True))
    config = job.config
    warm_up(config, job.backend)
    session = Session(
        config,
        backend=job.backend,
        keep_history=job.keep_history,
        truths=job.truths,
        truth_for_first=job.index == 0,
        check_frames=True,  # a link's frames (decision 0084)
    )
    source.busy = session.restart_under_way
    writer = None
    if job.out_dir is not None:
        writer = job.end.sink(
            Path(job.out_dir),
            vehicle_heading,
            lambda: session.elapsed_s,
            run=lambda: source.run or {},
            estimators=lambda: session.estimators,
        )
    session.add_sink(OutputsSink(source, session, build_model(config).n, send))
    end = EndSink(writer, job.end, send)
    session.add_sink(end)
    send(("ready", end.started_cpu_s))
    session.run(source, stop)


def name_warnings(index: int) -> None:
    """Python warnings raised in this process name worker `index`: the workers share the
    station's stderr, and an unnamed warning cannot be told from the station's own."""
    plain = warnings.formatwarning

    def named(
        message: Warning | str,
        category: type[Warning],
        filename: str,
        lineno: int,
        line: str | None = None,
    ) -> str:
        return f"filter worker {index}: " + plain(message, category, filename, lineno, line)

    warnings.formatwarning = named


def main() -> None:
    """The worker process: its ShardJob the first message on stdin, then the frames; its
    messages on the original stdout, which is stderr from here on (a print anywhere in
    the filters' code must not land in the pipe)."""
    blas.one_thread()
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    send = _writer(out)
    buffer = b""
    msgs: list[Any] = []
    while not msgs:
        chunk = os.read(0, READ_BYTES)
        if not chunk:
            return
        msgs, buffer, error = read_messages(buffer + chunk)
        if error is not None:
            sys.exit(f"filter worker: unreadable job: {error}")
    if isinstance(msgs[0], ShardJob):
        name_warnings(msgs[0].index)
    try:
        _work(msgs[0], PipeSource(0, buffer, msgs[1:]), send)
    except BrokenPipeError:
        pass  # the station has gone: nobody to tell
    except Exception as exc:  # reported by the station, which keeps the other vehicles
        with contextlib.suppress(BrokenPipeError):
            send(("failed", f"{type(exc).__name__}: {exc}"))


# ---- the station's end --------------------------------------------------------------


class RemoteEstimator:
    """What the station knows of a vehicle a worker estimates, from its frames' outputs:
    enough for the status line and the view's live table (report.live_table)."""

    def __init__(self, config: AircraftConfig, names: tuple[str, ...], coefficients: slice) -> None:
        self.config = config
        self.names = names
        self.coefficients = coefficients
        self.frames = 0
        self._outs: dict[FilterKind, StepOutput] = {}
        self._gusts: dict[FilterKind, float] = {}

    def update(
        self, frames: int, outs: Mapping[FilterKind, StepOutput], gusts: Mapping[FilterKind, float]
    ) -> None:
        self.frames = frames
        self._outs.update(outs)
        self._gusts.update(gusts)

    def snapshot(self) -> dict[FilterKind, Snapshot]:
        """As Estimator.snapshot, at the last frame whose outputs came back."""
        c = self.coefficients
        return {
            kind: Snapshot(out.x[c].copy(), out.info.sigma[c].copy(), self._gusts[kind])
            for kind, out in self._outs.items()
        }


class FilterShard(WorkerProcess):
    """The station's end of one worker: the frames sent and not yet answered, in order."""

    def __init__(self, job: ShardJob) -> None:
        super().__init__(
            "gcs_estimator.runtime.filter_worker", job, threaded=False, keep_input=True
        )
        self.index = job.index
        self.sent: deque[tuple[int, Frame]] = deque()
        """(sequence number, frame) of the frames sent whose outputs have not come back."""
        self.batch: list[Frame] = []
        self.next_seq = 0
        self.ready_seen = False
        self.end: tuple[Any, ...] | None = None
        """("end", results as checked without tracks, tables, CPU time [s], (why
        --refine's fit failed, why a check failed, for its vehicles where one did)) once
        the worker ended."""
        self.gone = False
        """The worker's output ended (after its end, or because it failed or died)."""
        self.lost = 0
        """Frames of its vehicles it did not answer before it had gone, or that came
        after."""

    def add(self, frame: Frame) -> None:
        if self.gone:
            self.lost += 1
            return
        self.batch.append(frame)
        if len(self.batch) >= BATCH_FRAMES:
            self.send_batch()

    def send_batch(self) -> None:
        if not self.batch or self.gone:
            self.batch = []
            return
        data, n_in = pack(self.batch)
        self.post(("frames", data, n_in, self.next_seq))
        for frame in self.batch:
            self.sent.append((self.next_seq, frame))
            self.next_seq += 1
        self.batch = []

    def answered(self, seq: int) -> Frame:
        """The frame sent with sequence number seq (the frames before it that the
        estimator did not admit have no outputs: dropped here)."""
        while self.sent and self.sent[0][0] < seq:
            self.sent.popleft()
        got, frame = self.sent.popleft()
        if got != seq:
            raise RuntimeError(f"filter process {self.index}: outputs of frame {seq} unexpected")
        return frame

    def exit_code(self) -> int:
        return self._process.wait()


def start_shards(jobs: Sequence[ShardJob]) -> tuple[list[FilterShard], float]:
    """Start a worker per job and wait until each has its kernels ready: the shards, and
    the workers' CPU time to ready [s]. Raises SourceError (the workers ended) if one
    could not start."""
    shards = [FilterShard(job) for job in jobs]
    start_cpu_s = 0.0
    deadline = time.monotonic() + READY_S
    try:
        for shard in shards:
            while not shard.ready_seen:
                if time.monotonic() > deadline:
                    raise SourceError(f"filter process {shard.index} did not start in time")
                for msg in shard.messages(POLL_S):
                    if msg is None or msg[0] != "ready":
                        why = "ended" if msg is None else f"failed: {msg[1]}"
                        raise SourceError(f"filter process {shard.index} {why} at its start")
                    shard.ready_seen = True
                    start_cpu_s += float(msg[1])
    except BaseException:
        for shard in shards:
            shard.close()
        raise
    return shards, start_cpu_s


class ShardedSession:
    """A station whose vehicles are estimated by `workers` filter processes (the module's
    text): the sinks given here see every frame's outputs and the final results as a
    Session's would; each vehicle's files and table are made by its worker."""

    def __init__(
        self,
        config: AircraftConfig,
        workers: int,
        out_dir: str | None,
        sinks: Sequence[Sink] = (),
        backend: Backend = "fast",
        keep_history: bool = True,
        truths: Mapping[int, Sequence[float]] | None = None,
        end: RunEnd | None = None,
        run_info: Callable[[], dict[str, Any]] | None = None,
        log: TextIO | None = None,
    ) -> None:
        if workers < 1:
            raise ValueError(f"filter workers: {workers} (at least 1)")
        self.config = config
        self.sinks = list(sinks)
        self.truths = truths
        self.end = RunEnd() if end is None else end
        """The end of the run the workers give their vehicles; the vehicles as checked
        and why a check failed come back into its checks (the view's final panels read
        them there, as in one process)."""
        self.run_info = run_info
        """Called at the end: what each vehicle's JSON says of the run."""
        self.log = sys.stderr if log is None else log
        own = None if truths is None else {sid: tuple(v) for sid, v in truths.items()}
        self.jobs = [
            ShardJob(i, config, backend, keep_history, own, out_dir, self.end)
            for i in range(workers)
        ]
        model = build_model(config)
        self._n = model.n
        self._names = model.names
        self._coefficients = model.coefficients
        self.shards: list[FilterShard] = []
        self.estimators: dict[int, RemoteEstimator] = {}
        """Each vehicle heard, in the order heard (its worker: its place mod workers)."""
        self.shard_of: dict[int, FilterShard] = {}
        self.texts: dict[int, str] = {}
        """Each vehicle's table, as its worker printed it."""
        self.errors: list[str] = []
        self.refine_failures: list[str] = []
        """Why --refine's fit failed, a line per vehicle where it did (its worker's
        RefineAsk.failures): the run's exit status, as a Session's results sink's."""
        self.workers_cpu_s = 0.0
        """The workers' CPU time [s] from when they were ready to their end (once they
        ended)."""
        self.workers_start_cpu_s = 0.0
        """The workers' CPU time [s] to when they were ready (imports, kernels)."""

    def add_sink(self, sink: Sink) -> None:
        self.sinks.append(sink)

    def estimator(self, system_id: int) -> RemoteEstimator:
        est = self.estimators.get(system_id)
        if est is None:
            est = self.estimators[system_id] = RemoteEstimator(
                self.config, self._names, self._coefficients
            )
            self.shard_of[system_id] = self.shards[(len(self.estimators) - 1) % len(self.shards)]
        return est

    def truth_of(self, system_id: int) -> FloatArray | None:
        """As Session.truth_of."""
        return truth_of(self.config, self.truths, self.estimators, system_id)

    def start(self) -> None:
        """Start the workers and wait until each has its kernels ready (start_shards)."""
        if not self.shards:
            self.shards, self.workers_start_cpu_s = start_shards(self.jobs)

    def run(self, source: Source, stop: Stop | None = None) -> dict[int, VehicleResult]:
        """As Session.run, the frames going to the workers."""
        stop = stop if stop is not None else Stop()
        self.start()
        if hasattr(source, "wake_fds"):  # the source's waits end when outputs come back
            source.wake_fds = [s.output_fd() for s in self.shards]
        try:
            for frame in source.frames(stop):
                if frame is not None:
                    self.process(frame)
                else:
                    self.pump(0.0)
                for sink in self.sinks:
                    sink.tick()
        finally:
            try:
                link = source.link_stats()
                results = self._finish(link)
                for sink in self.sinks:
                    sink.finish(results, link)
            finally:
                source.close()
                for shard in self.shards:
                    shard.close()
        return results

    def process(self, frame: Frame) -> None:
        """Send the frame to its vehicle's worker (its outputs come back later)."""
        self.estimator(frame.system_id)
        shard = self.shard_of[frame.system_id]
        shard.add(frame)
        if shard.input_pending and shard.write_input() > MAX_PENDING_BYTES:
            while shard.write_input() > MAX_PENDING_BYTES // 2 and not shard.gone:
                self._wait([shard], POLL_S)

    def pump(self, timeout_s: float) -> None:
        """Send every worker's batch, write what the pipes take, and hand the outputs
        that came back to the sinks (waiting up to timeout_s for some)."""
        for shard in self.shards:
            shard.send_batch()
            shard.write_input()
        self._wait([s for s in self.shards if s.input_pending], timeout_s)

    def _wait(self, writing: list[FilterShard], timeout_s: float) -> None:
        live = [s for s in self.shards if not s.gone]
        if not live:
            return
        readable, writable, _ = select.select(
            [s.output_fd() for s in live],
            [s.input_fd() for s in writing if not s.gone],
            [],
            timeout_s,
        )
        for shard in live:
            if shard.output_fd() in readable:
                self._take(shard, shard.messages(0.0))
            if shard.input_pending and shard.input_fd() in writable:
                shard.write_input()

    def _take(self, shard: FilterShard, msgs: list[tuple[Any, ...] | None]) -> None:
        width = output_width(self._n)
        for msg in msgs:
            if msg is None:
                shard.gone = True
                if shard.end is None:  # (after its end, what is left was not admitted)
                    shard.lost += len(shard.sent) + len(shard.batch)
                shard.sent.clear()
                shard.batch = []
                if shard.end is None:
                    self._error(
                        f"filter process {shard.index} ended early (exit code "
                        f"{shard.exit_code()}): the results of its vehicles are lost "
                        "(their history CSV holds what it wrote)"
                    )
            elif msg[0] == "outs":
                # One copy of the block: the outputs are views of its rows, writable.
                block = np.frombuffer(msg[1], np.float64).reshape(-1, width).copy()
                for row in block:
                    seq, frames, outs, gusts = read_row(row, self._n)
                    frame = shard.answered(seq)
                    self.estimators[frame.system_id].update(frames, outs, gusts)
                    for sink in self.sinks:
                        sink.on_frame(frame, outs)
            elif msg[0] == "end":
                shard.end = msg
                self.workers_cpu_s += float(msg[3])
                refine_failures, check_failures = msg[4]
                self.refine_failures += refine_failures
                self.end.checks.failures.extend(check_failures)
                self.end.checks.done.update(msg[1])
            elif msg[0] == "failed":
                self._error(f"filter process {shard.index} failed: {msg[1]}")

    def _error(self, text: str) -> None:
        self.errors.append(text)
        print(f"error: {text}", file=self.log)

    def _finish(self, link: Mapping[str, Any] | None) -> dict[int, VehicleResult]:
        """Tell every worker the run is over (with the link's counts and the run's
        record), take the rest of its outputs and its end; the results in the order the
        vehicles were heard."""
        run = self.run_info() if self.run_info is not None else None
        for shard in self.shards:
            shard.send_batch()
            shard.post(("finish", None if link is None else dict(link), run))
        while any(not s.gone for s in self.shards):
            for shard in self.shards:
                shard.write_input()
            self._wait([s for s in self.shards if s.input_pending], POLL_S)
            for sink in self.sinks:
                sink.tick()
        out: dict[int, VehicleResult] = {}
        for sid, shard in self.shard_of.items():
            if shard.end is not None and sid in shard.end[1]:
                out[sid] = shard.end[1][sid]
                self.texts[sid] = shard.end[2][sid]
        lost = sum(s.lost for s in self.shards)
        if lost:
            self._error(f"{lost} frames were not estimated: their filter process had ended")
        return out


class TablesSink:
    """The station's end of a sharded run on stdout: each vehicle's table and files as its
    worker wrote them, in the order the vehicles were heard, then the link's counts."""

    def __init__(self, session: ShardedSession, out: Any = None) -> None:
        self.session = session
        self.out = sys.stdout if out is None else out

    def on_frame(self, frame: Frame, outs: Mapping[FilterKind, StepOutput]) -> None:
        pass

    def tick(self) -> None:
        pass

    def finish(self, results: Mapping[int, VehicleResult], link: Mapping[str, Any] | None) -> None:
        if not results:
            print("no vehicle data received", file=sys.stderr)
        for sid in results:
            print(self.session.texts[sid], end="", file=self.out)
        if link is not None:
            print(link_line(link), file=self.out)


if __name__ == "__main__":
    # Through the package's module, not __main__: the classes it pickles must be the
    # ones the parent unpickles.
    from gcs_estimator.runtime import filter_worker

    filter_worker.main()
