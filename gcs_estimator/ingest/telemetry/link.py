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
from pathlib import Path
from typing import Any, TextIO

from gcs_estimator.config import STREAMED_MESSAGES, ConfigError, LinkConfig
from gcs_estimator.frames import Frame
from gcs_estimator.ingest.telemetry import mavlink
from gcs_estimator.ingest.telemetry.counters import LinkHealth
from gcs_estimator.ingest.telemetry.decode import (
    PLAUSIBLE,
    CommandAck,
    Decoded,
    DecodeStats,
    Heartbeat,
    Ranges,
    Sample,
    SampleReader,
    Unknown,
    decoded_message,
)
from gcs_estimator.ingest.telemetry.mavlink import Codec, TlogWriter
from gcs_estimator.ingest.telemetry.signing import SignatureCheck, Verdict, load_key, sign_outgoing
from gcs_estimator.ingest.telemetry.sync import Synchronizer

Address = tuple[str, int]

FIXED_WING_TYPES = frozenset(
    {mavlink.MAV_TYPE_FIXED_WING, mavlink.MAV_TYPE_GENERIC, *mavlink.MAV_TYPE_VTOL}
)
"""HEARTBEAT types the model fits (VTOLs fly as fixed wings in forward flight)."""

RATE_REQUEST_EVERY_S = 5.0
PIN_MOVE_S = 5.0
"""A vehicle's pinned address may move once it has been silent this long [s]."""
"""Until a vehicle acknowledges the rates asked for, ask again this often [s]."""


@dataclass
class VehicleLink:
    """One aircraft on the link: its synchroniser and where it speaks from."""

    system_id: int
    sync: Synchronizer
    address: Address | None = None
    """Where it speaks from: pinned at first contact (see MavlinkLink.pinned)."""
    last_heard: float = -math.inf
    """Receive time of its newest packet from that address [s since epoch]."""
    acked: set[int] = field(default_factory=set)
    """Results of its acknowledgements of our rate requests."""
    last_rate_request: float = -math.inf
    autopilot: int | None = None
    """The component whose HEARTBEAT says it is an autopilot (None: none heard yet)."""
    sources: dict[object, int] = field(default_factory=dict)
    """Which component each message is taken from (MavlinkLink._sample)."""


def link_name(address: Address | None) -> str:
    """The name a link's counters go under: the peer's address, or "recording"."""
    return "recording" if address is None else f"{address[0]}:{address[1]}"


COUNTER_TIME_WRAP_S = 86_400.0
"""Vehicle times that wrap sooner than this (32-bit microseconds) do not go to the
sequence counters; time_boot_ms (49.7 days) does."""


