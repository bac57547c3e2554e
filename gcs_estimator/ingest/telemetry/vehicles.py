"""The vehicles on a MAVLink link: one entry per system id heard (up to the cap), where
each speaks from (pinned at first contact, following its telemetry), which component each
message is taken from, their acknowledgements of our rate requests, and what the ground
station sends them."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import TextIO

from gcs_estimator.config import STREAMED_MESSAGES, LinkConfig
from gcs_estimator.frames import Frame
from gcs_estimator.ingest.telemetry import mavlink
from gcs_estimator.ingest.telemetry.counters import LinkHealth
from gcs_estimator.ingest.telemetry.decode import CommandAck, Heartbeat, Sample
from gcs_estimator.ingest.telemetry.mavlink import Codec
from gcs_estimator.ingest.telemetry.sync import Synchronizer, SyncStats

Address = tuple[str, int]

FIXED_WING_TYPES = frozenset(
    {mavlink.MAV_TYPE_FIXED_WING, mavlink.MAV_TYPE_GENERIC, *mavlink.MAV_TYPE_VTOL}
)
"""HEARTBEAT types the model fits (VTOLs fly as fixed wings in forward flight)."""

RATE_REQUEST_EVERY_S = 5.0
"""Until a vehicle acknowledges the rates asked for, ask again this often [s]."""
PIN_MOVE_S = 5.0
"""A vehicle's pinned address may move once it has been silent this long [s]."""


@dataclass
class VehicleLink:
    """One aircraft on the link: its synchroniser and where it speaks from."""

    system_id: int
    sync: Synchronizer
    address: Address | None = None
    """Where it speaks from: pinned at first contact, following its telemetry (see
    Vehicles.pinned)."""
    last_heard: float = -math.inf
    """Receive time of its newest packet from that address [s since epoch]."""
    last_telemetry: float = -math.inf
    """Receive time of its newest timed sample from that address [s since epoch]."""
    acked: set[int] = field(default_factory=set)
    """Results of its acknowledgements of our rate requests."""
    last_rate_request: float = -math.inf
    autopilot: int | None = None
    """The component whose HEARTBEAT says it is an autopilot (None: none heard yet)."""
    sources: dict[object, int] = field(default_factory=dict)
    """Which component each message is taken from (Vehicles.sample)."""


def link_name(address: Address | None) -> str:
    """The name a link's counters go under: the peer's address, or "recording"."""
    return "recording" if address is None else f"{address[0]}:{address[1]}"


# Over 200 lines: a link's vehicles (the cap, each one's address, its acknowledgements,
# heartbeats and sources per message) and a run's samples (samples) beside the rule per
# sample they take the common case of.
class Vehicles:
    """The vehicles of one link, by system id."""

    def __init__(
        self,
        config: LinkConfig,
        health: LinkHealth,
        report_once: Callable[[str, str], None],
        log: TextIO,
        linear_inputs: bool = True,
    ) -> None:
        self.config = config
        self.health = health
        self.report_once = report_once
        self.log = log
        self.linear_inputs = linear_inputs
        self.vehicles: dict[int, VehicleLink] = {}
        self.refused_vehicles: dict[int, int] = {}
        """Packets per system id beyond the vehicle cap (counted, not estimated)."""

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

    def pinned(
        self, sysid: int, address: Address, t_recv_s: float, name: str, event: object = None
    ) -> bool:
        """Whether a packet comes from where its system id speaks from. A vehicle's
        address is pinned at first contact, and follows its telemetry: a timed sample
        (the vehicle's data stream) from another address moves the pin there when the
        pinned address has sent no timed sample for PIN_MOVE_S (a lone heartbeat, or a
        sender that went quiet, holds no pin against the data stream), and so does any
        packet once the pinned address has been silent for PIN_MOVE_S (a vehicle that
        moved, say after a router's restart). A move is said and counted (`moved`).
        Other packets under its id from elsewhere are counted (`foreign`) and dropped,
        and nothing is sent there."""
        v = self.vehicles.get(sysid)
        if v is None or v.address is None:
            return True  # first contact: _seen pins it
        timed = isinstance(event, Sample) and event.t_vehicle_s is not None
        if v.address == address:
            v.last_heard = t_recv_s
            if timed:
                v.last_telemetry = t_recv_s
            return True
        if timed and t_recv_s - v.last_telemetry > PIN_MOVE_S:
            why = "the vehicle's telemetry comes from there"
        elif t_recv_s - v.last_heard > PIN_MOVE_S:
            why = f"its address was silent {t_recv_s - v.last_heard:.1f} s"
        else:
            self.health.counts(name).foreign += 1
            self.report_once(
                f"foreign-{sysid}-{name}",
                f"packets as system id {sysid} from {name}, not from its address "
                f"{link_name(v.address)}: dropped (a second sender with its id?)",
            )
            return False
        print(
            f"note: system id {sysid} now speaks from {name}, not {link_name(v.address)}: {why}",
            file=self.log,
        )
        self.health.counts(name).moved += 1
        v.address, v.last_heard = address, t_recv_s
        if timed:
            v.last_telemetry = t_recv_s
        return True

    def ack(self, sysid: int, compid: int, ack: CommandAck) -> None:
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

    def heartbeat(
        self, sysid: int, compid: int, event: Heartbeat, address: Address | None, t_recv_s: float
    ) -> None:
        """A vehicle's HEARTBEAT: which component is its autopilot, and whether it is a
        kind of aircraft the model fits."""
        v = self.seen(sysid, address, t_recv_s)
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

    def seen(self, sysid: int, address: Address | None, t_recv_s: float) -> VehicleLink | None:
        """The vehicle of a system id (see vehicle), its address pinned at first contact
        (see pinned)."""
        v = self.vehicle(sysid)
        if v is not None and address is not None and v.address is None:
            v.address, v.last_heard = address, t_recv_s
        return v

    def sample(self, v: VehicleLink, sample: Sample, compid: int) -> list[Frame]:
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
        if sample.t_vehicle_s is not None:
            v.last_telemetry = sample.t_recv_s  # from its pinned address (Vehicles.pinned)
        out = v.sync.add(sample)
        self._sync_notes(v.sync.stats)
        return out

    def samples(
        self, v: VehicleLink, samples: list[Sample | None], compids: list[int]
    ) -> list[Frame]:
        """sample() of each sample (None: none) in turn: one of a message taken from the
        component that sent it goes straight to the synchroniser."""
        out: list[Frame] = []
        sources, sync = v.sources, v.sync
        stats = sync.stats
        for sample, compid in zip(samples, compids, strict=False):
            if sample is None:
                continue
            if sources.get(sample.message) != compid or sample.message == "NAMED_VALUE_FLOAT":
                out += self.sample(v, sample, compid)  # its source to be set, or checked
                continue
            if sample.t_vehicle_s is not None:
                v.last_telemetry = sample.t_recv_s
            out += sync.add(sample)
            if stats.late_samples or stats.implausible_times:
                self._sync_notes(stats)
        return out

    def _sync_notes(self, stats: SyncStats) -> None:
        if stats.late_samples:
            self.report_once("late", "sample(s) for a frame already processed: counted, dropped")
        if stats.implausible_times:
            self.report_once(
                "time", "sample(s) with a vehicle time no later sample confirmed: dropped"
            )

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
