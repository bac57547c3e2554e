"""Who may speak: a vehicle's address is pinned at first contact. Over real UDP sockets on
loopback a second sender using its system id neither moves it nor receives the station's
heartbeats and commands, and its acknowledgement does not stop the rate requests; the
vehicle's own acknowledgement does."""

from __future__ import annotations

import io
import socket
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from gcs_estimator.config import load_config
from gcs_estimator.frames import Frame
from gcs_estimator.ingest.sources import UdpSource, open_udp
from gcs_estimator.ingest.telemetry import mavlink
from gcs_estimator.ingest.telemetry.decode import DecodeStats, decode_packet
from gcs_estimator.ingest.telemetry.link import MavlinkLink
from gcs_estimator.ingest.telemetry.vehicles import PIN_MOVE_S, link_name
from gcs_estimator.stop import Stop
from tests.telemetry.test_link import recorded_flight
from tests.udp import loopback

DEADLINE_S = 30.0
"""Hang guard: every wait below ends when what it waits for happened."""


def _peer() -> socket.socket:
    return loopback(0)


def _received(sock: socket.socket) -> list[str]:
    """Types of the messages waiting on a peer's socket."""
    codec = mavlink.Codec(9, 9)
    out: list[str] = []
    while True:
        try:
            data = sock.recv(65535)
        except BlockingIOError:
            return out
        out += [m.get_type() for m in codec.parse(data)]


def _run_until(frames: Iterator[Frame | None], done: Callable[[], bool]) -> None:
    end = time.monotonic() + DEADLINE_S
    while not done():
        assert time.monotonic() < end, "the station did not get there"
        next(frames)


def test_a_second_sender_with_the_vehicles_id_is_dropped_and_told_nothing() -> None:
    config = load_config("noc_uav")
    station = open_udp("127.0.0.1", 0)
    where = station.getsockname()
    log = io.StringIO()
    link = MavlinkLink(config.link, log=log)
    frames = UdpSource(station, link).frames(Stop())
    vehicle, spoofer = _peer(), _peer()
    real, fake = mavlink.Codec(1, 1), mavlink.Codec(1, 1)

    vehicle.sendto(real.heartbeat(mavlink.MAV_TYPE_FIXED_WING), where)
    _run_until(frames, lambda: 1 in link.vehicles)
    fake_name = link_name(spoofer.getsockname())
    spoofer.sendto(fake.heartbeat(mavlink.MAV_TYPE_FIXED_WING), where)
    ack = mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAV_RESULT_ACCEPTED, 255, 190
    spoofer.sendto(fake.command_ack(*ack), where)
    _run_until(frames, lambda: link.health.counts(fake_name).foreign == 2)

    got: list[str] = []

    def two_rounds() -> bool:
        got.extend(_received(vehicle))
        return got.count("HEARTBEAT") >= 2 and "COMMAND_LONG" in got

    _run_until(frames, two_rounds)
    assert _received(spoofer) == []  # nothing was sent to the second sender
    v = link.vehicles[1]
    assert v.address == vehicle.getsockname()
    assert v.acked == set()  # its acknowledgement did not count
    assert "not from its address" in log.getvalue()

    vehicle.sendto(real.command_ack(*ack), where)
    _run_until(frames, lambda: mavlink.MAV_RESULT_ACCEPTED in v.acked)
    for s in (station, vehicle, spoofer):
        s.close()


@pytest.mark.parametrize("addressed_to", [255, 0])
def test_an_ack_counts_only_for_a_request_we_sent_and_only_addressed_to_us(
    addressed_to: int,
) -> None:
    config = load_config("noc_uav")
    link = MavlinkLink(config.link, log=io.StringIO())
    codec = mavlink.Codec(1, 1)
    here = ("127.0.0.1", 5760)
    list(link.datagram(codec.heartbeat(mavlink.MAV_TYPE_FIXED_WING), 1.0, here))
    ack = mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAV_RESULT_ACCEPTED
    list(link.datagram(codec.command_ack(*ack, addressed_to), 1.1, here))
    assert link.vehicles[1].acked == set()  # nothing asked yet
    list(link.ground_messages(mavlink.Codec(255, 190), 2.0))  # the rate requests go out
    list(link.datagram(codec.command_ack(*ack, 42), 2.1, here))  # for another station
    assert link.vehicles[1].acked == set()
    # A gimbal on the vehicle's system id answers too: the request did not go to it.
    gimbal = mavlink.Codec(1, 154)
    list(link.datagram(gimbal.command_ack(*ack, addressed_to), 2.15, here))
    assert link.vehicles[1].acked == set()
    list(link.datagram(codec.command_ack(*ack, addressed_to), 2.2, here))
    assert link.vehicles[1].acked == {mavlink.MAV_RESULT_ACCEPTED}


