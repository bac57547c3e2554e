"""Loss counted from sequence numbers, on streams of real pymavlink packets through the
link as a replay feeds it: a stream like a real ArduPlane's (many message types, few of
them timed, at 2.5 Hz) with nothing lost counts nothing lost; injected losses of any
length, copies and reorders are counted exactly; packets of unknown message ids (junk
whose CRC cannot be checked) move no counter but their own.

The reference is what was dropped, copied or moved; the link sees only the packets."""

from __future__ import annotations

import io
import random
from typing import Any

import pytest

from gcs_estimator.config import load_config
from gcs_estimator.ingest.telemetry import mavlink
from gcs_estimator.ingest.telemetry.link import MavlinkLink

TICK_S = 0.01
"""The vehicle's loop [s]: each message goes every so many ticks."""
EVERY = {
    "mission_current": 5,
    "meminfo": 5,
    "power_status": 5,
    "sys_status": 5,
    "nav": 5,
    "rc": 5,
    "raw_imu": 10,
    "scaled_pressure": 10,
    "gps": 20,
    "attitude": 40,
    "vfr_hud": 40,
    "servo": 40,
    "heartbeat": 100,
}
"""Ticks between packets of each type: about 160 packets a second, of which only
ATTITUDE, SCALED_PRESSURE and SERVO_OUTPUT_RAW carry a time the estimator reads, ATTITUDE
at 2.5 Hz (as ALFA's ArduPlane 3.9 tlog streams)."""


def _message(mav: Any, kind: str, k: int) -> Any:  # noqa: C901 - one line per type
    """The message of a type at tick k (its fields vary with k)."""
    t_ms = 600_000 + 10 * k
    if kind == "mission_current":
        return mav.mission_current_encode(k % 7)
    if kind == "meminfo":
        return mav.meminfo_encode(k % 65536, 4000 + k % 100)
    if kind == "power_status":
        return mav.power_status_encode(5000 + k % 50, 5100, 0)
    if kind == "sys_status":
        return mav.sys_status_encode(0, 0, 0, 500, 12000 + k % 90, 100, 80, 0, 0, 0, 0, 0, 0)
    if kind == "nav":
        return mav.nav_controller_output_encode(0.1, 0.2, k % 360, 90, 100, 1.0, 0.5, 0.1)
    if kind == "rc":
        return mav.rc_channels_raw_encode(t_ms, 0, *([1500 + k % 7] * 8), 255)
    if kind == "raw_imu":
        return mav.raw_imu_encode(t_ms * 1000, 1, 2, -1000, k % 9, 0, 0, 0, 0, 0)
    if kind == "scaled_pressure":
        return mav.scaled_pressure_encode(t_ms, 1000.0 + (k % 10) / 10, 0.1, 2000)
    if kind == "gps":
        return mav.gps_raw_int_encode(t_ms * 1000, 3, k, 0, 100, 100, 100, 2000, 0, 9)
    if kind == "attitude":
        return mav.attitude_encode(t_ms, 0.0, 0.05 + (k % 40) * 1e-3, 0.0, 0.0, 0.01, 0.0)
    if kind == "vfr_hud":
        return mav.vfr_hud_encode(20.0 + (k % 10) / 10, 20.0, 0, 50, 100.0, 0.0)
    if kind == "servo":
        return mav.servo_output_raw_encode(t_ms * 1000, 0, *([1500 + k % 11] * 8))
    raise AssertionError(kind)


def arduplane_like(seconds: float) -> list[tuple[float, bytes]]:
    """(receive time, packet) of a vehicle streaming as above, in order, plus a ground
    station's heartbeats whose own sequence numbers skip (it sends elsewhere too)."""
    vehicle, gcs = mavlink.Codec(1, 1), mavlink.Codec(255, 190)
    out: list[tuple[float, bytes]] = []
    for k in range(round(seconds / TICK_S)):
        t = 1_700_000_000.0 + k * TICK_S
        for kind, every in EVERY.items():
            if k % every == 0:
                if kind == "heartbeat":
                    out.append((t, vehicle.heartbeat(mavlink.MAV_TYPE_FIXED_WING)))
                else:
                    out.append((t, vehicle.pack(_message(vehicle.mav, kind, k))))
        if k % 50 == 0:
            gcs.mav.seq = (gcs.mav.seq + k % 3) % 256  # what it sent to others
            out.append((t + 0.001, gcs.heartbeat(mavlink.MAV_TYPE_GCS)))
    return out


def _replay(records: list[tuple[float, bytes]]) -> dict[str, int]:
    link = MavlinkLink(load_config("noc_uav").link, log=io.StringIO())
    for t, packet in records:
        link.packet(packet, t)
    return link.health.total().as_dict()


