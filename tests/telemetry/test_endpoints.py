"""Connection strings: udpin:, udp:, udpout:, bare HOST:PORT and IPv6 work on loopback
with real sockets; TCP both ways; a bad, busy or unresolvable endpoint gives one clear
line and exit 2 (serial and a vehicle on udpin: test_serial_udpin.py)."""

from __future__ import annotations

import argparse
import contextlib
import io
import random
import socket
import time
from pathlib import Path

import numpy as np
import pytest

from gcs_estimator.cli import main
from gcs_estimator.config import AircraftConfig, ConfigError, load_config
from gcs_estimator.frames import Frame
from gcs_estimator.ingest import endpoints
from gcs_estimator.ingest.flightdata import Recording
from gcs_estimator.ingest.sources import RCVBUF_BYTES, TcpSource, TlogSource, UdpSource
from gcs_estimator.ingest.telemetry import mavlink
from gcs_estimator.ingest.telemetry.link import MavlinkLink
from gcs_estimator.ingest.telemetry.mavlink import read_tlog
from gcs_estimator.stop import Stop
from sim.cli import _target
from sim.truth import simulate
from sim.vehicle import SimulatedVehicle
from tests.telemetry.test_link import SHORT
from tests.udp import loopback, port_of

DEADLINE_S = 30.0


@pytest.mark.parametrize(
    ("text", "listen", "host", "port"),
    [
        ("udpin:127.0.0.1:14550", True, "127.0.0.1", 14550),
        ("udp:127.0.0.1:14551", True, "127.0.0.1", 14551),
        ("udpout:127.0.0.1:14552", False, "127.0.0.1", 14552),
        ("127.0.0.1:14553", True, "127.0.0.1", 14553),
        ("udpin:[::1]:0", True, "::1", 0),
        ("udpin::14554", True, "0.0.0.0", 14554),
        ("udpout:localhost:14555", False, None, 14555),
    ],
)
def test_connection_strings(text: str, listen: bool, host: str | None, port: int) -> None:
    e = endpoints.parse(text, default_listen=True)
    assert (e.listen, e.port) == (listen, port)
    if host is not None:
        assert e.host == host


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ("udpin:127.0.0.1:70000", "port 0..65535"),
        ("udpin:127.0.0.1", "port 0..65535"),
        ("udpout:127.0.0.1:0", "a port to send to"),
        ("udpout:no-such-host.invalid:14550", "cannot resolve"),
    ],
)
def test_bad_endpoints_say_what_is_wrong(text: str, says: str) -> None:
    with pytest.raises(ConfigError, match=says.replace(".", r"\.")):
        endpoints.parse(text, default_listen=True)


