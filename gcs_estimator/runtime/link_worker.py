"""A live UDP link on two cores: a worker process receives, decodes and synchronises the
telemetry while this process runs the filters (`listen --link-worker`).

On a live link every packet is per-packet Python (a datagram read with its arrival time,
its checks, the sample reader, the synchroniser, the recording) and the filters are
compiled; in one process they take turns. The worker runs exactly the code a station in
one process runs (UdpSource over a MavlinkLink, on the socket this process bound and hands
over), so the frames are the same, and so are the estimates: it records the tlog, speaks
to the vehicles (heartbeats, rate requests) and sends each receive round's frames as soon
as the socket is drained, with the link's counters. This process keeps a mirror of those
counters for the status line and the view, prints the link's notes and gets the link's
final counts when the worker ends. Its protocol and process handling are
decode_worker's.
"""

from __future__ import annotations

import math
import pickle
import socket
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from gcs_estimator import blas
from gcs_estimator.frames import Frame
from gcs_estimator.ingest.sources import SourceError, UdpSource
from gcs_estimator.ingest.telemetry.counters import LinkCounts
from gcs_estimator.ingest.telemetry.link import MavlinkLink
from gcs_estimator.model.channels import N_OBS
from gcs_estimator.runtime.decode_worker import (
    POLL_S,
    LinkArgs,
    WorkerProcess,
    _Lines,
    _writer,
    mirror,
)
from gcs_estimator.stop import Stop

READY_S = 60.0
"""Longest wait for a starting worker (its imports, on a cold machine) [s]."""
MIRROR_S = 0.5
"""Time between two reports of the link's counters [s]."""


@dataclass(frozen=True)
class LiveJob:
    """What the worker builds its UdpSource from."""

    fd: int
    """The bound UDP socket's descriptor (handed to the worker, which owns it then)."""
    link: LinkArgs
    record: str | None
    """Where the worker records the tlog (None: nothing recorded)."""
    rejected: str | None
    idle_exit_s: float | None
    max_seconds: float | None
    peer: tuple[str, int] | None


@dataclass(frozen=True)
class LinkState:
    """The worker's link counters when it sent a message (what the status line and the
    view read)."""

    t_first_recv: float
    t_last_recv: float
    links: dict[str, LinkCounts]
    kernel_dropped: int


def pack(frames: list[Frame]) -> tuple[bytes, int]:
    """Frames as the rows of one float64 matrix, in bytes, and the inputs per frame:
    system id, vehicle time, receive time, inputs, observations, clock reset, inputs known.
    Exact (a system id is far below 2^53), and about fifty times cheaper per message than
    pickling the frames: with many vehicles most messages hold one frame."""
    if not frames:
        return b"", 0
    n_in = len(frames[0].inputs)
    rows = []
    for f in frames:
        if len(f.inputs) != n_in:
            raise ValueError(f"frames with {len(f.inputs)} and {n_in} inputs in one batch")
        head = (f.system_id, f.t_vehicle_s, f.t_recv_s)
        rows.append((*head, *f.inputs, *f.y, f.clock_reset, f.inputs_known))
    return np.array(rows, np.float64).tobytes(), n_in


def unpack(data: bytes, n_in: int) -> Iterator[Frame]:
    """pack's frames."""
    if not data:
        return
    rows = np.frombuffer(data, np.float64).reshape(-1, 3 + n_in + N_OBS + 2)
    y0 = 3 + n_in
    for row in rows:
        yield Frame(
            int(row[0]),
            float(row[1]),
            float(row[2]),
            row[3:y0].copy(),
            row[y0 : y0 + N_OBS].copy(),
            bool(row[-2]),
            bool(row[-1]),
        )


def _work(job: LiveJob, send: Any) -> None:
    """The worker: receive on the socket through a link, send each receive round's frames,
    then ("end", link stats, its CPU time [s]). SIGINT and SIGTERM end it cleanly: what
    arrived is still decoded and sent, and the recording closed."""
    from gcs_estimator.ingest.telemetry.mavlink import TlogWriter

    stop = Stop().install()
    log: Any = _Lines(send)
    try:
        sock = socket.socket(fileno=job.fd)
        args = job.link
        link = MavlinkLink(
            args.config,
            recorder=TlogWriter(job.record) if job.record else None,
            log=log,
            linear_inputs=args.linear_inputs,
            ranges=args.ranges,
            rejected_path=Path(job.rejected) if job.rejected else None,
            elevator_travel_deg=args.elevator_travel_deg,
        )
        source = UdpSource(sock, link, job.idle_exit_s, job.max_seconds, job.peer)
        send(("ready",))
        try:
            _receive(source, stop, send)
            stats = source.link_stats()
        finally:
            source.close()
        send(("end", stats, time.process_time()))
    except BrokenPipeError:
        pass  # the parent has gone: nobody to tell
    except Exception as exc:  # reported by the parent, which keeps what it had
        send(("failed", f"{type(exc).__name__}: {exc}", False))


def _receive(source: UdpSource, stop: Stop, send: Any) -> None:
    """Each receive round's frames as soon as it ends; the link's counters (one entry per
    address: many with many vehicles) at most every MIRROR_S, and with the last frames."""
    link = source.link

    def state() -> LinkState:
        return LinkState(
            link.t_first_recv, link.t_last_recv, link.health.links, source.kernel_dropped
        )

    batch: list[Frame] = []
    mirrored = -math.inf
    clock_sent = False
    for frame in source.frames(stop):
        if frame is not None:
            batch.append(frame)
            continue
        now = time.monotonic()
        # The first frames go with the link's clock: the view times frames from it.
        mirror = now - mirrored > MIRROR_S or (bool(batch) and not clock_sent)
        if batch or mirror:
            send(("frames", *pack(batch), state() if mirror else None))
            batch = []
            if mirror:
                mirrored = now
                clock_sent = not math.isnan(link.t_first_recv)
    send(("frames", *pack(batch), state()))


