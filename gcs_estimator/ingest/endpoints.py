"""Connection strings as MAVProxy and QGroundControl users write them.

    udpin:HOST:PORT   listen on HOST:PORT (the vehicle sends to it); PORT 0: any free port
    udp:HOST:PORT     the same (as in pymavlink's mavutil)
    udpout:HOST:PORT  send to HOST:PORT first (the vehicle, or a router, listens there)
    tcp:HOST:PORT     connect to HOST:PORT (ArduPilot's SITL serves tcp:127.0.0.1:5760)
    tcpin:HOST:PORT   wait for one TCP connection on HOST:PORT
    HOST:PORT         udpin (listen) for the station, udpout (send) for the simulated vehicle
    DEVICE[,BAUD]     a serial port (/dev/ttyUSB0,57600, COM3,115200; also DEVICE:BAUD and
                      serial:DEVICE[,BAUD]); BAUD defaults to 57600, a telemetry radio's

HOST may be a name, an IPv4 address or an IPv6 address in brackets ([::1]:14550).
"""

from __future__ import annotations

import contextlib
import re
import socket
import struct
import sys
from dataclasses import dataclass
from typing import TYPE_CHECKING

from gcs_estimator.config import ConfigError

if TYPE_CHECKING:
    import serial

Address = tuple[str, int]

SERIAL_DEVICE = re.compile(r"^(?:serial:)?(/dev/[^,:]+|COM\d+|\\\\\.\\COM\d+)(?:[,:](\w*))?$")
"""A serial device (Unix path, or Windows COMn) and an optional baud rate after , or :."""
DEFAULT_BAUD = 57600
"""A telemetry radio's rate (SiK radios, MAVProxy's default)."""


@dataclass(frozen=True)
class Endpoint:
    listen: bool
    """True: bind here and wait for the vehicle; False: send to here first."""
    host: str
    port: int
    family: int
    tcp: bool = False
    device: str = ""
    """A serial device ("" for a network endpoint); port is then its baud rate."""

    @property
    def serial(self) -> bool:
        return bool(self.device)

    @property
    def address(self) -> Address:
        return (self.device, 0) if self.device else (self.host, self.port)

    def __str__(self) -> str:
        if self.device:
            return f"{self.device},{self.port}"
        host = f"[{self.host}]" if ":" in self.host else self.host
        if self.tcp:
            return f"{'tcpin' if self.listen else 'tcp'}:{host}:{self.port}"
        return f"{'udpin' if self.listen else 'udpout'}:{host}:{self.port}"


def parse(text: str, default_listen: bool) -> Endpoint:
    """An endpoint from a connection string; a ConfigError that says what is wrong."""
    if text.startswith(("serial:", "/dev/", "COM", "\\\\.\\")):
        return _serial(text)
    scheme, sep, rest = text.partition(":")
    tcp = bool(sep) and scheme in ("tcp", "tcpin")
    if sep and scheme in ("udpin", "udp", "udpout", "tcp", "tcpin"):
        listen = scheme in ("udpin", "udp", "tcpin")
    else:
        listen, rest = default_listen, text
    host, _, port = rest.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ConfigError(
            f"endpoint {text!r}: expected [udpin:|udpout:|udp:|tcp:|tcpin:]HOST:PORT with a "
            "port 0..65535"
        )
    if not listen and int(port) == 0:
        raise ConfigError(f"endpoint {text!r}: a port to send to is needed (not 0)")
    host = host or ("0.0.0.0" if listen else "127.0.0.1")
    try:
        info = socket.getaddrinfo(host, int(port), type=socket.SOCK_DGRAM)
    except socket.gaierror as exc:
        raise ConfigError(f"endpoint {text!r}: cannot resolve {host!r}: {exc.strerror}") from None
    family, _, _, _, sockaddr = info[0]
    return Endpoint(listen, str(sockaddr[0]), int(port), int(family), tcp)


