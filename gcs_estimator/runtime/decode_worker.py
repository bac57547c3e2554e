"""Replay on two cores: a worker process reads, decodes and synchronises a tlog while
this process runs the filters.

Decoding is per-packet Python (framing and field reading compiled: tlog_fast) and the
filters are compiled; in one process they take turns, and threads would too (they share
the GIL). The worker runs exactly the code a replay in one process runs (the tlog source
over a MavlinkLink) and sends its frames over a pipe in batches, with the link's counters
and the read position, so the frames, and so the estimates, are the same; the link's
notes are printed by this process.

The worker is `python -m gcs_estimator.runtime.decode_worker`, not a multiprocessing child: a
spawned child would import the caller's main module again, so every script that
replays would need a `__main__` guard.
"""

from __future__ import annotations

import os
import pickle
import queue
import select
import signal
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, TextIO

import numpy as np

from gcs_estimator import blas
from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import LinkConfig
from gcs_estimator.frames import Frame
from gcs_estimator.ingest.sources import SourceError, TlogSource
from gcs_estimator.ingest.telemetry.counters import LinkCounts
from gcs_estimator.ingest.telemetry.decode import Ranges
from gcs_estimator.ingest.telemetry.link import MavlinkLink
from gcs_estimator.ingest.telemetry.tlog_fast import tlog_source_class
from gcs_estimator.stop import Stop

BATCH_FRAMES = 512
"""Frames sent at a time (a batch also goes after BATCH_S without a full one)."""
BATCH_S = 0.1
QUEUE_BATCHES = 32
"""Batches the worker may be ahead of the filters (bounds memory)."""
READ_BYTES = 1 << 20
"""Most bytes one read of a worker's pipe takes (without the thread)."""
POLL_S = 0.1
"""Longest wait for a batch before the sinks get a tick and the worker is checked [s]."""
CLOSE_S = 5.0
"""How long a worker told to stop has to end before it is killed [s]."""


@dataclass(frozen=True)
class LinkArgs:
    """What the worker builds its MavlinkLink from."""

    config: LinkConfig
    linear_inputs: bool
    ranges: Ranges
    elevator_travel_deg: float = 0.0


@dataclass(frozen=True)
class Progress:
    """The worker's position and its link's state when it sent a batch."""

    position: int
    total: int
    records: int
    t_first_recv: float
    t_last_recv: float
    links: dict[str, LinkCounts]


class Counters(Protocol):
    """A worker's link clock and counters as it last sent them (Progress, LinkState)."""

    @property
    def t_first_recv(self) -> float: ...
    @property
    def t_last_recv(self) -> float: ...
    @property
    def links(self) -> dict[str, LinkCounts]: ...


def mirror(link: Any, counters: Counters) -> None:
    """Set this process's MavlinkLink to a worker's clock and counters: the status line
    and the view read them as the run goes."""
    link.t_first_recv = counters.t_first_recv
    link.t_last_recv = counters.t_last_recv
    link.health.links = counters.links


@dataclass(frozen=True)
class Batch:
    """Frames, column by column (one pickle of a few arrays, not one per frame)."""

    system_id: np.ndarray[Any, np.dtype[np.int64]]
    t: FloatArray
    """[t_vehicle_s, t_recv_s] per frame."""
    inputs: FloatArray
    y: FloatArray
    flags: np.ndarray[Any, np.dtype[np.bool_]]
    """[clock_reset, inputs_known] per frame."""

    @staticmethod
    def of(frames: Sequence[Frame]) -> Batch:
        return Batch(
            np.array([f.system_id for f in frames], np.int64),
            np.array([(f.t_vehicle_s, f.t_recv_s) for f in frames], float),
            np.array([f.inputs for f in frames], float),
            np.array([f.y for f in frames], float),
            np.array([(f.clock_reset, f.inputs_known) for f in frames], bool),
        )

    def frames(self) -> Iterator[Frame]:
        for i in range(len(self.system_id)):
            yield Frame(
                int(self.system_id[i]),
                float(self.t[i, 0]),
                float(self.t[i, 1]),
                self.inputs[i].copy(),
                self.y[i].copy(),
                bool(self.flags[i, 0]),
                bool(self.flags[i, 1]),
            )


class _Lines:
    """A text stream whose lines go to the parent (the link's and the source's notes)."""

    def __init__(self, send: Any) -> None:
        self._send = send
        self._buf = ""

    def write(self, text: str) -> int:
        self._buf += text
        while "\n" in self._buf:
            line, self._buf = self._buf.split("\n", 1)
            self._send(("log", line))
        return len(text)

    def flush(self) -> None:
        pass


