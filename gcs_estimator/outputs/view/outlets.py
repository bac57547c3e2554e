"""Where the view's data goes: Rerun recording streams, in this process or in a helper.

Everything the view logs is a small picklable operation (`Op`), applied to a
`rerun.RecordingStream` by `apply`. Sinks that cannot block the estimator (an .rrd file,
a gRPC server that viewers join) live on a stream in this process. Sinks that connect
out to a viewer ("spawn", "connect") live in a helper process: connecting to a viewer
that is absent takes seconds, and one that accepts the connection but never answers makes
the SDK's flush and exit hang indefinitely. The estimator only hands operations to a
bounded queue; at exit the helper gets `shutdown_timeout_s` to drain, then is killed.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import queue
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, TextIO

import numpy as np

from gcs_estimator.arrays import FloatArray
from gcs_estimator.outputs.view.layout import Range, SeriesStyle, build_blueprint
from gcs_estimator.stop import Stop

APPLICATION_ID = "gcs-estimator"


@dataclass(frozen=True)
class Columns:
    """Rows of one Scalars entity: index columns (timeline -> seconds) and values [N x k]."""

    entity: str
    times: dict[str, FloatArray]
    values: FloatArray


@dataclass(frozen=True)
class Text:
    """A Markdown document at one time (timeline -> seconds; none: static)."""

    entity: str
    times: dict[str, float]
    text: str


@dataclass(frozen=True)
class Style:
    """Static series names, colours and widths of one entity."""

    entity: str
    style: SeriesStyle


@dataclass(frozen=True)
class Layout:
    """The blueprint for these vehicles (sent again when a vehicle appears, when the
    coefficients' ranges have moved, and at the end with the identifiability marks)."""

    system_ids: tuple[int, ...]
    names: tuple[str, ...]
    axes: tuple[str, ...]
    power_input: str
    ranges: Mapping[int, Sequence[Range | None]] = field(default_factory=dict)
    """Per vehicle, each coefficient panel's y range (None: the viewer's own)."""
    marks: Mapping[int, Sequence[str]] = field(default_factory=dict)
    """Per vehicle, each coefficient's identifiability (panel titles; empty: none yet)."""


Op = Columns | Text | Style | Layout


def apply(rec: Any, op: Op) -> None:
    """Log one operation to a recording stream."""
    import rerun as rr

    if isinstance(op, Columns):
        rec.send_columns(
            op.entity,
            indexes=[
                rr.TimeColumn(name, duration=np.asarray(t, np.float64))
                for name, t in op.times.items()
            ],
            columns=rr.Scalars.columns(scalars=np.asarray(op.values, np.float64)),
        )
    elif isinstance(op, Text) and not op.times:
        rec.log(op.entity, rr.TextDocument(op.text, media_type=rr.MediaType.MARKDOWN), static=True)
    elif isinstance(op, Text):
        rec.send_columns(
            op.entity,
            indexes=[rr.TimeColumn(name, duration=[t]) for name, t in op.times.items()],
            columns=rr.TextDocument.columns(text=[op.text], media_type=["text/markdown"]),
        )
    elif isinstance(op, Style):
        rec.log(
            op.entity,
            rr.SeriesLines(
                names=list(op.style.names),
                colors=list(op.style.colors),
                widths=list(op.style.widths),
            ),
            static=True,
        )
    elif isinstance(op, Layout):
        rec.send_blueprint(
            build_blueprint(op.system_ids, op.names, op.axes, op.power_input, op.ranges, op.marks),
            make_active=True,
            make_default=True,
        )


class Outlet:
    """Takes operations; must never block for long."""

    description: str = ""

    def send(self, op: Op) -> None:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError


class LocalOutlet(Outlet):
    """A recording stream in this process with non-blocking sinks (file, gRPC server)."""

    def __init__(
        self,
        recording_id: str,
        save: Path | None = None,
        serve: tuple[str, int, str] | None = None,
        shutdown_timeout_s: float = 3.0,
        linger_s: float = 0.0,
        stop: Stop | None = None,
        log: TextIO = sys.stderr,
    ) -> None:
        import rerun as rr

        self.linger_s = linger_s
        """A server stays up this long after the run (viewers behind catch up)."""
        self.stop = stop
        self.log = log
        self.rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id)
        sinks: list[Any] = []
        parts = []
        self.server_uri: str | None = None
        if save is not None:
            save.parent.mkdir(parents=True, exist_ok=True)
            sinks.append(rr.FileSink(str(save)))
            parts.append(f"saving to {save}")
        if serve is not None:
            bind, port, memory_limit = serve
            _check_free(bind, port)
            server = rr.GrpcServerSink(bind, port, server_memory_limit=memory_limit)
            self.server_uri = server.uri
            sinks.append(server)
            parts.append(f"serving at {server.uri}")
        self.rec.set_sinks(*sinks)
        self.description = "; ".join(parts)
        self.timeout = shutdown_timeout_s

    def send(self, op: Op) -> None:
        apply(self.rec, op)

    def close(self) -> None:
        try:
            self.rec.flush(timeout_sec=self.timeout)
        except RuntimeError as exc:  # a flush timeout: the file keeps what was written
            print(f"note: view: {exc}", file=self.log)
        if self.server_uri is not None and self.linger_s > 0:
            self._linger()
        self.rec.disconnect()

    def _linger(self) -> None:
        """Keep serving after the run, so that a viewer that joined late or is behind
        gets the end too; a signal (Ctrl-C) ends the wait."""
        print(
            f"view: the run has ended; still serving {self.server_uri} for "
            f"{self.linger_s:g} s so viewers can catch up (Ctrl-C to stop now)",
            file=self.log,
            flush=True,
        )
        signals = self.stop.count if self.stop is not None else 0
        end = time.monotonic() + self.linger_s
        while time.monotonic() < end:
            if self.stop is not None and self.stop.count != signals:
                break
            time.sleep(LINGER_POLL_S)  # a slice of the wait, to notice a signal