def test_a_busy_port_is_one_line_and_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    busy = loopback()
    port = port_of(busy)
    code = main(
        ["listen", f"udpin:127.0.0.1:{port}", "--view", "off", "--out", str(tmp_path / "o")]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert err[-1].startswith("error: endpoint udpin:127.0.0.1:") and "cannot bind" in err[-1]
    assert not (tmp_path / "o" / "telemetry.tlog").exists()  # nothing opened for writing
    busy.close()


def test_a_vehicle_over_ipv6_loopback(tmp_path: Path) -> None:
    config = load_config("noc_uav", SHORT)
    station = endpoints.open_socket(endpoints.parse("udpin:[::1]:0", True), RCVBUF_BYTES)
    port = station.getsockname()[1]
    fl = simulate(config, seed=5)
    rec = Recording(fl.t_s, fl.inputs, fl.measurements, "throttle")
    target = _target(f"udpout:[::1]:{port}")
    assert isinstance(target, tuple)
    vehicle = SimulatedVehicle(rec, config.link, target, speed=0.0)
    vehicle.run()
    link = MavlinkLink(config.link, log=io.StringIO())
    frames = [f for f in UdpSource(station, link, idle_exit_s=0.5).frames(Stop()) if f]
    assert len(frames) == len(fl.t_s)
    address = link.vehicles[1].address
    assert address is not None and address[0] == "::1"
    station.close()


def test_udpout_speaks_first_then_takes_the_vehicle_that_answers() -> None:
    config = load_config("noc_uav")
    vehicle = loopback(DEADLINE_S)
    endpoint = endpoints.parse(f"udpout:127.0.0.1:{port_of(vehicle)}", True)
    station = endpoints.open_socket(endpoint, RCVBUF_BYTES)
    link = MavlinkLink(config.link, log=io.StringIO())
    frames = UdpSource(station, link, peer=endpoint.address).frames(Stop())
    next(frames)  # the first idle tick sends the station's heartbeat to the peer
    data, station_address = vehicle.recvfrom(65535)
    assert [m.get_type() for m in mavlink.Codec(1, 1).parse(data)] == ["HEARTBEAT"]
    vehicle.sendto(mavlink.Codec(1, 1).heartbeat(mavlink.MAV_TYPE_FIXED_WING), station_address)
    end = time.monotonic() + DEADLINE_S
    while 1 not in link.vehicles:
        assert time.monotonic() < end
        next(frames)
    assert link.vehicles[1].address == vehicle.getsockname()
    vehicle.close()
    station.close()


def test_the_simulated_vehicle_takes_the_same_strings() -> None:
    assert _target("udpout:127.0.0.1:14550") == ("127.0.0.1", 14550)
    assert _target("127.0.0.1:14550") == ("127.0.0.1", 14550)
    assert _target("[::1]:14550") == ("::1", 14550)
    with pytest.raises(argparse.ArgumentTypeError, match="speaks UDP or serial"):
        _target("tcp:127.0.0.1:5760")
    with pytest.raises(argparse.ArgumentTypeError, match="cannot resolve"):
        _target("udpout:no-such-host.invalid:14550")


def _flight_packets(config: AircraftConfig, tmp_path: Path) -> list[bytes]:
    fl = simulate(config, seed=6)
    rec = Recording(fl.t_s, fl.inputs, fl.measurements, "throttle")
    path = tmp_path / "v.tlog"
    SimulatedVehicle(rec, config.link, ("127.0.0.1", 9), speed=0.0, tlog=path).run()
    return [r.packet for r in read_tlog(path)]


def _rows(frames: list[Frame]) -> np.ndarray:
    return np.array([(f.t_vehicle_s, *f.inputs, *f.y) for f in frames])


@pytest.mark.parametrize("station_listens", [False, True], ids=["tcp", "tcpin"])
def test_a_vehicle_over_tcp_with_packets_split_anywhere(
    tmp_path: Path, station_listens: bool
) -> None:
    """The byte stream is cut at random places (packets split across reads, junk in
    between): the station makes the frames a replay of the same packets makes."""
    config = load_config("noc_uav", SHORT)
    packets = _flight_packets(config, tmp_path)
    stream = b"".join(packets[:100]) + b"\xfd\x09junk" + b"".join(packets[100:])
    replayed = [
        f for f in TlogSource([tmp_path / "v.tlog"], MavlinkLink(config.link)).frames(Stop()) if f
    ]

    if station_listens:
        endpoint = endpoints.parse("tcpin:127.0.0.1:0", True)
        station = endpoints.open_tcp(endpoint)
        vehicle = socket.create_connection(station.getsockname()[:2])
    else:
        server = socket.socket()
        server.bind(("127.0.0.1", 0))
        server.listen(1)
        endpoint = endpoints.parse(f"tcp:127.0.0.1:{server.getsockname()[1]}", True)
        station = endpoints.open_tcp(endpoint)
        vehicle, _ = server.accept()
        server.close()
    link = MavlinkLink(config.link, log=io.StringIO())
    source = TcpSource(station, link, station_listens)
    frames_it = source.frames(Stop())
    rng = random.Random(11)
    i = 0
    got: list[Frame] = []
    while i < len(stream):
        n = rng.randint(1, 600)
        vehicle.sendall(stream[i : i + n])
        i += n
        f = next(frames_it)
        if f is not None:
            got.append(f)
    vehicle.setblocking(False)
    heard: list[str] = []
    end = time.monotonic() + DEADLINE_S
    while "HEARTBEAT" not in heard:  # the station speaks back on the connection
        assert time.monotonic() < end
        f = next(frames_it)
        if f is not None:
            got.append(f)
        with contextlib.suppress(BlockingIOError):
            heard += [m.get_type() for m in mavlink.Codec(9, 9).parse(vehicle.recv(65535))]
    vehicle.close()  # the vehicle hangs up: the session ends
    got += [f for f in frames_it if f is not None]
    source.close()
    np.testing.assert_array_equal(_rows(got), _rows(replayed))  # NaN where NaN
    h = link.health.total()
    assert h.corrupt == 1 and h.received == len(packets) and h.lost == 0


def test_tcp_refused_is_one_line_and_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    closed = socket.socket()
    closed.bind(("127.0.0.1", 0))
    port = closed.getsockname()[1]
    closed.close()  # nothing listens there
    code = main(["listen", f"tcp:127.0.0.1:{port}", "--view", "off", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and "cannot connect" in err[-1] and err[-1].startswith("error: endpoint tcp:")
