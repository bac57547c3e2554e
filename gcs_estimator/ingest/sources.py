"""Frame sources over MAVLink: live UDP, and .tlog recordings (session.RecordingSource
serves data files and simulated flights).

Both feed the same MavlinkLink (decode, link health, synchronise), so a replay of a
live session's recording makes the same frames as the live run did.
"""

from __future__ import annotations

import select
import socket
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO, TypeVar

from gcs_estimator.frames import Frame
from gcs_estimator.ingest import endpoints
from gcs_estimator.ingest.telemetry import mavlink
from gcs_estimator.ingest.telemetry.link import MavlinkLink
from gcs_estimator.ingest.telemetry.mavlink import (
    Codec,
    TlogError,
    TlogStats,
    read_tlog,
)
from gcs_estimator.stop import Stop

if TYPE_CHECKING:
    import serial

T = TypeVar("T")

RCVBUF_BYTES = 8 * 1024 * 1024
"""Listener socket buffer: the ~212 KB default drops packets at high rates."""

POLL_S = 0.02
"""Longest wait for a datagram before the sinks get an idle tick [s]."""
DRAIN_READS = 256
"""Reads per turn of a live source's loop: a link that never goes quiet still leaves
time for the ground station's own messages."""
SLEEP_SLICE_S = 0.05
"""A paced replay sleeps in slices this long, checking for a stop request between them."""


class SourceError(RuntimeError):
    """A source cannot deliver (unreadable or not a recording); the message says which."""


def open_udp(host: str, port: int) -> socket.socket:
    """A non-blocking UDP socket bound to an IPv4 host and port (endpoints.open_socket)."""
    return endpoints.open_socket(endpoints.Endpoint(True, host, port, socket.AF_INET), RCVBUF_BYTES)


class LiveSource:
    """The loop every live link shares: read what arrived, send the ground station's own
    messages once a second (heartbeat, rate requests until acknowledged), write the
    recording through, and end on a stop request, the idle timeout, the time limit or a
    link that failed. Subclasses say how to read and where the messages go."""

    def __init__(
        self, link: MavlinkLink, idle_exit_s: float | None, max_seconds: float | None
    ) -> None:
        self.link = link
        self.idle_exit_s = idle_exit_s
        self.max_seconds = max_seconds
        self.codec = Codec(mavlink.GCS_SYSTEM_ID, mavlink.GCS_COMPONENT_ID)
        link.sign(self.codec, time.time())
        self._last_data: float | None = None
        self._ended = False
        """The link failed or the other side closed it."""
        self.idle = False
        """Nothing was waiting to be read when the last None was yielded (the session
        then does restart work ahead: Session.work_ahead)."""
        self.wake_fds: list[int] = []
        """Descriptors whose data end a wait for the link's as well (a sharded session's
        workers' outputs: filter_worker.ShardedSession)."""

    def frames(self, stop: Stop) -> Iterator[Frame | None]:
        start = time.time()
        last_ground = 0.0
        while not stop.requested and not self._done(start):
            yield from self._receive()
            now = time.time()
            if now - last_ground >= 1.0:
                last_ground = now
                self._send_ground(now)
                self.link.flush_recording()
            self.idle = not self._waiting()
            yield None
        yield from self.link.flush()

    def _waiting(self) -> bool:
        """Whether more data is ready to be read now."""
        return False

    def _done(self, start: float) -> bool:
        now = time.time()
        if self._ended or (self.max_seconds is not None and now - start > self.max_seconds):
            return True
        last = self._last_data
        return self.idle_exit_s is not None and last is not None and now - last > self.idle_exit_s

    def _receive(self) -> Iterator[Frame]:
        """Frames completed by what arrived within about POLL_S."""
        raise NotImplementedError

    def _send_ground(self, now: float) -> None:
        raise NotImplementedError

    def _stream_ground(self, now: float) -> bytes:
        """The ground messages for a point-to-point stream (TCP, serial): all of them
        down the one line, and a heartbeat while nobody has been heard, as on udpout."""
        out = [p for p, _ in self.link.ground_messages(self.codec, now)]
        return b"".join(out or [self.codec.heartbeat(mavlink.MAV_TYPE_GCS)])

    def link_stats(self) -> dict[str, Any]:
        return self.link.stats()

    def close(self) -> None:
        self.link.close()


