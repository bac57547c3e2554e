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
from pathlib import Path
from typing import Any, TextIO

from gcs_estimator.config import AircraftConfig, ConfigError, LinkConfig
from gcs_estimator.frames import Frame
from gcs_estimator.ingest.telemetry import mavlink
from gcs_estimator.ingest.telemetry.counters import LinkHealth
from gcs_estimator.ingest.telemetry.decode import (
    PLAUSIBLE,
    CommandAck,
    Decoded,
    DecodeStats,
    Heartbeat,
    ParamValue,
    Ranges,
    Sample,
    SampleReader,
    Unknown,
    decoded_message,
    ranges_of,
)
from gcs_estimator.ingest.telemetry.mavlink import Codec, TlogWriter
from gcs_estimator.ingest.telemetry.signing import SigningGate, load_key, sign_outgoing
from gcs_estimator.ingest.telemetry.vehicle_setup import VehicleSetup
from gcs_estimator.ingest.telemetry.vehicles import Address, VehicleLink, Vehicles, link_name

RECORDING = link_name(None)
"""The counters' name for a recording's packets."""
COUNTER_TIME_WRAP_S = 86_400.0
"""Vehicle times that wrap sooner than this (32-bit microseconds) do not go to the
sequence counters; time_boot_ms (49.7 days) does."""


def _counted(
    sysid: int, compids: list[int], samples: list[Sample], start: int
) -> Iterator[tuple[tuple[int, int], float | None, str]]:
    """What the counters take of each sample from `start` on, up to the first of another
    system id: its (system, component), its vehicle time where its clock wraps no sooner
    than COUNTER_TIME_WRAP_S (else None), its message (as sample_packet gives them)."""
    inf = math.inf
    for k in range(start, len(samples)):
        sample = samples[k]
        if sample.system_id != sysid:
            return
        counted = (sample.wrap_s or inf) > COUNTER_TIME_WRAP_S
        yield (sysid, compids[k]), sample.t_vehicle_s if counted else None, sample.message


