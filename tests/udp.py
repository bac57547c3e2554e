"""Real UDP on loopback for the tests: a socket bound to a free port, and a ground
station's socket that asks a simulated vehicle (in this process) and reads its answers."""

from __future__ import annotations

import socket
import time
from collections.abc import Callable
from typing import Any

from gcs_estimator.ingest.telemetry import mavlink
from sim.ports import UdpOut
from sim.vehicle import SimulatedVehicle

DEADLINE_S = 10.0
"""Longest wait for a vehicle's answer [s]."""


def loopback(timeout_s: float | None = None) -> socket.socket:
    """A UDP socket bound to a free port of 127.0.0.1 (timeout_s: its receive timeout;
    0 makes it non-blocking)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    if timeout_s is not None:
        sock.settimeout(timeout_s)
    return sock


def port_of(sock: socket.socket) -> int:
    return int(sock.getsockname()[1])


class Ground:
    """A ground station's socket, a simulated vehicle's target (SimulatedVehicle or a
    subclass: the ArduPlane's)."""

    def __init__(self) -> None:
        self.sock = loopback(0.05)
        self.codec = mavlink.Codec(255, 190)

    def send(self, vehicle: SimulatedVehicle, msg: Any) -> None:
        assert isinstance(vehicle.port, UdpOut)
        self.sock.sendto(self.codec.pack(msg), vehicle.port.sock.getsockname())

    def until(self, vehicle: SimulatedVehicle, want: Callable[[Any], bool]) -> list[Any]:
        """Let the vehicle answer until a message it sent satisfies want; all it sent."""
        got: list[Any] = []
        end = time.monotonic() + DEADLINE_S
        while not any(want(m) for m in got):
            assert time.monotonic() < end, [m.get_type() for m in got]
            vehicle._serve()
            try:
                data = self.sock.recv(65535)
            except TimeoutError:
                continue
            got += [m for m in self.codec.parse(data) if m.get_type() != "BAD_DATA"]
        return got