class MavlinkLink:
    """Decoder, link health and vehicles of one session."""

    def __init__(
        self,
        config: LinkConfig,
        recorder: TlogWriter | None = None,
        log: TextIO | None = None,
        linear_inputs: bool = True,
        ranges: Ranges = PLAUSIBLE,
        rejected_path: Path | None = None,
    ) -> None:
        self.config = config
        self.recorder = recorder
        self.rejected_path = rejected_path
        """With signing on: where packets that fail the signature check are recorded
        (opened at the first one), apart from the recording the estimate is made of."""
        self._rejected: TlogWriter | None = None
        self.log = sys.stderr if log is None else log
        self.linear_inputs = linear_inputs
        self.ranges = ranges
        self.decoder = mavlink.Decoder()
        self.health = LinkHealth()
        self.decode_stats = DecodeStats()
        self.samples = SampleReader(config, self.decode_stats, ranges)
        self.vehicles: dict[int, VehicleLink] = {}
        self.refused_vehicles: dict[int, int] = {}
        """Packets per system id beyond the vehicle cap (counted, not estimated)."""
        self.t_first_recv = math.nan
        self.t_last_recv = math.nan
        self._reported: set[str] = set()
        self._pending: dict[Address, bytes] = {}
        """Per stream: the start of a packet still arriving."""
        self._key: bytes | None = None
        self.signatures: SignatureCheck | None = None
        """With link.signing_key_file: the check every packet must pass."""
        if config.signing_key_file:
            try:
                self._key = load_key(config.signing_key_file)
            except (OSError, ValueError) as exc:
                raise ConfigError(f"link.signing_key_file: {exc}") from exc
            self.signatures = SignatureCheck(self._key)

    def sign(self, codec: Codec, t_unix_s: float) -> None:
        """Make the station's codec sign what it sends (with signing on)."""
        if self._key is not None:
            sign_outgoing(codec.mav, self._key, t_unix_s)

    def report_once(self, key: str, text: str) -> None:
        """Say a problem once (it is counted every time)."""
        if key not in self._reported:
            self._reported.add(key)
            print(f"note: {text}", file=self.log)

    def vehicle(self, system_id: int) -> VehicleLink | None:
        """The vehicle of a system id, new at first contact; None beyond the cap."""
        v = self.vehicles.get(system_id)
        if v is not None:
            return v
        allowed = self.config.allowed_system_ids
        if allowed and system_id not in allowed:
            self.refused_vehicles[system_id] = self.refused_vehicles.get(system_id, 0) + 1
            self.report_once(
                f"allowed-{system_id}",
                f"system id {system_id} not estimated: not in link.allowed_system_ids "
                f"{list(allowed)}; its packets are counted",
            )
            return None
        if len(self.vehicles) >= self.config.max_vehicles:
            self.refused_vehicles[system_id] = self.refused_vehicles.get(system_id, 0) + 1
            self.report_once(
                f"cap-{system_id}",
                f"system id {system_id} not estimated: already {len(self.vehicles)} vehicles "
                "(link.max_vehicles); its packets are counted",
            )
            return None
        if self.vehicles:
            self.report_once(
                f"vehicle-{system_id}",
                f"another vehicle on the link: system id {system_id} (estimated separately)",
            )
        sync = Synchronizer(system_id, self.config, self.linear_inputs)
        v = self.vehicles[system_id] = VehicleLink(system_id, sync)
        return v

    def datagram(self, data: bytes, t_recv_s: float, address: Address | None = None) -> list[Frame]:
        """Frames completed by one received datagram (one or more packets, found by
        mavlink.scan; each run of junk between them counts as one corrupt packet).
        A datagram that is exactly one channel message passing its CRC (what a vehicle
        sends, nearly always) is read once, as packet() reads it, without the scan."""
        decoded = self._fast(data, t_recv_s)
        if decoded is not None:
            return self._decoded(data, None, t_recv_s, address, decoded)
        return self._items(list(mavlink.scan(data, self.decoder)), t_recv_s, address)

    def stream(self, data: bytes, t_recv_s: float, address: Address) -> list[Frame]:
        """Frames completed by bytes read from a stream (TCP, serial): packets may be
        split across reads, so a packet still arriving at the end waits for the rest."""
        buf = self._pending.pop(address, b"") + data
        items = list(mavlink.scan(buf, self.decoder))
        if items and isinstance(items[-1], int):
            tail = len(buf) - items[-1]
            keep = mavlink.incomplete_tail(buf, tail)
            if keep is not None:
                self._pending[address] = buf[keep:]
                items[-1] = keep - tail  # the junk before it, if any
                if not items[-1]:
                    items.pop()
        return self._items(items, t_recv_s, address)

    def _items(
        self, items: list[tuple[bytes, Any] | int], t_recv_s: float, address: Address | None
    ) -> list[Frame]:
        name = link_name(address)
        out: list[Frame] = []
        for item in items:
            if isinstance(item, int):
                self._junk(name, item)
            else:
                out += self._decoded(
                    item[0], item[1], t_recv_s, address, self._fast(item[0], t_recv_s)
                )
        return out

    def _junk(self, name: str, n_bytes: int) -> None:
        counts = self.health.counts(name)
        counts.junk_bytes += n_bytes
        counts.corrupt += 1
        self.report_once("corrupt", "corrupt packet(s) or junk bytes (CRC or framing): skipped")

    def packet(self, packet: bytes, t_recv_s: float, address: Address | None = None) -> list[Frame]:
        """Record, decode and synchronise one packet received at t_recv_s [s since epoch]
        (a tlog record); returns the frames it lets go (lists, not generators: this runs
        once per packet)."""
        decoded = self._fast(packet, t_recv_s)
        if decoded is not None:
            return self._decoded(packet, None, t_recv_s, address, decoded)
        msg = self.decoder.decode(packet)
        if msg is None:
            if self.recorder is not None:
                self.recorder.write(int(round(t_recv_s * 1e6)), packet)
            self._junk(link_name(address), len(packet))
            return []
        return self._decoded(packet, msg, t_recv_s, address)

    def _fast(self, packet: bytes, t_recv_s: float) -> Decoded | None:
        """The packet's meaning by decode.SampleReader where it can tell (a channel
        message that passes its CRC), else None. Not with signing on: there a packet's
        meaning counts only once its signature has passed."""
        if self.signatures is not None:
            return None
        decoded = self.samples(packet, t_recv_s)
        return decoded if isinstance(decoded, Decoded) else None

    def _decoded(
        self,
        packet: bytes,
        msg: Any,
        t_recv_s: float,
        address: Address | None,
        decoded: Decoded | None = None,
    ) -> list[Frame]:
        """A packet that passed its CRC: its message (msg), or what it means already
        (decoded)."""
        name = link_name(address)
        if self.signatures is not None and not self._signed(packet, t_recv_s, name):
            return []
        if self.recorder is not None:
            self.recorder.write(int(round(t_recv_s * 1e6)), packet)
        if math.isnan(self.t_first_recv):
            self.t_first_recv = t_recv_s
        self.t_last_recv = t_recv_s
        if decoded is None:
            decoded = decoded_message(
                msg, packet, t_recv_s, self.config, self.decode_stats, self.ranges
            )
        event = decoded.event
        t_vehicle = None
        if isinstance(event, Sample) and (event.wrap_s or math.inf) > COUNTER_TIME_WRAP_S:
            t_vehicle = event.t_vehicle_s
        sysid = decoded.system_id
        if address is not None and not self.pinned(sysid, address, t_recv_s, name):
            return []
        if not self.health.on_packet(
            name, sysid, decoded.component_id, decoded.seq, packet, t_vehicle
        ):
            self.report_once(
                "dup", "copies of packets, or packets long behind the vehicle's time: dropped"
            )
            return []
        return self._event(sysid, decoded.component_id, event, address, name)

    def _event(
        self, sysid: int, compid: int, event: object, address: Address | None, name: str
    ) -> list[Frame]:
        out: list[Frame] = []
        if isinstance(event, Sample):
            if sysid != mavlink.GCS_SYSTEM_ID:
                v = self._seen(sysid, address)
                if v is not None:
                    out = self._sample(v, event, compid)
        elif isinstance(event, Unknown):
            self.health.counts(name).unknown += 1
            self.report_once("unknown", f"message unknown to the dialect ({event.name}): skipped")
        elif isinstance(event, Heartbeat):
            if not event.ground_station:
                self._heartbeat(sysid, compid, event, address)
        elif isinstance(event, CommandAck):
            self._ack(sysid, compid, event)
        if self.decode_stats.invalid_values:
            self.report_once("invalid", "NaN or absurd field value(s): counted, dropped")
        return out

    def _signed(self, packet: bytes, t_recv_s: float, name: str) -> bool:
        """Whether a packet passes the signature check; else it is counted by why,
        dropped, and recorded apart (rejected_path), not in the recording the estimate is
        made of. The check's state moves only with good packets, so a replay of the
        recording with the key accepts what the live run accepted. The rejected file is
        for forensics: replayed alone, a replayed copy there looks fresh."""
        assert self.signatures is not None
        verdict = self.signatures.check(packet, t_recv_s)
        if verdict == Verdict.SIGNED:
            return True
        counts = self.health.counts(name)
        setattr(counts, verdict.value, getattr(counts, verdict.value) + 1)
        where = ""
        if self.rejected_path is not None:
            if self._rejected is None:
                self._rejected = TlogWriter(self.rejected_path)
            self._rejected.write(int(round(t_recv_s * 1e6)), packet)
            where = f", recorded to {self.rejected_path}"
        self.report_once(
            f"sign-{verdict.value}",
            f"{verdict.value.replace('_', ' ')} packet(s) with signing on: dropped{where}",
        )
        return False

    def pinned(self, sysid: int, address: Address, t_recv_s: float, name: str) -> bool:
        """Whether a packet comes from where its system id speaks from. A vehicle's
        address is pinned at first contact: packets under its id from anywhere else are
        counted (`foreign`) and dropped, and nothing is sent there, unless its own
        address has been silent for PIN_MOVE_S (a vehicle that moved, say after a
        router's restart): then the pin moves, and says so."""
        v = self.vehicles.get(sysid)
        if v is None or v.address is None:
            return True  # first contact: _seen pins it
        if v.address == address:
            v.last_heard = t_recv_s
            return True
        if t_recv_s - v.last_heard > PIN_MOVE_S:
            print(
                f"note: system id {sysid} now speaks from {name}; its address "
                f"{link_name(v.address)} was silent {t_recv_s - v.last_heard:.1f} s",
                file=self.log,
            )
            v.address, v.last_heard = address, t_recv_s
            return True
        self.health.counts(name).foreign += 1
        self.report_once(
            f"foreign-{sysid}-{name}",
            f"packets as system id {sysid} from {name}, not from its address "
            f"{link_name(v.address)}: dropped (a second sender with its id?)",
        )
        return False

    def _ack(self, sysid: int, compid: int, ack: CommandAck) -> None:
        """An acknowledgement counts only for a command we sent to that vehicle, only
        from the component the command went to (mavlink.RATE_REQUEST_COMPONENT), and
        only if addressed to us (or to everyone, as some autopilots do): a camera or
        gimbal on the vehicle's system id that answers too does not stop the requests."""
        v = self.vehicles.get(sysid)
        if (
            v is not None
            and compid == mavlink.RATE_REQUEST_COMPONENT
            and ack.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
            and ack.target_system in (mavlink.GCS_SYSTEM_ID, 0)
            and v.last_rate_request > -math.inf
        ):
            v.acked.add(ack.result)

    def _heartbeat(
        self, sysid: int, compid: int, event: Heartbeat, address: Address | None
    ) -> None:
        v = self._seen(sysid, address)
        if v is None or not event.autopilot:
            return  # a gimbal, camera or companion computer says nothing of the aircraft
        if v.autopilot is None:
            v.autopilot = compid
        if event.mav_type not in FIXED_WING_TYPES:
            kind = mavlink.MAV_TYPE_NAMES.get(event.mav_type, str(event.mav_type))
            self.report_once(
                f"type-{sysid}",
                f"system id {sysid} says it is {kind} (HEARTBEAT type); the estimator's model "
                "is a fixed-wing aircraft's longitudinal motion: check the numbers it gives",
            )

    def _seen(self, sysid: int, address: Address | None) -> VehicleLink | None:
        v = self.vehicle(sysid)
        if v is not None and address is not None and v.address is None:
            v.address, v.last_heard = address, self.t_last_recv  # pinned (see pinned)
        return v

    def _sample(self, v: VehicleLink, sample: Sample, compid: int) -> list[Frame]:
        """A sample into the vehicle's synchroniser. Each message is taken from one
        component of the system: the first heard sending it, or its autopilot (by
        HEARTBEAT) once that sends it too; the same message from another component (a
        gimbal's ATTITUDE, a companion computer's) would be read as the aircraft's, so it
        is counted and dropped."""
        key: object = sample.message
        if key == "NAMED_VALUE_FLOAT":  # one message, several channels by name
            key = sample.values[0][0] if sample.values else key
        source = v.sources.setdefault(key, compid)
        if source != compid:
            if compid == v.autopilot:
                v.sources[key] = compid
                self.report_once(
                    f"source-{v.system_id}-{key}",
                    f"system id {v.system_id}: {sample.message} taken from component {compid} "
                    f"(its autopilot, by HEARTBEAT) from now on, not component {source}",
                )
            else:
                v.sync.stats.other_component += 1
                self.report_once(
                    f"other-{v.system_id}-{key}",
                    f"system id {v.system_id}: component {compid} sends {sample.message} too "
                    f"(a gimbal, a camera, a companion computer?); the aircraft's is taken "
                    f"from component {source}: the other's counted (other_component) and "
                    "dropped",
                )
                return []
        out = v.sync.add(sample)
        if v.sync.stats.late_samples:
            self.report_once("late", "sample(s) for a frame already processed: counted, dropped")
        if v.sync.stats.implausible_times:
            self.report_once(
                "time", "sample(s) with a vehicle time no later sample confirmed: dropped"
            )
        return out

    def flush(self) -> Iterator[Frame]:
        """End of stream: whatever is open."""
        for v in self.vehicles.values():
            yield from v.sync.finish()

    def flush_recording(self) -> None:
        """Write what was recorded through to the file (the link may go quiet)."""
        for recorder in (self.recorder, self._rejected):
            if recorder is not None:
                recorder.flush()

    def close(self) -> None:
        for recorder in (self.recorder, self._rejected):
            if recorder is not None:
                recorder.close()

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
        out["invalid_values"] = self.decode_stats.invalid_values
        out["ignored_messages"] = self.decode_stats.ignored_messages
        if self.refused_vehicles:
            out["refused_vehicles"] = {str(k): n for k, n in self.refused_vehicles.items()}
        out["vehicles"] = {str(v.system_id): v.sync.stats.as_dict() for v in self.vehicles.values()}
        return out
