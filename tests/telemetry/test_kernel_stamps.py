"""Receive times from the kernel: a datagram that waited in the socket's buffer is stamped
when it arrived, not when the station got round to it (so latency counts the queue and
the recording holds true arrival times), and datagrams the kernel dropped for a full
buffer are counted and said once."""

from __future__ import annotations

import io
import select
import socket
import sys
import time
from pathlib import Path

import pytest

from gcs_estimator.config import load_config
from gcs_estimator.ingest import endpoints
from gcs_estimator.ingest.flightdata import Recording
from gcs_estimator.ingest.sources import RCVBUF_BYTES, UdpSource
from gcs_estimator.ingest.telemetry.link import MavlinkLink
from gcs_estimator.ingest.telemetry.mavlink import read_tlog
from gcs_estimator.stop import Stop
from sim.truth import simulate
from sim.vehicle import SimulatedVehicle
from tests.telemetry.test_link import SHORT

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux"), reason="SO_TIMESTAMPNS and SO_RXQ_OVFL are Linux's"
)

QUEUED_S = 0.3
"""How long the test lets the datagrams wait in the buffer before the station reads."""


def _packets(tmp_path: Path) -> list[bytes]:
    config = load_config("noc_uav", SHORT)
    fl = simulate(config, seed=3)
    rec = Recording(fl.t_s, fl.inputs, fl.measurements, "throttle")
    path = tmp_path / "v.tlog"
    SimulatedVehicle(rec, config.link, ("127.0.0.1", 9), speed=0.0, tlog=path).run()
    return [r.packet for r in read_tlog(path)]


def _stamping(station: socket.socket, vehicle: socket.socket) -> None:
    """Wait until the kernel stamps datagrams as they arrive. Linux turns its receive
    stamps on from a deferred work item when the first socket asks for them; until it
    has run, a datagram is stamped when it is read (the fallback the station has anyway).
    A probe is sent, left to wait, and read, until its stamp is earlier than its read."""
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline:
        vehicle.sendto(b"probe", station.getsockname())
        select.select([station], [], [], 1.0)
        time.sleep(0.05)  # the probe waits in the buffer
        _, ancillary, _, _ = station.recvmsg(64, endpoints.ANCILLARY_BYTES)
        read = time.time()
        if endpoints.arrival(ancillary, read)[0] < read - 0.025:
            return
    pytest.fail("this system gives no kernel receive stamps within 10 s of asking")


def test_a_queued_datagram_is_stamped_when_it_arrived(tmp_path: Path) -> None:
    config = load_config("noc_uav", SHORT)
    packets = _packets(tmp_path)[:300]
    station = endpoints.open_socket(endpoints.parse("udpin:127.0.0.1:0", True), RCVBUF_BYTES)
    vehicle = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    _stamping(station, vehicle)
    sent_from = time.time()
    for p in packets:
        vehicle.sendto(p, station.getsockname())
    sent_until = time.time()
    time.sleep(QUEUED_S)  # the station is busy elsewhere: the datagrams wait
    read_from = time.time()
    link = MavlinkLink(config.link, log=io.StringIO())
    source = UdpSource(station, link, idle_exit_s=0.3)
    frames = [f for f in source.frames(Stop()) if f is not None]
    source.close()
    vehicle.close()
    assert frames and link.health.total().received == len(packets)
    for f in frames:
        assert sent_from - 1e-3 <= f.t_recv_s <= sent_until + 1e-3 < read_from - QUEUED_S / 2
    assert source.link_stats()["dropped_by_this_machine"] == 0


def test_datagrams_dropped_for_a_full_buffer_are_counted(tmp_path: Path) -> None:
    config = load_config("noc_uav", SHORT)
    packets = _packets(tmp_path)
    station = endpoints.open_socket(endpoints.parse("udpin:127.0.0.1:0", True), RCVBUF_BYTES)
    station.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # a tiny buffer
    vehicle = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    log = io.StringIO()
    link = MavlinkLink(config.link, log=log)
    source = UdpSource(station, link, idle_exit_s=0.3)
    frames = source.frames(Stop())
    for p in packets[:400]:  # far more than the buffer holds: most are dropped
        vehicle.sendto(p, station.getsockname())
    next(frames)  # the station reads what the buffer kept
    for p in packets[400:]:  # later datagrams carry the kernel's drop count
        vehicle.sendto(p, station.getsockname())
    list(frames)
    source.close()
    vehicle.close()
    dropped = source.link_stats()["dropped_by_this_machine"]
    assert dropped > 0
    assert dropped + link.health.total().received <= len(packets)
    assert "dropped by this machine" in log.getvalue()
