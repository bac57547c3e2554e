"""The MAVLink link: packets in, frames out, with the link's health and its vehicles.

packets -> decode (SI samples and link events, both clocks) -> link health (sequence
numbers) -> per-vehicle synchroniser -> frames. Pure of sockets and files but for the
optional tlog recorder: the UDP and tlog sources feed it, so a replay of a recording makes
the same frames as the live run did. It also says what the ground station should send
(`ground_messages`): heartbeats, and rate requests until they are acknowledged.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, TextIO

from gcs_estimator.config import STREAMED_MESSAGES, LinkConfig
from gcs_estimator.frames import Frame
from gcs_estimator.telemetry import mavlink
from gcs_estimator.telemetry.decode import (
    CommandAck,
    DecodeStats,
    Heartbeat,
    Sample,
    Unknown,
    decode_packet,
)
from gcs_estimator.telemetry.mavlink import Codec, TlogWriter
from gcs_estimator.telemetry.sync import LinkHealth, Synchronizer

Address = tuple[str, int]

RATE_REQUEST_EVERY_S = 5.0
"""Until a vehicle acknowledges the rates asked for, ask again this often [s]."""


@dataclass
class VehicleLink:
    """One aircraft on the link: its synchroniser and where it speaks from."""

    system_id: int
    sync: Synchronizer
    address: Address | None = None
    acked: set[int] = field(default_factory=set)
    """Results of its acknowledgements of our rate requests."""
    last_rate_request: float = -math.inf


class MavlinkLink:
    """Decoder, link health and vehicles of one session."""

    def __init__(
        self, config: LinkConfig, recorder: TlogWriter | None = None, log: TextIO | None = None
    ) -> None:
        self.config = config
        self.recorder = recorder
        self.log = sys.stderr if log is None else log
        self.decoder = mavlink.Decoder()
        self.health = LinkHealth()
        self.decode_stats = DecodeStats()
        self.vehicles: dict[int, VehicleLink] = {}
        self.unknown_messages = 0
        self.t_first_recv = math.nan
        self.t_last_recv = math.nan
        self._reported: set[str] = set()

    def report_once(self, key: str, text: str) -> None:
        """Say a problem once (it is counted every time)."""
        if key not in self._reported:
            self._reported.add(key)
            print(f"note: {text}", file=self.log)

    def vehicle(self, system_id: int) -> VehicleLink:
        v = self.vehicles.get(system_id)
        if v is None:
            if self.vehicles:
                self.report_once(
                    f"vehicle-{system_id}",
                    f"another vehicle on the link: system id {system_id} (estimated separately)",
                )
            v = self.vehicles[system_id] = VehicleLink(
                system_id, Synchronizer(system_id, self.config)
            )
        return v

    def datagram(
        self, data: bytes, t_recv_s: float, address: Address | None = None
    ) -> Iterator[Frame]:
        """Frames completed by one received datagram (one or more packets)."""
        packets, junk = mavlink.split_packets(data)
        if junk:
            self.health.junk_bytes += junk
            self.health.corrupt += 1
            self.report_once("junk", "bytes that are no MAVLink packet: skipped")
        for pkt in packets:
            yield from self.packet(pkt, t_recv_s, address)

    def packet(
        self, packet: bytes, t_recv_s: float, address: Address | None = None
    ) -> Iterator[Frame]:
        """Record, decode and synchronise one packet received at t_recv_s [s since epoch];
        yields the frames it completes (and partial ones that waited long enough)."""
        if self.recorder is not None:
            self.recorder.write(int(round(t_recv_s * 1e6)), packet)
        if math.isnan(self.t_first_recv):
            self.t_first_recv = t_recv_s
        self.t_last_recv = t_recv_s
        yield from self.poll(t_recv_s)
        decoded = decode_packet(self.decoder, packet, t_recv_s, self.config, self.decode_stats)
        if decoded is None:
            self.health.corrupt += 1
            self.report_once("corrupt", "corrupt packet(s) (CRC or framing): counted, skipped")
            return
        sysid = decoded.system_id
        if not self.health.on_packet(sysid, decoded.component_id, decoded.seq):
            self.report_once("dup", "duplicated packet(s): counted, dropped")
            return
        yield from self._event(sysid, decoded.event, address)

    def _event(self, sysid: int, event: object, address: Address | None) -> Iterator[Frame]:
        if isinstance(event, Unknown):
            self.unknown_messages += 1
            self.report_once("unknown", f"message unknown to the dialect ({event.name}): skipped")
        elif isinstance(event, Heartbeat):
            if not event.ground_station:
                self._seen(sysid, address)
        elif isinstance(event, CommandAck):
            if event.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL and sysid in self.vehicles:
                self.vehicles[sysid].acked.add(event.result)
        elif isinstance(event, Sample) and sysid != mavlink.GCS_SYSTEM_ID:
            yield from self._sample(self._seen(sysid, address), event)
        if self.decode_stats.invalid_values:
            self.report_once("invalid", "NaN or absurd field value(s): counted, dropped")

    def _seen(self, sysid: int, address: Address | None) -> VehicleLink:
        v = self.vehicle(sysid)
        if address is not None:
            v.address = address
        return v

    def _sample(self, v: VehicleLink, sample: Sample) -> Iterator[Frame]:
        yield from v.sync.add(sample)
        if v.sync.stats.late_samples:
            self.report_once("late", "sample(s) older than the last frame: counted, dropped")

    def poll(self, t_recv_s: float) -> Iterator[Frame]:
        """Partial frames that have waited long enough (receive time)."""
        for v in self.vehicles.values():
            yield from v.sync.poll(t_recv_s)

    def flush(self) -> Iterator[Frame]:
        """End of stream: whatever is open."""
        for v in self.vehicles.values():
            yield from v.sync.flush()

    def close(self) -> None:
        if self.recorder is not None:
            self.recorder.close()

    def ground_messages(self, codec: Codec, now: float) -> Iterator[tuple[bytes, Address]]:
        """What the ground station sends each second: a heartbeat to every vehicle, and
        the configured rates until a vehicle acknowledges them."""
        for v in self.vehicles.values():
            if v.address is None:
                continue
            yield codec.heartbeat(mavlink.MAV_TYPE_GCS), v.address
            if (
                mavlink.MAV_RESULT_ACCEPTED in v.acked
                or now - v.last_rate_request <= RATE_REQUEST_EVERY_S
            ):
                continue
            v.last_rate_request = now
            for name in STREAMED_MESSAGES:
                yield (
                    codec.set_message_interval(v.system_id, name, self.config.rate(name)),
                    v.address,
                )

    def session_time(self) -> float:
        """Seconds from the first packet to the newest [s] (NaN before any)."""
        return self.t_last_recv - self.t_first_recv

    def stats(self) -> dict[str, Any]:
        out: dict[str, Any] = dict(self.health.as_dict())
        out["unknown_messages"] = self.unknown_messages
        out["invalid_values"] = self.decode_stats.invalid_values
        out["ignored_messages"] = self.decode_stats.ignored_messages
        out["vehicles"] = {
            str(v.system_id): {
                "frames": v.sync.stats.frames,
                "partial_frames": v.sync.stats.partial_frames,
                "late_samples": v.sync.stats.late_samples,
                "clock_resets": v.sync.stats.clock_resets,
                "frames_before_inputs": v.sync.stats.waiting_for_inputs,
            }
            for v in self.vehicles.values()
        }
        return out