def main() -> None:
    """The worker process: its LiveJob pickled on stdin, its messages on stdout."""
    blas.one_thread()
    job = pickle.load(sys.stdin.buffer)
    _work(job, _writer(sys.stdout.buffer))


class LinkWorker(WorkerProcess):
    """The parent's end: starts the worker on the socket and yields its frames."""

    def __init__(self, job: LiveJob, log: TextIO | None = None) -> None:
        self.log = sys.stderr if log is None else log
        super().__init__(
            "gcs_estimator.runtime.link_worker", job, pass_fds=(job.fd,), threaded=False
        )
        self.state: LinkState | None = None
        self.stats: dict[str, Any] | None = None
        self.cpu_s = 0.0
        """The worker's CPU time [s], once it ended."""
        self.idle = False
        """Nothing from the worker was waiting when the last None was yielded."""
        self.wake_fds: list[int] = []
        """Descriptors whose data end a wait for the worker's as well."""

    def wait_ready(self) -> None:
        """Wait until the worker has its link and recording open and its signal handlers
        in place. Raises SourceError if it ended or failed first."""
        deadline = time.monotonic() + READY_S
        while time.monotonic() < deadline:
            for msg in self.messages(POLL_S):
                if msg is not None and msg[0] == "ready":
                    return
                if msg is None or msg[0] != "log":
                    self.close()
                    why = "ended" if msg is None else f"failed: {msg[1]}"
                    raise SourceError(f"the link process {why} before it could receive")
                print(msg[1], file=self.log)
        self.close()
        raise SourceError(f"the link process did not start within {READY_S:g} s")

    def frames(self, stop: Stop) -> Iterator[Frame | None]:
        """Frames as the worker sends them; None between its messages and while waiting
        (a tick for the sinks). Raises SourceError if the worker failed or died."""
        told = False
        try:
            while True:
                told = self._pass_on(stop, told)
                msgs = self.messages(POLL_S, self.wake_fds)
                if not msgs:
                    self.idle = True
                    yield None
                    continue
                for msg in msgs:
                    if msg is None or msg[0] == "end":
                        self._end(msg, told)
                        return
                    yield from self._frames_of(msg)
                self.idle = not self.ready()
                yield None
        finally:
            self.close()

    def _end(self, msg: tuple[Any, ...] | None, told: bool) -> None:
        """The worker's end: its final counts, or (the pipe ended without them) an error
        unless it was told to stop (a signal during its start)."""
        if msg is not None:
            self.stats, self.cpu_s = msg[1], msg[2]
            return
        code = self._process.wait()
        if not told:
            raise SourceError(f"the link process ended early (exit code {code})")

    def _frames_of(self, msg: tuple[Any, ...]) -> Iterator[Frame]:
        if msg[0] == "log":
            print(msg[1], file=self.log)
            return iter(())
        if msg[0] == "frames":
            if msg[3] is not None:
                self.state = msg[3]
            return unpack(msg[1], msg[2])
        raise SourceError(f"link process: {msg[1]}")


class WorkerUdpSource:
    """A UDP source whose link runs in a worker process (LinkWorker): the session sees
    the frames a UdpSource in this process would give, and `link` mirrors the worker's
    counters for the status line and the view."""

    def __init__(
        self,
        sock: socket.socket,
        job: LiveJob,
        link: MavlinkLink,
        log: TextIO | None = None,
    ) -> None:
        self.sock: socket.socket | None = sock
        """This process's copy of the socket, closed once the worker has its own."""
        self.job = job
        self.link = link
        self.log = log
        self._worker: LinkWorker | None = None
        self.wake_fds: list[int] = []
        """Descriptors whose data end a wait for the link's as well (LiveSource's)."""

    @property
    def idle(self) -> bool:
        return self._worker is not None and self._worker.idle

    @property
    def kernel_dropped(self) -> int:
        state = None if self._worker is None else self._worker.state
        return 0 if state is None else state.kernel_dropped

    @property
    def worker_cpu_s(self) -> float:
        """The link process's CPU time [s] (once it ended)."""
        return 0.0 if self._worker is None else self._worker.cpu_s

    def start(self) -> None:
        """Start the worker (frames does, if nobody did): once it runs, it receives and
        records, so a station says it listens only after this."""
        if self._worker is None:
            self._worker = LinkWorker(self.job, self.log)
            self._worker.wait_ready()
        if self.sock is not None:
            self.sock.close()
            self.sock = None

    def frames(self, stop: Stop) -> Iterator[Frame | None]:
        self.start()
        worker = self._worker
        assert worker is not None
        worker.wake_fds = self.wake_fds
        mirrored = None
        for frame in worker.frames(stop):
            state = worker.state
            if state is not mirrored and state is not None:
                mirrored = state
                mirror(self.link, state)
            yield frame

    def link_stats(self) -> dict[str, Any]:
        if self._worker is not None:
            self._worker.close()
            if self._worker.stats is not None:
                return self._worker.stats
        return {**self.link.stats(), "dropped_by_this_machine": self.kernel_dropped}

    def close(self) -> None:
        if self._worker is not None:
            self._worker.close()
        if self.sock is not None:
            self.sock.close()
        self.link.close()


if __name__ == "__main__":
    # Through the package's module, not __main__: the classes it pickles must be the
    # ones the parent unpickles.
    from gcs_estimator.runtime import link_worker

    link_worker.main()