class UdpSource(LiveSource):
    """Datagrams from a bound UDP socket; the ground station's own messages go back to
    each vehicle's address."""

    def __init__(
        self,
        sock: socket.socket,
        link: MavlinkLink,
        idle_exit_s: float | None = None,
        max_seconds: float | None = None,
        peer: tuple[str, int] | None = None,
    ) -> None:
        super().__init__(link, idle_exit_s, max_seconds)
        self.peer = peer
        """udpout: where the station speaks first (heartbeats) until a vehicle answers."""
        self.sock = sock
        self.kernel_dropped = 0
        """Datagrams the system dropped because this socket's buffer was full (the
        kernel's counter, as of the last datagram that carried it)."""

    def _receive(self) -> Iterator[Frame]:
        fd = self.sock.fileno()
        ready, _, _ = select.select([fd, *self.wake_fds], [], [], POLL_S)
        if fd in ready:
            yield from self._drain()

    def _drain(self) -> Iterator[Frame]:
        """Datagrams waiting, each with the kernel's arrival time where the system gives
        it (endpoints.kernel_stamps), so time spent queued in the socket counts as latency
        and the recording holds when packets really arrived."""
        for _ in range(DRAIN_READS):  # then the loop's own work (ground messages) comes
            try:
                data, ancillary, _, addr = self.sock.recvmsg(65535, endpoints.ANCILLARY_BYTES)
            except OSError:  # BlockingIOError: drained
                return
            now = self._last_data = time.time()
            t, dropped = endpoints.arrival(ancillary, now)
            if dropped is not None and dropped > self.kernel_dropped:
                if self.kernel_dropped == 0:
                    self.link.report_once(
                        "kernel-drop",
                        "packets dropped by this machine: the socket's buffer was full "
                        "(the station fell behind the link)",
                    )
                self.kernel_dropped = dropped
            yield from self.link.datagram(data, min(t, now), addr)

    def _waiting(self) -> bool:
        return bool(select.select([self.sock], [], [], 0)[0])

    def _send_ground(self, now: float) -> None:
        out = list(self.link.ground_messages(self.codec, now))
        if self.peer is not None and all(a[:2] != self.peer for _, a in out):
            out.append((self.codec.heartbeat(mavlink.MAV_TYPE_GCS), self.peer))
        for packet, address in out:
            try:
                self.sock.sendto(packet, address)
            except OSError:
                self.link.report_once("send", f"cannot send to {address}: vehicle gone?")

    def link_stats(self) -> dict[str, Any]:
        return {**self.link.stats(), "dropped_by_this_machine": self.kernel_dropped}

    def close(self) -> None:
        self.sock.close()
        super().close()


class TcpSource(LiveSource):
    """Bytes from one TCP connection: to the vehicle (tcp:), or from it once it connects
    (tcpin:). Packets may be split across reads (MavlinkLink.stream); the ground
    station's messages go back over the same connection. The vehicle closing it ends
    the session, as the idle timeout would."""

    def __init__(
        self,
        sock: socket.socket,
        link: MavlinkLink,
        listening: bool,
        idle_exit_s: float | None = None,
        max_seconds: float | None = None,
    ) -> None:
        super().__init__(link, idle_exit_s, max_seconds)
        self._listener = sock if listening else None
        self._conn: socket.socket | None = None if listening else sock
        self._address = self._peer_of(self._conn)

    @staticmethod
    def _peer_of(conn: socket.socket | None) -> tuple[str, int] | None:
        return None if conn is None else tuple(conn.getpeername()[:2])

    def frames(self, stop: Stop) -> Iterator[Frame | None]:
        while self._conn is None and not stop.requested:
            assert self._listener is not None
            ready, _, _ = select.select([self._listener], [], [], POLL_S)
            if ready:
                self._conn, _ = self._listener.accept()
                self._conn.setblocking(False)
                self._address = self._peer_of(self._conn)
            yield None
        if self._conn is not None:
            yield from super().frames(stop)

    def _receive(self) -> Iterator[Frame]:
        assert self._conn is not None and self._address is not None
        fd = self._conn.fileno()
        ready, _, _ = select.select([fd, *self.wake_fds], [], [], POLL_S)
        if fd not in ready:
            return
        for _ in range(DRAIN_READS):
            try:
                data = self._conn.recv(65536)
            except BlockingIOError:
                return
            except OSError as exc:
                data = b""
                self.link.report_once("tcp", f"the connection failed: {exc.strerror or exc}")
            if not data:
                self._ended = True
                self.link.report_once("tcp-closed", "the vehicle closed the connection")
                return
            t = self._last_data = time.time()
            yield from self.link.stream(data, t, self._address)

    def _waiting(self) -> bool:
        return self._conn is not None and bool(select.select([self._conn], [], [], 0)[0])

    def _send_ground(self, now: float) -> None:
        assert self._conn is not None
        try:
            self._conn.sendall(self._stream_ground(now))
        except OSError:
            self.link.report_once("send", "cannot send on the connection: vehicle gone?")

    def close(self) -> None:
        for sock in (self._listener, self._conn):
            if sock is not None:
                sock.close()
        super().close()


