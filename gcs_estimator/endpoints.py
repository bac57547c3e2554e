"""Connection strings as MAVProxy and QGroundControl users write them, for UDP.

    udpin:HOST:PORT   listen on HOST:PORT (the vehicle sends to it); PORT 0: any free port
    udp:HOST:PORT     the same (as in pymavlink's mavutil)
    udpout:HOST:PORT  send to HOST:PORT first (the vehicle, or a router, listens there)
    tcp:HOST:PORT     connect to HOST:PORT (ArduPilot's SITL serves tcp:127.0.0.1:5760)
    tcpin:HOST:PORT   wait for one TCP connection on HOST:PORT
    HOST:PORT         udpin (listen) for the station, udpout (send) for the simulated vehicle

HOST may be a name, an IPv4 address or an IPv6 address in brackets ([::1]:14550). Serial
links are refused with the way to reach them through a router, not mistaken for UDP.
"""

from __future__ import annotations

import socket
from dataclasses import dataclass

from gcs_estimator.config import ConfigError

Address = tuple[str, int]

ROUTED = (
    "serial:",
    "/dev/",
    "COM",
)
"""Forms this station does not open itself (yet): routed through MAVProxy or mavlink-router."""


@dataclass(frozen=True)
class Endpoint:
    listen: bool
    """True: bind here and wait for the vehicle; False: send to here first."""
    host: str
    port: int
    family: int
    tcp: bool = False

    @property
    def address(self) -> Address:
        return (self.host, self.port)

    def __str__(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        if self.tcp:
            return f"{'tcpin' if self.listen else 'tcp'}:{host}:{self.port}"
        return f"{'udpin' if self.listen else 'udpout'}:{host}:{self.port}"


def parse(text: str, default_listen: bool) -> Endpoint:
    """An endpoint from a connection string; a ConfigError that says what is wrong."""
    if text.startswith(ROUTED):
        raise ConfigError(
            f"endpoint {text!r}: serial links are not opened by the station itself yet; "
            "route them to UDP, e.g. mavproxy.py --master="
            + text.split(":", 1)[-1]
            + " --out=udpout:127.0.0.1:14550, then listen on udpin:127.0.0.1:14550"
        )
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
    sock.setblocking(False)
    return sock