_LENGTH = struct.Struct("<I")


def _message(msg: Any) -> bytes:
    """A message as it goes down a pipe: its length, then its pickle."""
    data = pickle.dumps(msg, protocol=pickle.HIGHEST_PROTOCOL)
    return _LENGTH.pack(len(data)) + data


def _writer(stream: Any) -> Any:
    def send(msg: tuple[Any, ...]) -> None:
        stream.write(_message(msg))
        stream.flush()

    return send


def read_messages(buffer: bytes) -> tuple[list[Any], bytes, str | None]:
    """The complete messages at the start of what was read of a pipe, the rest, and why
    reading stopped early (a message that does not unpickle; None: it did not)."""
    out = []
    at = 0
    while len(buffer) - at >= _LENGTH.size:
        (n,) = _LENGTH.unpack_from(buffer, at)
        end = at + _LENGTH.size + n
        if len(buffer) < end:
            break
        try:
            out.append(pickle.loads(buffer[at + _LENGTH.size : end]))
        except Exception as exc:
            return out, buffer[at:], str(exc)
        at = end
    return out, buffer[at:], None


def _read_message(stream: Any) -> tuple[Any, ...] | None:
    """The next message on the pipe; None at its end."""
    head = stream.read(_LENGTH.size)
    if len(head) < _LENGTH.size:
        return None
    (n,) = _LENGTH.unpack(head)
    data = stream.read(n)
    if len(data) < n:
        return None
    msg: tuple[Any, ...] = pickle.loads(data)
    return msg


def _work(paths: list[str], args: LinkArgs, send: Any) -> None:
    """The worker: replay the files through a link, send the frames in batches, then
    ("end", link stats, errors, progress). SIGINT and SIGTERM end it cleanly."""
    stop = Stop().install()
    log: Any = _Lines(send)
    link = MavlinkLink(
        args.config,
        log=log,
        linear_inputs=args.linear_inputs,
        ranges=args.ranges,
        elevator_travel_deg=args.elevator_travel_deg,
    )
    source = tlog_source_class()(paths, link, log=log)

    def progress() -> Progress:
        position, total = source.progress()
        return Progress(
            position, total, source.done, link.t_first_recv, link.t_last_recv, link.health.links
        )

    batch: list[Frame] = []
    sent = time.monotonic()
    try:
        for frame in source.frames(stop):
            if frame is not None:
                batch.append(frame)
            if len(batch) >= BATCH_FRAMES or (batch and time.monotonic() - sent > BATCH_S):
                send(("frames", Batch.of(batch), progress()))
                batch, sent = [], time.monotonic()
        if batch:
            send(("frames", Batch.of(batch), progress()))
        send(("end", link.stats(), source.errors, progress()))
    except SourceError as exc:
        send(("failed", str(exc), True))
    except BrokenPipeError:
        pass  # the parent has gone: nobody to tell
    except Exception as exc:  # reported by the parent, which keeps what it had
        send(("failed", f"{type(exc).__name__}: {exc}", False))


def main() -> None:
    """The worker process: its job (paths, LinkArgs) pickled on stdin, its messages on
    stdout."""
    blas.one_thread()
    paths, args = pickle.load(sys.stdin.buffer)
    _work(paths, args, _writer(sys.stdout.buffer))