class SerialSource(LiveSource):
    """Bytes from a serial port (a telemetry radio, a USB cable to the autopilot).
    Packets may be split across reads (MavlinkLink.stream); the ground station's
    messages go back over the same port."""

    def __init__(
        self,
        port: serial.Serial,
        link: MavlinkLink,
        idle_exit_s: float | None = None,
        max_seconds: float | None = None,
    ) -> None:
        super().__init__(link, idle_exit_s, max_seconds)
        self.port = port
        self.address = (f"serial:{port.port}", 0)

    def _receive(self) -> Iterator[Frame]:
        """What arrived: waits up to the port's read timeout for the first byte."""
        import serial

        try:
            data = self.port.read(max(1, self.port.in_waiting))
        except (serial.SerialException, OSError) as exc:
            self._ended = True
            self.link.report_once("serial", f"the serial port failed: {exc}")
            return
        if data:
            t = self._last_data = time.time()
            yield from self.link.stream(data, t, self.address)

    def _waiting(self) -> bool:
        try:
            return bool(self.port.in_waiting)
        except (OSError, ValueError):
            return False

    def _send_ground(self, now: float) -> None:
        import serial

        try:
            self.port.write(self._stream_ground(now))
        except (serial.SerialException, OSError) as exc:
            self.link.report_once("send", f"cannot write to the serial port: {exc}")

    def close(self) -> None:
        self.port.close()
        super().close()


class TlogSource:
    """The packets of .tlog files, in order, as fast as possible or at a multiple of the
    recorded real time (speed > 0)."""

    def __init__(
        self,
        paths: Sequence[str | Path],
        link: MavlinkLink,
        speed: float = 0.0,
        log: TextIO | None = None,
    ) -> None:
        self.paths = [Path(p) for p in paths]
        self.link = link
        self.speed = speed
        self.log = sys.stderr if log is None else log
        self.total = 0
        self._stats = TlogStats()
        self.errors: list[str] = []
        """Files that could not be replayed (the others' frames are processed)."""

    def _records(
        self, path: Path, stats: TlogStats, read: Callable[[Path, TlogStats], Iterator[T]]
    ) -> Iterator[T]:
        """The file's records as `read` reads them (a piece at a time; read_tlog, or
        tlog_fast's runs of records), with its notes."""
        try:
            self.total = path.stat().st_size
            if self.total == 0:
                raise SourceError(f"{path}: an empty file (no MAVLink record)")
            yield from read(path, stats)
        except TlogError as exc:
            raise SourceError(str(exc)) from exc
        except OSError as exc:
            raise SourceError(f"{path}: cannot read: {exc.strerror}") from exc
        if stats.junk_bytes:
            print(f"note: {path}: {stats.junk_bytes} garbage bytes skipped", file=self.log)
        if stats.bad_times:
            print(
                f"note: {path}: {stats.bad_times} record(s) with a corrupt receive time kept, "
                "stamped with the time of the record before",
                file=self.log,
            )
        if stats.time_jumps:
            print(
                f"note: {path}: the recording's clock jumped {stats.time_jumps} time(s) "
                "(recordings joined into one file, or the recorder's clock set); every "
                "record kept",
                file=self.log,
            )
        if stats.truncated_tail:
            print(
                f"note: {path}: truncated at the end; the last partial record is ignored",
                file=self.log,
            )

    def frames(self, stop: Stop) -> Iterator[Frame | None]:
        t0_rec = t0_wall = None
        for path in self.paths:
            self._stats = stats = TlogStats()
            try:
                jumps = 0
                for rec in self._records(path, stats, read_tlog):
                    if stop.requested:
                        break
                    t = rec.t_recv_us * 1e-6
                    if self.speed > 0:
                        if t0_rec is None or t0_wall is None or stats.time_jumps != jumps:
                            # The first record, or a new time base: its time is now.
                            jumps = stats.time_jumps
                            t0_rec, t0_wall = t, time.time()
                        yield from self._wait((t - t0_rec) / self.speed + t0_wall, stop)
                    yield from self.link.packet(rec.packet, t)
            except SourceError as exc:
                self.errors.append(str(exc))
                print(f"error: {exc}; skipped", file=self.log)
        yield from self.link.flush()

    @staticmethod
    def _wait(until: float, stop: Stop) -> Iterator[None]:
        """Sleep until the wall-clock time `until`, in slices, ticking the sinks and
        giving up as soon as a stop is requested."""
        while not stop.requested:
            left = until - time.time()
            if left <= 0:
                return
            time.sleep(min(left, SLEEP_SLICE_S))
            yield None

    def progress(self) -> tuple[int, int]:
        """(bytes read, bytes in the current file)."""
        return self._stats.position, self.total

    @property
    def done(self) -> int:
        """Records of the current file replayed so far."""
        return self._stats.records

    def link_stats(self) -> dict[str, Any]:
        return self.link.stats()

    def close(self) -> None:
        self.link.close()
