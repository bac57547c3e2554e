"""Where the simulated vehicle's bytes go: UDP to the station (udpout), UDP to whoever
speaks first (udpin), or a serial port. One port may carry several vehicles, as one
radio carries one autopilot's components: each vehicle sees everything that arrives."""

from __future__ import annotations

import contextlib
import select
import socket
import threading
import time
from typing import TYPE_CHECKING, Protocol

from gcs_estimator.ingest import endpoints
from gcs_estimator.ingest.endpoints import Endpoint

if TYPE_CHECKING:
    import serial


class Port(Protocol):
    def send(self, packet: bytes) -> None:
        """Send one packet (never raises: a vehicle keeps flying when nobody listens)."""
        ...

    def receive(self) -> list[bytes]:
        """What arrived since the last call, without waiting."""
        ...

    def close(self) -> None: ...


class UdpOut:
    """Datagrams to the station's address; its answers come back to our port."""

    def __init__(self, target: tuple[str, int]) -> None:
        self.target = target
        family = socket.getaddrinfo(target[0], target[1], type=socket.SOCK_DGRAM)[0][0]
        self.sock = socket.socket(family, socket.SOCK_DGRAM)
        loopback = target[0].startswith("127.") or target[0] == "::1"
        if family == socket.AF_INET6:
            self.sock.bind(("::1" if loopback else "::", 0))
        else:
            self.sock.bind(("127.0.0.1" if loopback else "0.0.0.0", 0))
        self.sock.setblocking(False)

    def send(self, packet: bytes) -> None:
        # Nobody listening (ICMP unreachable) is no reason to stop flying.
        with contextlib.suppress(OSError):
            self.sock.sendto(packet, self.target)

    def receive(self) -> list[bytes]:
        out: list[bytes] = []
        while True:
            try:
                data, _ = self.sock.recvfrom(65535)
            except OSError:  # drained, or the station went away
                return out
            out.append(data)

    def close(self) -> None:
        self.sock.close()


class UdpIn:
    """A bound UDP port: the station speaks first (its heartbeat), and the vehicle
    answers to the address it last heard from."""

    def __init__(self, endpoint: Endpoint) -> None:
        self.sock = endpoints.open_socket(endpoint, 1 << 20)
        self.peer: tuple[str, int] | None = None
        self._pending: list[bytes] = []
        """Received while waiting for the station, kept for receive()."""

    @property
    def bound(self) -> tuple[str, int]:
        host, port = self.sock.getsockname()[:2]
        return str(host), int(port)

    def wait_for_peer(self, timeout_s: float | None) -> bool:
        """Wait until a station has sent something (kept for receive()); False on timeout."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while self.peer is None:
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                return False
            wait = 0.5 if left is None else min(left, 0.5)
            ready, _, _ = select.select([self.sock], [], [], wait)
            if ready:
                self._pending = self.receive()
        return True

    def send(self, packet: bytes) -> None:
        if self.peer is None:  # nobody has spoken yet: nowhere to send it
            return
        with contextlib.suppress(OSError):
            self.sock.sendto(packet, self.peer)

    def receive(self) -> list[bytes]:
        out, self._pending = list(self._pending), []
        while True:
            try:
                data, addr = self.sock.recvfrom(65535)
            except OSError:
                return out
            self.peer = (str(addr[0]), int(addr[1]))
            out.append(data)

    def close(self) -> None:
        self.sock.close()


class SerialPort:
    """A serial device (a radio, or one end of a pty pair in the tests)."""

    def __init__(self, endpoint: Endpoint) -> None:
        self.port: serial.Serial = endpoints.open_serial(endpoint)
        self.port.timeout = 0

    def send(self, packet: bytes) -> None:
        import serial

        with contextlib.suppress(serial.SerialException, OSError):
            self.port.write(packet)

    def receive(self) -> list[bytes]:
        import serial

        try:
            data = self.port.read(self.port.in_waiting or 1)
        except (serial.SerialException, OSError):
            return []
        return [data] if data else []

    def close(self) -> None:
        self.port.close()


class Shared:
    """One port for several vehicles: sends one at a time, everything received goes to
    every vehicle (each answers only what is addressed to it), closed with the last."""

    def __init__(self, port: Port, users: int) -> None:
        self.port = port
        self._lock = threading.Lock()
        self._inbox: dict[int, list[bytes]] = {i: [] for i in range(users)}
        self._open = users

    def user(self, index: int) -> SharedUser:
        return SharedUser(self, index)

    def send(self, packet: bytes) -> None:
        with self._lock:
            self.port.send(packet)

    def receive(self, index: int) -> list[bytes]:
        with self._lock:
            arrived = self.port.receive()
            for box in self._inbox.values():
                box.extend(arrived)
            out, self._inbox[index] = self._inbox[index], []
        return out

    def close(self) -> None:
        with self._lock:
            self._open -= 1
            if self._open == 0:
                self.port.close()


class SharedUser:
    """One vehicle's view of a Shared port."""

    def __init__(self, shared: Shared, index: int) -> None:
        self.shared = shared
        self.index = index

    def send(self, packet: bytes) -> None:
        self.shared.send(packet)

    def receive(self) -> list[bytes]:
        return self.shared.receive(self.index)

    def close(self) -> None:
        self.shared.close()