class WorkerProcess:
    """The parent's end of a worker (`python -m MODULE`, its job pickled on stdin, its
    messages on stdout): a thread reads the messages onto a bounded queue, or, with
    threaded False, the caller reads them (`messages`) without one."""

    def __init__(
        self,
        module: str,
        job: Any,
        pass_fds: Sequence[int] = (),
        threaded: bool = True,
        keep_input: bool = False,
    ) -> None:
        self._process = subprocess.Popen(
            [sys.executable, "-m", module],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            pass_fds=tuple(pass_fds),
            bufsize=0 if not threaded else -1,
        )
        assert self._process.stdin is not None and self._process.stdout is not None
        self._input = bytearray()
        """Messages to the worker not yet written (keep_input: `post`, `write_input`)."""
        if keep_input:  # the job is the first message; more follow (read_messages)
            self._input += _message(job)
            self.write_input(block=True)
            os.set_blocking(self._process.stdin.fileno(), False)
        else:
            data = memoryview(pickle.dumps(job))
            while data:  # unbuffered (threaded False), a write may take only part
                data = data[self._process.stdin.write(data) or 0 :]
            self._process.stdin.close()
        self._queue: queue.Queue[tuple[Any, ...] | None] = queue.Queue(QUEUE_BATCHES)
        """The reader thread's messages (threaded only)."""
        self._reader: threading.Thread | None = None
        self._buffer = b""
        """What `messages` read of the pipe and has not parsed yet (unthreaded only)."""
        self._ended = False
        if threaded:
            self._reader = threading.Thread(
                target=self._read, args=(self._process.stdout,), name=module, daemon=True
            )
            self._reader.start()

    def post(self, msg: tuple[Any, ...]) -> None:
        """A message for the worker (keep_input), written by write_input."""
        self._input += _message(msg)

    @property
    def input_pending(self) -> int:
        """Bytes of posted messages not yet written to the worker."""
        return len(self._input)

    def write_input(self, block: bool = False) -> int:
        """Write what the worker's pipe takes of the posted messages (all of them, with
        block); returns the bytes still pending. A worker that has gone takes nothing:
        its messages are dropped (its end is read from its output)."""
        stdin = self._process.stdin
        assert stdin is not None
        while self._input:
            try:
                n = os.write(stdin.fileno(), self._input)
            except BlockingIOError:
                if not block:
                    break
                select.select([], [stdin], [], POLL_S)
                continue
            except (BrokenPipeError, ValueError):  # the worker has gone, or input closed
                self._input.clear()
                break
            del self._input[:n]
        return len(self._input)

    def input_fd(self) -> int:
        stdin = self._process.stdin
        assert stdin is not None
        return stdin.fileno()

    def output_fd(self) -> int:
        stdout = self._process.stdout
        assert stdout is not None
        return stdout.fileno()

    def ready(self) -> bool:
        """Without the thread: whether a message (or the pipe's end) is waiting."""
        stdout = self._process.stdout
        assert stdout is not None
        if self._ended:
            return True
        if len(self._buffer) >= _LENGTH.size:
            (n,) = _LENGTH.unpack_from(self._buffer)
            if len(self._buffer) >= _LENGTH.size + n:
                return True
        return bool(select.select([stdout], [], [], 0)[0])

    def messages(
        self, timeout_s: float, wake_fds: Sequence[int] = ()
    ) -> list[tuple[Any, ...] | None]:
        """Without the thread: the messages complete after one read of what the pipe holds
        (waiting up to timeout_s for it), None last at the pipe's end. A thread that waits
        for the pipe takes the interpreter's lock from the filters at every message, so a
        live link's frames would wait up to its switch interval (5 ms); read here, they
        wait for nothing. Data on one of wake_fds ends the wait too."""
        stdout = self._process.stdout
        assert stdout is not None
        if self._ended:
            return [None]
        fd = stdout.fileno()
        if fd in select.select([fd, *wake_fds], [], [], timeout_s)[0]:
            chunk = os.read(fd, READ_BYTES)
            if chunk:
                self._buffer += chunk
            else:
                self._ended = True
        msgs, self._buffer, error = read_messages(self._buffer)
        out: list[tuple[Any, ...] | None] = list(msgs)
        if error is not None:  # the worker's end, as the thread takes it
            out.append(("failed", f"unreadable message from the worker: {error}", False))
            self._ended = True
        if self._ended:
            out.append(None)
        return out

    def _read(self, stream: Any) -> None:
        """Messages from the pipe onto the queue (a thread: its reads wait without the
        GIL); None at the end."""
        while True:
            try:
                msg = _read_message(stream)
            except Exception as exc:  # a message that does not unpickle: the worker's end
                msg = ("failed", f"unreadable message from the worker: {exc}", False)
                self._queue.put(msg)
                msg = None
            self._queue.put(msg)
            if msg is None:
                return

    def _pass_on(self, stop: Stop, told: bool) -> bool:
        """A stop requested here goes to the worker once (SIGTERM): it ends as on its own
        signal, and what it still sends comes. Returns whether it was told."""
        if stop.requested and not told:
            self._signal(signal.SIGTERM)
            return True
        return told

    def _signal(self, signum: int) -> None:
        if self._process.poll() is None:
            self._process.send_signal(signum)

    def close(self) -> None:
        """End the worker (if it is still running) and wait for it; what it still sends
        is read and dropped, so that it never waits on a full pipe."""
        self._signal(signal.SIGTERM)
        deadline = time.monotonic() + CLOSE_S
        if self._reader is None:  # unthreaded: read to the end here
            while not self._ended and time.monotonic() < deadline:
                self.messages(0.05)
        while self._reader is not None and self._reader.is_alive() and time.monotonic() < deadline:
            try:
                self._queue.get(timeout=0.05)
            except queue.Empty:
                continue
        if self._process.poll() is None:
            try:
                self._process.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                self._process.kill()
                self._process.wait()