# Over 200 lines: one packet's path from bytes to frames (framing, CRC, signing, pinning,
# counting, decoding, routing) reads best in one place; the parts with state of their own,
# the vehicles and the signing gate, are classes apart.
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
        elevator_travel_deg: float = 0.0,
    ) -> None:
        self.config = config
        self.elevator_travel_deg = elevator_travel_deg
        """The airframe's elevator travel at full output [deg] (0: not given): what a
        vehicle's own servo parameters need to give the elevator in radians."""
        self.setups: dict[int, VehicleSetup] = {}
        """Per system id: its autopilot, parameters, channel sources and requests."""
        self.recorder = recorder
        self.rejected_path = rejected_path
        """With signing on: where packets that fail the signature check are recorded
        (opened at the first one), apart from the recording the estimate is made of."""
        self.log = sys.stderr if log is None else log
        self.linear_inputs = linear_inputs
        self.ranges = ranges
        self.decoder = mavlink.Decoder()
        self.health = LinkHealth()
        self.decode_stats = DecodeStats()
        self.samples = SampleReader(config, self.decode_stats, ranges)
        self.fleet = Vehicles(config, self.health, self.report_once, self.log, linear_inputs)
        self.t_first_recv = math.nan
        self.t_last_recv = math.nan
        self._reported: set[str] = set()
        self._pending: dict[Address, bytes] = {}
        """Per stream: the start of a packet still arriving."""
        self.signing: SigningGate | None = None
        """With link.signing_key_file: the check every packet must pass."""
        if config.signing_key_file:
            try:
                key = load_key(config.signing_key_file)
            except (OSError, ValueError) as exc:
                raise ConfigError(f"link.signing_key_file: {exc}") from exc
            self.signing = SigningGate(key, self.health, self.report_once, rejected_path)

    def sign(self, codec: Codec, t_unix_s: float) -> None:
        """Make the station's codec sign what it sends (with signing on)."""
        if self.signing is not None:
            sign_outgoing(codec.mav, self.signing.key, t_unix_s)

    def report_once(self, key: str, text: str) -> None:
        """Say a problem once (it is counted every time)."""
        if key not in self._reported:
            self._reported.add(key)
            print(f"note: {text}", file=self.log)

    @property
    def vehicles(self) -> dict[int, VehicleLink]:
        return self.fleet.vehicles

    @property
    def refused_vehicles(self) -> dict[int, int]:
        return self.fleet.refused_vehicles

    def ground_messages(self, codec: Codec, now: float) -> Iterator[tuple[bytes, Address]]:
        """What the ground station sends each second: the fleet's heartbeats and rate
        requests (Vehicles.ground_messages), then each vehicle's further requests
        (VehicleSetup.requests: its autopilot's own messages, stream groups, parameters)."""
        yield from self.fleet.ground_messages(codec, now)
        for v in list(self.vehicles.values()):
            if v.address is None:
                continue
            setup = self.setup(v.system_id)
            fleet_asked = v.last_rate_request == now
            for packet in setup.requests(codec, v.acked, fleet_asked, now):
                yield packet, v.address
            self._setup_notes(setup)

    def setup(self, system_id: int) -> VehicleSetup:
        s = self.setups.get(system_id)
        if s is None:
            s = self.setups[system_id] = VehicleSetup(
                system_id, self.config, self.elevator_travel_deg, self.ranges
            )
        return s

    def rates_status(self, system_id: int) -> str:
        """The status line's account of a vehicle's channels: each one's recent rate and
        source ("!": too slow to identify anything from), "" before any."""
        setup = self.setups.get(system_id)
        return "" if setup is None else setup.rates_status()

    def _setup_notes(self, setup: VehicleSetup) -> None:
        for note in setup.notes:
            print(f"note: {note}", file=self.log)
        setup.notes.clear()

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

    def decoded_packet(self, packet: bytes, t_recv_s: float, decoded: Decoded) -> list[Frame]:
        """As packet(), for a packet whose meaning SampleReader.of_fields has given
        already (a tlog record read by tlog_fast): the same counters, notes and frames."""
        if self.signing is not None:
            return self.packet(packet, t_recv_s)
        return self._decoded(packet, None, t_recv_s, None, decoded)

    def sample_packet(
        self, packet: bytes, t_recv_s: float, compid: int, seq: int, sample: Sample
    ) -> list[Frame]:
        """As decoded_packet, for a recording's channel message that SampleReader.columns
        read whole (every value finite and in range), without signing: _decoded's steps
        for a Sample from no address, in its order (tests/telemetry/test_tlog_compiled.py
        compares the two on every damage case)."""
        if self.recorder is not None:
            self.recorder.write(int(round(t_recv_s * 1e6)), packet)
        if self.t_first_recv != self.t_first_recv:  # NaN: the first packet
            self.t_first_recv = t_recv_s
        self.t_last_recv = t_recv_s
        sysid = sample.system_id
        t_vehicle, kind = None, ""
        if (sample.wrap_s or math.inf) > COUNTER_TIME_WRAP_S:
            t_vehicle, kind = sample.t_vehicle_s, sample.message
        ground = sysid == mavlink.GCS_SYSTEM_ID
        if ground:
            self.health.ground_station(sysid, compid)
        if not self.health.on_packet(RECORDING, sysid, compid, seq, packet, t_vehicle, kind):
            self.report_once(
                "dup", "copies of packets, or packets long behind the vehicle's time: dropped"
            )
            return []
        out = [] if ground else self._sample(sysid, compid, sample, None, t_recv_s)
        if self.decode_stats.invalid_values:
            self.report_once("invalid", "NaN or absurd field value(s): counted, dropped")
        return out

    def samples_common(
        self,
        packets: list[bytes],
        t_recv_s: list[float],
        compids: list[int],
        seqs: list[int],
        samples: list[Sample],
        start: int = 0,
    ) -> tuple[int, list[Frame]]:
        """sample_packet over packets one after the other from `start`, for as many as
        are a vehicle's already heard (its channel sources set up), not a ground
        station's, and the common case of the counters (LinkHealth.on_common): counted
        as a run, their channels chosen as a run where the sources have settled
        (VehicleSetup.prepare_common), then each into the vehicle's synchroniser. Returns
        how many were taken and the frames they let go; sample_packet takes the rest
        (tests/telemetry/test_link_common.py compares the two on every damage case)."""
        if self.recorder is not None or self.signing is not None or start >= len(samples):
            return 0, []
        if self.t_first_recv != self.t_first_recv:  # NaN: no packet yet
            return 0, []
        sysid = samples[start].system_id
        v = self.fleet.vehicles.get(sysid)
        setup = self.setups.get(sysid)
        if v is None or setup is None or sysid == mavlink.GCS_SYSTEM_ID:
            return 0, []
        counted = _counted(sysid, compids, samples, start)
        n = self.health.on_common(RECORDING, packets, seqs, counted, start)
        if not n:
            return 0, []
        end = start + n
        self.t_last_recv = t_recv_s[end - 1]
        frames = self._synchronised(
            v, setup, compids[start:end], samples[start:end], t_recv_s[start:end]
        )
        return n, frames

    def _synchronised(
        self,
        v: VehicleLink,
        setup: VehicleSetup,
        compids: list[int],
        samples: list[Sample],
        t_recv_s: list[float],
    ) -> list[Frame]:
        """samples_common's samples, counted, into the vehicle's synchroniser: chosen as
        a run as far as VehicleSetup.prepare_common takes them, the rest by _sample."""
        chosen = setup.prepare_common(samples)
        stats = self.decode_stats
        if stats.invalid_values:  # sample_packet's note, said at its first packet
            out: list[Frame] = []
            for sample, compid in zip(chosen, compids, strict=False):
                if sample is not None:
                    out += self.fleet.sample(v, sample, compid)
                self.report_once("invalid", "NaN or absurd field value(s): counted, dropped")
        else:  # (none can come of these: the values counted are of_fields')
            out = self.fleet.samples(v, chosen, compids)
        for k in range(len(chosen), len(samples)):
            out += self._sample(v.system_id, compids[k], samples[k], None, t_recv_s[k])
            if stats.invalid_values:
                self.report_once("invalid", "NaN or absurd field value(s): counted, dropped")
        return out

    def _fast(self, packet: bytes, t_recv_s: float) -> Decoded | None:
        """The packet's meaning by decode.SampleReader where it can tell (a channel
        message that passes its CRC), else None. Not with signing on: there a packet's
        meaning counts only once its signature has passed."""
        if self.signing is not None:
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
        if self.signing is not None and not self.signing.passes(packet, t_recv_s, name):
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
        sysid = decoded.system_id
        if isinstance(event, Unknown):
            # Its CRC could not be checked: it may be junk that happens to frame, so no
            # counter but its own moves (nor the pin, nor the sequence).
            return self._event(sysid, decoded.component_id, event, address, name, t_recv_s)
        t_vehicle, kind = None, ""
        if isinstance(event, Sample) and (event.wrap_s or math.inf) > COUNTER_TIME_WRAP_S:
            t_vehicle, kind = event.t_vehicle_s, event.message
        if address is not None and not self.fleet.pinned(sysid, address, t_recv_s, name, event):
            return []
        if sysid == mavlink.GCS_SYSTEM_ID or (
            isinstance(event, Heartbeat) and event.ground_station
        ):
            self.health.ground_station(sysid, decoded.component_id)
        if not self.health.on_packet(
            name, sysid, decoded.component_id, decoded.seq, packet, t_vehicle, kind
        ):
            self.report_once(
                "dup", "copies of packets, or packets long behind the vehicle's time: dropped"
            )
            return []
        return self._event(sysid, decoded.component_id, event, address, name, t_recv_s)

    def _event(
        self,
        sysid: int,
        compid: int,
        event: object,
        address: Address | None,
        name: str,
        t_recv_s: float,
    ) -> list[Frame]:
        out: list[Frame] = []
        if isinstance(event, Sample):
            if sysid != mavlink.GCS_SYSTEM_ID:
                out = self._sample(sysid, compid, event, address, t_recv_s)
        elif isinstance(event, Unknown):
            self.health.counts(name).unknown += 1
            self.report_once("unknown", f"message unknown to the dialect ({event.name}): skipped")
        elif isinstance(event, Heartbeat | ParamValue):
            self._vehicle_event(sysid, compid, event, address, t_recv_s)
        elif isinstance(event, CommandAck):
            self.fleet.ack(sysid, compid, event)
        if self.decode_stats.invalid_values:
            self.report_once("invalid", "NaN or absurd field value(s): counted, dropped")
        return out

    def _vehicle_event(
        self,
        sysid: int,
        compid: int,
        event: Heartbeat | ParamValue,
        address: Address | None,
        t_recv_s: float,
    ) -> None:
        """A vehicle's HEARTBEAT (its presence, and which autopilot it is) or one of its
        parameters."""
        if isinstance(event, Heartbeat):
            if not event.ground_station:
                self.fleet.heartbeat(sysid, compid, event, address, t_recv_s)
                if event.autopilot and sysid in self.vehicles:
                    self.setup(sysid).autopilot(event.autopilot_kind)
        elif sysid != mavlink.GCS_SYSTEM_ID and self.fleet.seen(sysid, address, t_recv_s):
            setup = self.setup(sysid)
            setup.param(event)
            self._setup_notes(setup)

    def _sample(
        self, sysid: int, compid: int, event: Sample, address: Address | None, t_recv_s: float
    ) -> list[Frame]:
        """A vehicle's sample, as its parameters read it and with only the channels it is
        the chosen source of (VehicleSetup.prepare), into its synchroniser."""
        v = self.fleet.seen(sysid, address, t_recv_s)
        if v is None:
            return []
        setup = self.setup(sysid)
        sample = setup.prepare(event)
        if setup.notes:
            self._setup_notes(setup)
        return [] if sample is None else self.fleet.sample(v, sample, compid)

    def flush(self) -> Iterator[Frame]:
        """End of stream: whatever is open."""
        for v in self.vehicles.values():
            yield from v.sync.finish()

    def flush_recording(self) -> None:
        """Write what was recorded through to the file (the link may go quiet)."""
        for recorder in self._recorders():
            recorder.flush()

    def close(self) -> None:
        for recorder in self._recorders():
            recorder.close()

    def _recorders(self) -> list[TlogWriter]:
        """The files this link writes: the recording, and the rejected packets' file."""
        rejected = None if self.signing is None else self.signing.rejected
        return [r for r in (self.recorder, rejected) if r is not None]

    def session_time(self) -> float:
        """Seconds from the first packet to the newest [s] (NaN before any)."""
        return self.t_last_recv - self.t_first_recv

    def stats(self) -> dict[str, Any]:
        out: dict[str, Any] = dict(self.health.as_dict())
        out["invalid_values"] = self.decode_stats.invalid_values + sum(
            s.invalid_values for s in self.setups.values()
        )
        out["ignored_messages"] = self.decode_stats.ignored_messages
        if self.refused_vehicles:
            out["refused_vehicles"] = {str(k): n for k, n in self.refused_vehicles.items()}
        out["vehicles"] = {str(v.system_id): v.sync.stats.as_dict() for v in self.vehicles.values()}
        out["sources"] = {str(sid): s.report() for sid, s in self.setups.items()}
        return out


def link_of(config: AircraftConfig, **options: Any) -> MavlinkLink:
    """A link that decodes as the airframe file says (its [link] table, [data]
    input_hold and plausible ranges, the elevator's travel), with the caller's own
    options (recorder, log, rejected_path): the one place a session, a batch's task and
    a flight read ahead build it."""
    return MavlinkLink(
        config.link,
        linear_inputs=config.data.input_hold == "linear",
        ranges=ranges_of(config.data),
        elevator_travel_deg=config.airframe.elevator_travel_deg,
        **options,
    )