def test_the_pin_moves_once_the_vehicles_address_is_silent() -> None:
    config = load_config("noc_uav")
    log = io.StringIO()
    link = MavlinkLink(config.link, log=log)
    codec = mavlink.Codec(1, 1)
    old, new = ("127.0.0.1", 5000), ("127.0.0.1", 6000)
    list(link.datagram(codec.heartbeat(mavlink.MAV_TYPE_FIXED_WING), 100.0, old))
    list(link.datagram(codec.heartbeat(mavlink.MAV_TYPE_FIXED_WING), 101.0, new))
    assert link.vehicles[1].address == old
    assert link.health.counts(link_name(new)).foreign == 1
    list(link.datagram(codec.heartbeat(mavlink.MAV_TYPE_FIXED_WING), 101.0 + PIN_MOVE_S, old))
    t_moved = 101.0 + 2 * PIN_MOVE_S + 0.5
    list(link.datagram(codec.heartbeat(mavlink.MAV_TYPE_FIXED_WING), t_moved, new))
    assert link.vehicles[1].address == new
    assert "now speaks from 127.0.0.1:6000" in log.getvalue()


def test_only_allowed_system_ids_are_estimated_and_sent_to() -> None:
    config = load_config("noc_uav", ["link.allowed_system_ids=[1, 3]"])
    log = io.StringIO()
    link = MavlinkLink(config.link, log=log)
    codecs = {sysid: mavlink.Codec(sysid, 1) for sysid in (1, 2, 3)}
    for sysid in (1, 2, 3, 2):
        beat = codecs[sysid].heartbeat(mavlink.MAV_TYPE_FIXED_WING)
        list(link.datagram(beat, 1.0, ("::1", sysid)))
    assert sorted(link.vehicles) == [1, 3]
    assert link.refused_vehicles == {2: 2}
    sent_to = {address for _, address in link.ground_messages(mavlink.Codec(255, 190), 2.0)}
    assert sent_to == {("::1", 1), ("::1", 3)}
    assert "system id 2 not estimated: not in link.allowed_system_ids" in log.getvalue()
    assert link.stats()["refused_vehicles"] == {"2": 2}


def test_a_lone_spoofed_heartbeat_does_not_hold_the_pin_against_the_telemetry(
    tmp_path: Path,
) -> None:
    """Without signing: a heartbeat under the vehicle's id from elsewhere, a second before
    the vehicle is heard, pins that address; the vehicle's timed telemetry moves the pin
    to where it comes from (said, and counted as `moved`), none of its telemetry is
    dropped, and the station sends to it. A sender of telemetry under its id while the
    vehicle streams does not move the pin."""
    config, recs = recorded_flight(tmp_path)
    log = io.StringIO()
    link = MavlinkLink(config.link, log=log)
    vehicle, spoofer = ("127.0.0.1", 5000), ("127.0.0.1", 6000)
    t0 = recs[0][0] / 1e6
    list(link.datagram(mavlink.Codec(1, 1).heartbeat(mavlink.MAV_TYPE_FIXED_WING), t0 - 1, spoofer))
    assert link.vehicles[1].address == spoofer
    frames = 0
    for t_us, packet in recs[:2000]:
        frames += len(link.datagram(packet, t_us / 1e6, vehicle))
    v = link.vehicles[1]
    assert v.address == vehicle
    assert link.health.counts(link_name(vehicle)).moved == 1
    assert "now speaks from 127.0.0.1:5000" in log.getvalue()
    # Only what came before its first timed sample was dropped.
    decoder, stats = mavlink.Decoder(), DecodeStats()
    events = [decode_packet(decoder, p, t / 1e6, config.link, stats) for t, p in recs]
    timed = [e is not None and getattr(e.event, "t_vehicle_s", None) is not None for e in events]
    assert link.health.counts(link_name(vehicle)).foreign == timed.index(True)
    assert frames > 300
    assert {a for _, a in link.ground_messages(mavlink.Codec(255, 190), t0 + 1)} == {vehicle}
    # The spoofer now sends telemetry too: the vehicle streams on, so it is foreign.
    for t_us, packet in recs[2000:2100]:
        list(link.datagram(packet, t_us / 1e6, spoofer))
    assert v.address == vehicle
    assert link.health.counts(link_name(spoofer)).foreign == 100