def _vehicle_indices(records: list[tuple[float, bytes]]) -> list[int]:
    return [i for i, (_, p) in enumerate(records) if mavlink.header(p)[1] == 1]


def test_a_stream_like_arduplanes_with_nothing_lost_counts_nothing_lost() -> None:
    records = arduplane_like(60.0)
    counts = _replay(records)
    assert counts["received"] == len(records)
    assert (counts["lost"], counts["duplicates"], counts["out_of_order"], counts["stale"]) == (
        0,
        0,
        0,
        0,
    )


@pytest.mark.parametrize("burst", [1, 2, 127, 128, 200, 255, 256, 257, 511, 1000])
def test_a_burst_of_any_length_is_counted_exactly(burst: int) -> None:
    records = arduplane_like(40.0)
    start = _vehicle_indices(records)[3000]
    drop = set(_vehicle_indices(records)[3000 : 3000 + burst])
    kept = [r for i, r in enumerate(records) if i not in drop]
    counts = _replay(kept)
    assert (counts["lost"], counts["out_of_order"]) == (burst, 0), start
    assert counts["received"] == len(kept)


def test_single_losses_copies_and_reorders_are_counted_exactly() -> None:
    rng = random.Random(51)
    records = arduplane_like(40.0)
    vehicle = _vehicle_indices(records)
    lost = set(rng.sample(vehicle[100:], 40))
    # Neighbours swapped (a reorder by one), away from the losses.
    swaps = [i for i in rng.sample(vehicle[100:-2], 30) if not {i - 1, i, i + 1, i + 2} & lost]
    out = [r for i, r in enumerate(records) if i not in lost]
    where = {id(r): k for k, r in enumerate(out)}
    moved = 0
    for i in swaps:
        a, b = where.get(id(records[i])), where.get(id(records[i + 1]))
        if a is None or b is None or b != a + 1 or mavlink.header(records[i + 1][1])[1] != 1:
            continue
        out[a], out[b] = out[b], out[a]
        where[id(out[a])], where[id(out[b])] = a, b
        moved += 1
    copies = rng.sample(range(200, len(out)), 25)
    for k in sorted(copies, reverse=True):
        out.insert(k + 1, out[k])  # a copy right after the packet
    counts = _replay(out)
    assert counts["lost"] == len(lost)
    assert counts["out_of_order"] == moved
    assert counts["duplicates"] == len(copies)
    assert counts["received"] == len(records) - len(lost)


def _unknown_id(packet: bytes, rng: random.Random) -> bytes:
    """The packet with its message id changed to one the dialect does not know (its CRC
    then cannot be checked: junk that frames as a packet)."""
    out = bytearray(packet)
    assert out[0] == mavlink.STX_V2
    while True:
        msgid = rng.randrange(1 << 24)
        if msgid not in mavlink.MAX_PAYLOAD:
            break
    out[7:10] = msgid.to_bytes(3, "little")
    out[4] = rng.randrange(256)  # any sequence number
    return bytes(out)


def test_packets_of_unknown_ids_move_no_counter_but_their_own() -> None:
    rng = random.Random(7)
    records = arduplane_like(30.0)
    fuzzed: list[tuple[float, bytes]] = []
    injected = 0
    for t, p in records:
        fuzzed.append((t, p))
        if rng.random() < 0.05:
            fuzzed.append((t, _unknown_id(p, rng)))
            injected += 1
    clean, noisy = _replay(records), _replay(fuzzed)
    assert noisy["unknown"] == injected > 100
    noisy["unknown"] = 0
    assert noisy == clean


@pytest.mark.parametrize("block", [2, 8, 60])
def test_a_stream_shuffled_in_blocks_loses_nothing(block: int) -> None:
    """Every packet arrives, each block of the vehicle's packets in a random order: none
    is lost; those that arrive after a later one are out of order, each counted once."""
    rng = random.Random(block)
    records = arduplane_like(20.0)
    vehicle = [r for r in records if mavlink.header(r[1])[1] == 1]
    out: list[tuple[float, bytes]] = []
    for i in range(0, len(vehicle), block):
        chunk = vehicle[i : i + block]
        rng.shuffle(chunk)
        out += chunk
    order = {id(r): k for k, r in enumerate(vehicle)}
    newest, late = -1, 0
    for r in out:
        late += order[id(r)] < newest
        newest = max(newest, order[id(r)])
    counts = _replay(out)
    assert (counts["lost"], counts["out_of_order"]) == (0, late) and late > 0
    assert counts["received"] == len(vehicle)