def _serial(text: str) -> Endpoint:
    match = SERIAL_DEVICE.match(text)
    baud = match.group(2) if match else None
    if match is None or (baud and not baud.isdigit()):
        raise ConfigError(
            f"endpoint {text!r}: expected a serial device and an optional baud rate, "
            "e.g. /dev/ttyUSB0,57600 or COM3,115200"
        )
    rate = int(baud) if baud else DEFAULT_BAUD
    if rate <= 0:
        raise ConfigError(f"endpoint {text!r}: the baud rate must be positive")
    return Endpoint(True, "", rate, 0, device=match.group(1))


def open_serial(endpoint: Endpoint) -> serial.Serial:
    """The serial port, raw, 8N1, reads returning what has arrived within 20 ms. A
    missing or busy device is a ConfigError that names it."""
    import serial

    try:
        port = serial.Serial(endpoint.device, endpoint.port, timeout=0.02, write_timeout=1.0)
    except (serial.SerialException, ValueError) as exc:
        raise ConfigError(f"endpoint {endpoint}: cannot open: {exc}") from None
    return port


def open_tcp(endpoint: Endpoint, timeout_s: float = 5.0) -> socket.socket:
    """tcp: a connection to the vehicle (or SITL, or a router); tcpin: a socket listening
    for one. A refused or unreachable one is a ConfigError that names it."""
    sock = socket.socket(endpoint.family, socket.SOCK_STREAM)
    try:
        if endpoint.listen:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind(endpoint.address)
            sock.listen(1)
        else:
            sock.settimeout(timeout_s)
            sock.connect(endpoint.address)
    except OSError as exc:
        sock.close()
        what = "cannot listen" if endpoint.listen else "cannot connect"
        raise ConfigError(f"endpoint {endpoint}: {what}: {exc.strerror or exc}") from None
    sock.setblocking(False)
    return sock


def open_socket(endpoint: Endpoint, rcvbuf: int) -> socket.socket:
    """A non-blocking UDP socket: bound to the endpoint (listen), or to a free port of
    the same family (send). A port in use is a ConfigError that names it."""
    sock = socket.socket(endpoint.family, socket.SOCK_DGRAM)
    # SO_RCVBUF is capped by net.core.rmem_max; FORCE (privileged) is not.
    try:
        sock.setsockopt(socket.SOL_SOCKET, getattr(socket, "SO_RCVBUFFORCE", 33), rcvbuf)
    except OSError:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    bind = (
        endpoint.address
        if endpoint.listen
        else ("::" if endpoint.family == socket.AF_INET6 else "0.0.0.0", 0)
    )
    try:
        sock.bind(bind)
    except OSError as exc:
        sock.close()
        raise ConfigError(f"endpoint {endpoint}: cannot bind: {exc.strerror}") from None
    kernel_stamps(sock)
    sock.setblocking(False)
    return sock


SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
"""Linux: each datagram carries the kernel's arrival time (struct timespec)."""
SO_RXQ_OVFL = getattr(socket, "SO_RXQ_OVFL", 40)
"""Linux: datagrams carry the count the socket has dropped for a full buffer so far."""
ANCILLARY_BYTES = 64
"""Room for both (a timespec and a counter, with their headers)."""


def kernel_stamps(sock: socket.socket) -> None:
    """Ask for arrival times and the drop counter with every datagram (Linux); elsewhere
    nothing (receive times are then read after the fact). Linux starts stamping from a
    deferred work item when the first socket on the machine asks, so the first datagrams
    of a station may still be stamped when read."""
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
            sock.setsockopt(socket.SOL_SOCKET, SO_RXQ_OVFL, 1)


def arrival(ancillary: list[tuple[int, int, bytes]], fallback: float) -> tuple[float, int | None]:
    """(the kernel's arrival time [s since the epoch], or fallback; the socket's drop
    counter, or None) from a recvmsg's ancillary data."""
    t, dropped = fallback, None
    for level, kind, data in ancillary:
        if level != socket.SOL_SOCKET:
            continue
        if kind == SO_TIMESTAMPNS and len(data) >= 16:
            sec, nsec = struct.unpack("qq", data[:16])
            t = sec + nsec * 1e-9
        elif kind == SO_RXQ_OVFL and len(data) >= 4:
            (dropped,) = struct.unpack("I", data[:4])
    return t, dropped