LINGER_POLL_S = 0.1


def _check_free(bind: str, port: int) -> None:
    """Refuse a port another program listens on before the view's server is started on
    it: its server thread would stop at once, and the run would go on saying it serves.
    (A port freed a moment ago, in TIME_WAIT, is free: the probe reuses addresses as a
    server does.)"""
    import socket

    from gcs_estimator.schema import ConfigError

    family = socket.AF_INET6 if ":" in bind else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((bind, port))
        except OSError as exc:
            raise ConfigError(
                f"view.serve_port {port} on {bind}: cannot serve there ({exc.strerror}); "
                "choose another with --serve-port, or stop what holds it"
            ) from None


RemoteSink = tuple[Literal["spawn", "connect"], str]


def viewer_executable() -> str | None:
    """The viewer binary shipped with rerun-sdk in this environment (found even when the
    environment's bin directory is not on PATH)."""
    import rerun as rr

    for candidate in (
        Path(sys.executable).parent / "rerun",
        Path(rr.__file__).resolve().parent.parent / "rerun_cli" / "rerun",
    ):
        if candidate.exists():
            return str(candidate)
    return None


def _helper_main(
    ops: mp.Queue[Op | None], sinks: Sequence[RemoteSink], recording_id: str, timeout: float
) -> None:
    """The helper process: apply operations until told to stop, then leave without
    waiting for a viewer that may never answer."""
    import rerun as rr

    rec: Any = None
    try:
        rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id)
        real: list[Any] = []
        for kind, arg in sinks:
            if kind == "spawn":
                port = int(arg)
                rr.spawn(
                    port=port,
                    connect=False,
                    executable_path=viewer_executable(),
                    recording=rec,
                )
                real.append(rr.GrpcSink(f"rerun+http://127.0.0.1:{port}/proxy"))
            else:
                real.append(rr.GrpcSink(arg))
        rec.set_sinks(*real)
    except Exception as exc:  # say it once; the estimator goes on without this viewer
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        print(f"note: view: no viewer connection ({first}); the run goes on", file=sys.stderr)
        rec = None
    while True:
        op = ops.get()
        if op is None:
            break
        if rec is not None:
            apply(rec, op)
    if rec is not None:
        with contextlib.suppress(RuntimeError):  # a flush timeout: the viewer is silent
            rec.flush(timeout_sec=timeout)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)  # the SDK's own exit path may wait forever on a silent viewer


@dataclass
class ProcessOutlet(Outlet):
    """Viewer connections in a helper process behind a bounded queue."""

    sinks: Sequence[RemoteSink]
    recording_id: str
    shutdown_timeout_s: float = 3.0
    max_queued: int = 4000
    dropped: int = field(default=0, init=False)

    def __post_init__(self) -> None:
        ctx = mp.get_context("spawn")
        self.ops: mp.Queue[Op | None] = ctx.Queue(maxsize=self.max_queued)
        self.proc = ctx.Process(
            target=_helper_main,
            args=(self.ops, list(self.sinks), self.recording_id, self.shutdown_timeout_s),
            daemon=True,
            name="gcs-estimator-viewer",
        )
        self.proc.start()
        self.description = "; ".join(
            f"spawning a viewer on port {a}" if k == "spawn" else f"streaming to {a}"
            for k, a in self.sinks
        )

    def send(self, op: Op) -> None:
        try:
            self.ops.put_nowait(op)
        except queue.Full:
            if self.dropped == 0:
                print(
                    "note: view: the viewer connection is not keeping up; its display "
                    "skips data (files and results keep everything)",
                    file=sys.stderr,
                )
            self.dropped += 1

    def close(self) -> None:
        with contextlib.suppress(queue.Full):
            self.ops.put(None, timeout=0.5)
        self.proc.join(self.shutdown_timeout_s + 2.0)
        if self.proc.is_alive():
            print(
                "note: view: the viewer did not take the last data in time; connection cut",
                file=sys.stderr,
            )
            self.proc.kill()
            self.proc.join(2.0)
        self.ops.cancel_join_thread()  # never wait on a pipe nobody reads
        self.ops.close()