class DecodeWorker(WorkerProcess):
    """The parent's end: starts the worker and yields its frames in order."""

    def __init__(self, paths: Sequence[Path], args: LinkArgs, log: TextIO | None = None) -> None:
        self.log = sys.stderr if log is None else log
        super().__init__("gcs_estimator.runtime.decode_worker", ([str(p) for p in paths], args))
        self.progress: Progress | None = None
        self.stats: dict[str, Any] | None = None
        self.errors: list[str] = []

    def frames(self, stop: Stop) -> Iterator[Frame | None]:
        """Frames in order; None while waiting (a tick for the sinks). Raises
        SourceError if the worker could not read its files or died."""
        told = False
        try:
            while True:
                told = self._pass_on(stop, told)
                try:
                    msg = self._queue.get(timeout=POLL_S)
                except queue.Empty:
                    yield None
                    continue
                if msg is None:
                    code = self._process.wait()
                    if told:
                        return  # stopped before it could say so (a signal during its start)
                    raise SourceError(f"the decoding process ended early (exit code {code})")
                kind = msg[0]
                if kind == "log":
                    print(msg[1], file=self.log)
                elif kind == "frames":
                    self.progress = msg[2]
                    yield from msg[1].frames()
                    yield None
                elif kind == "end":
                    self.stats, self.errors, self.progress = msg[1], msg[2], msg[3]
                    return
                elif msg[2]:  # failed: the files
                    raise SourceError(msg[1])
                else:
                    raise RuntimeError(f"decoding process: {msg[1]}")
        finally:
            self.close()


class WorkerTlogSource:
    """A TlogSource whose reading, decoding and synchronising runs in a DecodeWorker
    while this process runs the filters: the same frames, link counters and notes as
    TlogSource in this process. The command chooses it (replay as fast as possible on
    more than one core, see use_decode_worker); a source never starts a process itself."""

    def __init__(self, paths: Sequence[str | Path], link: MavlinkLink, log: TextIO | None = None):
        self.paths = [Path(p) for p in paths]
        self.link = link
        self.log = sys.stderr if log is None else log
        self.errors: list[str] = []
        """Files that could not be replayed (the others' frames are processed)."""
        self._worker: DecodeWorker | None = None

    def frames(self, stop: Stop) -> Iterator[Frame | None]:
        link = self.link
        args = LinkArgs(link.config, link.linear_inputs, link.ranges, link.elevator_travel_deg)
        worker = self._worker = DecodeWorker(self.paths, args, self.log)
        mirrored = None
        for frame in worker.frames(stop):
            progress = worker.progress
            if progress is not mirrored and progress is not None:
                mirrored = progress
                mirror(link, progress)
            yield frame
        self.errors = worker.errors  # each already said by the worker, through self.log

    def progress(self) -> tuple[int, int]:
        """(bytes read, bytes in the current file)."""
        p = None if self._worker is None else self._worker.progress
        return (0, 0) if p is None else (p.position, p.total)

    @property
    def done(self) -> int:
        """Records of the current file replayed so far."""
        p = None if self._worker is None else self._worker.progress
        return 0 if p is None else p.records

    def link_stats(self) -> dict[str, Any]:
        if self._worker is not None:
            self._worker.close()
            if self._worker.stats is not None:
                return self._worker.stats
        return self.link.stats()

    def close(self) -> None:
        if self._worker is not None:
            self._worker.close()
        self.link.close()


def use_decode_worker(speed: float, link: MavlinkLink) -> bool:
    """Decode in a worker process when replaying as fast as possible on more than one
    core, and the link records nothing (a recording is written by the reading process)."""
    return speed <= 0 and (os.cpu_count() or 1) > 1 and link.recorder is None


def tlog_source(
    paths: Sequence[str | Path], link: MavlinkLink, speed: float = 0.0, log: TextIO | None = None
) -> TlogSource | WorkerTlogSource:
    """The replay's source: decoded in a worker process where use_decode_worker says so,
    else in this one."""
    if use_decode_worker(speed, link):
        return WorkerTlogSource(paths, link, log)
    return tlog_source_class()(paths, link, speed=speed, log=log)


if __name__ == "__main__":
    # Through the package's module, not __main__: the classes it pickles must be the
    # ones the parent unpickles.
    from gcs_estimator.runtime import decode_worker

    decode_worker.main()
