"""Link health: packets received, lost, duplicated, late and stale, per link and per vehicle.

Each (link, system, component) has its own 8-bit sequence, and loss is counted from it
alone: a step of d from the newest sequence number is d - 1 packets lost; a number
counted lost a little earlier that arrives is a late arrival (out of order), processed,
and the loss taken back; a step of 0 (the same number, other bytes) is a run of 255 lost.
A step is ambiguous by whole wraps of 256: 256 lost look like none, 1,000 like 232. Only
where the vehicle's time says more than a wrap went by are whole wraps added, and only on
evidence of the same message type (its time before and after the gap, its own period,
and the packets per second of vehicle time measured between its consecutive packets
where no loss or gap was counted: decision 0037). A copy of a packet already received
(the same bytes, on any link) is dropped. A packet with a vehicle time well behind the
stream's newest is stale (a copy from long ago, or a delayed one whose frame has gone):
dropped and counted, unless CONFIRM_PACKETS in a row say the vehicle rebooted, which
starts the stream afresh. A ground station's sequence numbers are not counted for loss:
it numbers what it sends to every vehicle and link, and only some of that is relayed
here.
"""

from __future__ import annotations

import math
import statistics
from collections import OrderedDict, deque
from collections.abc import Iterable
from dataclasses import dataclass, field
from itertools import islice
from typing import Any

STALE_S = 1.0
"""A packet this far behind its stream's newest vehicle time is stale [s]."""
CONFIRM_PACKETS = 3
"""Stale packets in a row that mean the vehicle's clock restarted (a reboot); packets in
a row that confirm a time this far ahead of the newest (a gap in the data)."""
SAME_TIME_S = 0.002
"""Times this close are one time (time_boot_ms and time_usec of one instant differ by the
millisecond's rounding): their order is judged by sequence number."""
MISSING_KEPT = 128
"""A sequence number counted lost can arrive late within this many packets."""
COPIES_KEPT = 1024
"""Packets of a stream remembered to recognise copies. The same bytes more than 255
packets apart are a copy only if they carry a vehicle time not after the newest (an
untimed message, such as a heartbeat, can repeat itself byte for byte)."""
RATE_MEMORY_S = 10.0
"""The packets per second of a stream are measured over about this much recent vehicle
time (between one message type's consecutive packets where nothing was lost) [s]."""
RATE_EVIDENCE_S = 1.0
"""Whole wraps are added to a gap only once the rate was measured over this long [s]."""
PERIODS_KEPT = 9
"""A message type's own period is the median of its last this many spans."""


class Verdict:
    NEW = "new"
    LATE = "late"
    """Arrived after packets sent after it (it had been counted lost)."""
    STALE = "stale"


@dataclass
class LinkCounts:
    """Counters of one link (one source address, or one recording)."""

    received: int = 0
    lost: int = 0
    duplicates: int = 0
    out_of_order: int = 0
    stale: int = 0
    corrupt: int = 0
    """Packets that failed the CRC or could not be framed."""
    junk_bytes: int = 0
    unknown: int = 0
    """Messages the dialect does not know (framed, their checksum cannot be checked): no
    other counter moves for them."""
    foreign: int = 0
    """Packets under a known vehicle's system id from another address: dropped."""
    unsigned: int = 0
    """With signing on: packets without a signature, dropped."""
    bad_signature: int = 0
    """With signing on: packets whose signature is wrong (forged, or another key)."""
    replayed: int = 0
    """With signing on: signed packets whose timestamp is not newer than their stream's."""
    moved: int = 0
    """Without signing: times a vehicle's telemetry moved to another address (the pin
    followed it)."""

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)

    def add(self, other: LinkCounts) -> None:
        for k, v in other.__dict__.items():
            setattr(self, k, getattr(self, k) + v)


@dataclass(slots=True)
class _Kind:
    """One message type's clock on a stream: the evidence for gaps longer than a wrap."""

    t: float
    """Its newest vehicle time [s]."""
    index: int
    """The stream's packet index at that packet."""
    gaps: int
    """The stream's gap count at that packet."""
    packets: float = 0.0
    seconds: float = 0.0
    """Packets of the stream, and vehicle seconds, between its consecutive packets where
    no loss was counted (recent ones weigh most)."""
    periods: deque[float] = field(default_factory=lambda: deque(maxlen=PERIODS_KEPT))
    """Its recent spans between consecutive packets with nothing lost [s]."""

    def clean(self, n: int, dt: float) -> None:
        if self.seconds > RATE_MEMORY_S:
            keep = RATE_MEMORY_S / self.seconds
            self.packets *= keep
            self.seconds *= keep
        self.packets += n
        self.seconds += dt
        self.periods.append(dt)

    def wraps_missed(self, n_seq: int, dt: float) -> int:
        """Whole wraps of 256 lost beyond the n_seq packets the sequence says were sent
        in dt: 0 unless a packet of this type is missing by its own period and the rate
        says more than half a wrap more were sent."""
        if self.seconds < RATE_EVIDENCE_S:
            return 0
        wraps = round((self.packets / self.seconds * dt - n_seq) / 256.0)
        if wraps < 1 or dt < 1.5 * statistics.median(self.periods):
            return 0
        return wraps


@dataclass
class _Stream:
    """One sequence: a (link, system, component)."""

    last_seq: int
    counted: bool = True
    """Whether its gaps are losses (not a ground station's)."""
    index: int = 0
    """Packets sent up to the newest (received and lost)."""
    gaps: int = 0
    """Gaps counted so far (a loss of any length)."""
    lost: int = 0
    newest_t: float = math.nan
    missing: dict[int, int] = field(default_factory=dict)
    """Sequence numbers counted lost -> the index they were counted at."""
    behind: int = 0
    """Stale packets in a row."""
    ahead: int = 0
    """Packets in a row with a time well ahead of the newest (a gap, or a bad time)."""
    ahead_t: float = math.nan
    kinds: dict[str, _Kind] = field(default_factory=dict)

    def restart(self, seq: int, t: float) -> None:
        """The vehicle restarted: this stream begins again at this packet."""
        self.last_seq, self.index, self.behind, self.ahead = seq, 0, 0, 0
        self.newest_t = t
        self.missing.clear()
        self.kinds.clear()

    def timed(self, t: float) -> None:
        newest = self.newest_t
        if newest != newest or t > newest:  # NaN (none yet), or later: max(newest, t)
            self.newest_t = t


@dataclass(slots=True)
class _Copies:
    """One (system, component)'s recent packets, to recognise copies."""

    seen: OrderedDict[bytes, tuple[str, int, int]] = field(default_factory=OrderedDict)
    """Recent packets -> the link they came by, the position they were taken at, and that
    link's stream index then."""
    position: int = 0
    """Packets sent up to the newest, by its sequence numbers' forward steps of less than
    half a wrap (others count none): packets 256 or more apart may repeat the same bytes
    (a heartbeat, after its sequence number came round again)."""
    last_seq: int = 0
    newest: float = -math.inf
    """The newest vehicle time among them [s]."""


# Over 200 lines: the counting rules (copies, sequence, stale, whole wraps) and their
# common case over a run (on_common, decision 0069) beside the rules it writes out, so
# that each shortcut is read next to what it must equal.
@dataclass
class LinkHealth:
    """Counters per link, and the copies seen per vehicle stream across links."""

    links: dict[str, LinkCounts] = field(default_factory=dict)
    _streams: dict[tuple[str, int, int], _Stream] = field(default_factory=dict)
    _copies: dict[tuple[int, int], _Copies] = field(default_factory=dict)
    """Per (system, component): what recognises copies of its packets."""
    _ground: set[tuple[int, int]] = field(default_factory=set)
    """(system, component)s that said they are ground stations."""

    def counts(self, link: str) -> LinkCounts:
        c = self.links.get(link)
        if c is None:
            c = self.links[link] = LinkCounts()
        return c

    def ground_station(self, system_id: int, component_id: int) -> None:
        """A (system, component) said it is a ground station: its gaps are no loss here
        (any counted so far is taken back)."""
        key = (system_id, component_id)
        if key in self._ground:
            return
        self._ground.add(key)
        for (link, sysid, compid), s in self._streams.items():
            if (sysid, compid) == key and s.counted:
                self.counts(link).lost -= s.lost
                s.counted, s.lost = False, 0

    def on_packet(
        self,
        link: str,
        system_id: int,
        component_id: int,
        seq: int,
        packet: bytes,
        t_vehicle_s: float | None = None,
        kind: str = "",
    ) -> bool:
        """Count a packet; False if it is to be dropped (a copy, or stale).

        t_vehicle_s: the vehicle time it carries, if its clock does not wrap within days;
        kind: its message type (whose own clock that time is)."""
        counts = self.links.get(link) or self.counts(link)
        key = (link, system_id, component_id)
        stream = self._streams.get(key)
        if self._is_copy((system_id, component_id), seq, packet, t_vehicle_s, link, stream):
            counts.duplicates += 1
            return False
        if stream is None:
            stream = _Stream(seq, counted=(system_id, component_id) not in self._ground)
            self._streams[key] = stream
            if t_vehicle_s is not None:
                stream.timed(t_vehicle_s)
                stream.kinds[kind] = _Kind(t_vehicle_s, 0, 0)
            counts.received += 1
            return True
        verdict = self._judge(stream, seq, t_vehicle_s, kind, counts)
        if verdict == Verdict.STALE:
            counts.stale += 1
            return False
        counts.received += 1
        return True

    def on_common(  # noqa: C901 - a packet's common case in one loop: in calls, it costs them
        self,
        link: str,
        packets: list[bytes],
        seqs: list[int],
        counted: Iterable[tuple[tuple[int, int], float | None, str]],
        start: int = 0,
    ) -> int:
        """on_packet over packets[start:] one after the other (each of a (system,
        component) already heard on this link, not a ground station's), for as many as
        are the common case: no copy (bytes not among the recent ones), the next
        sequence number and not one counted lost, and a time within STALE_S of the
        stream's newest (or none). `counted`: what on_packet takes of each beside its
        bytes and number, (system, component), vehicle time, message type (read only as
        far as taken). Those are counted as on_packet counts them (its _is_copy and
        _next, written out: tests/telemetry/test_link_common.py compares the two on
        random streams); the count taken is returned, and on_packet takes the rest from
        the first not taken."""
        counts = self.links.get(link)
        if counts is None:
            return 0
        streams, copies = self._streams, self._copies
        taken = 0
        last_key: tuple[int, int] | None = None
        s: _Stream | None = None
        c: _Copies | None = None
        each = zip(islice(packets, start, None), islice(seqs, start, None), counted, strict=False)
        for packet, seq, (key, t, kind) in each:
            if key != last_key:  # (one sender's packets mostly follow each other)
                last_key, s, c = key, streams.get((link, *key)), copies.get(key)
            if s is None or c is None or (seq - s.last_seq) & 0xFF != 1 or seq in s.missing:
                break
            seen = c.seen
            if packet in seen:
                break
            newest = s.newest_t
            if t is not None and not newest - STALE_S <= t <= newest + STALE_S:
                break  # (and while newest is NaN)
            step = (seq - c.last_seq) & 0xFF  # _is_copy, no copy
            if 0 < step < 128:
                c.position += step
            c.last_seq = seq
            seen[packet] = (link, c.position, s.index)
            if len(seen) > COPIES_KEPT:
                seen.popitem(last=False)
            s.index += 1
            s.last_seq = seq
            s.behind = 0
            if t is not None:  # _next
                if t > c.newest:
                    c.newest = t
                s.ahead = 0
                self._clock(s, kind, t, counts)
                if t > newest:
                    s.newest_t = t
            taken += 1
        counts.received += taken
        return taken

    def _is_copy(
        self,
        key: tuple[int, int],
        seq: int,
        packet: bytes,
        t: float | None,
        link: str,
        stream: _Stream | None,
    ) -> bool:
        """Whether the packet is a copy of one taken less than a wrap of its sequence
        before (on its own link by that link's count of packets sent, losses and whole
        wraps included; from another link by _Copies.position), or carries a vehicle
        time not after the newest taken."""
        c = self._copies.get(key)
        if c is None:
            c = self._copies[key] = _Copies()
        seen = c.seen
        step = (seq - c.last_seq) & 0xFF
        position = c.position + (step if 0 < step < 128 else 0)
        index = -1 if stream is None else stream.index  # the stream of (link, *key)
        at = seen.get(packet)
        if at is not None:
            near = index - at[2] < 255 if at[0] == link else position - at[1] < 256
            if near or (t is not None and t <= c.newest):
                return True
            seen.move_to_end(packet)  # a new packet goes in at the end anyway
        c.position, c.last_seq = position, seq
        seen[packet] = (link, position, index)
        if len(seen) > COPIES_KEPT:
            seen.popitem(last=False)
        if t is not None and t > c.newest:
            c.newest = t
        return False

    def _judge(self, s: _Stream, seq: int, t: float | None, kind: str, counts: LinkCounts) -> str:
        if t is not None and (seq - s.last_seq) & 0xFF == 1 and seq not in s.missing:
            newest = s.newest_t
            if newest - STALE_S <= t <= newest + STALE_S:  # (False while newest is NaN)
                return self._next(s, seq, t, kind, counts)
        return self._judged(s, seq, t, kind, counts)

    def _next(self, s: _Stream, seq: int, t: float, kind: str, counts: LinkCounts) -> str:
        """The common case: the next sequence number, its time within STALE_S of the
        newest, its number not among those counted lost (others may be: a late arrival
        is judged when it comes); what _judged does then, without its tests (not stale,
        not a late arrival, the time believed, no gap)."""
        s.behind = s.ahead = 0
        s.index += 1
        s.last_seq = seq
        self._clock(s, kind, t, counts)
        if t > s.newest_t:
            s.newest_t = t
        return Verdict.NEW

    def _judged(self, s: _Stream, seq: int, t: float | None, kind: str, counts: LinkCounts) -> str:
        if t is not None and not math.isnan(s.newest_t) and t < s.newest_t - STALE_S:
            s.behind += 1
            if s.behind < CONFIRM_PACKETS:
                return Verdict.STALE
            s.restart(seq, t)  # the vehicle's clock restarted
            s.kinds[kind] = _Kind(t, 0, 0)
            return Verdict.NEW
        s.behind = 0
        at = s.missing.pop(seq, None)
        if at is not None and s.index - at < MISSING_KEPT and not _forward(s, seq, t, kind, at):
            self._lose(s, counts, -1)
            counts.out_of_order += 1
            return Verdict.LATE
        t = _believed(s, t)
        d = (seq - s.last_seq) & 0xFF
        if d >= MISSING_KEPT and (
            s.index < 256 - d or (t is not None and t < s.newest_t - SAME_TIME_S)
        ):
            # Behind the stream's first packet (sent before it), or behind the newest by
            # sequence and by time yet not counted lost (delayed beyond MISSING_KEPT
            # packets): processed, counted late.
            counts.out_of_order += 1
            return Verdict.LATE
        n = d or 256  # the same number with other bytes: a run of 255 lost
        if n > 1:
            s.gaps += 1
            self._lose(s, counts, n - 1)
            for k in range(max(1, n - MISSING_KEPT), n):
                s.missing[(s.last_seq + k) & 0xFF] = s.index + k
        s.index += n
        s.last_seq = seq
        if t is not None:
            self._clock(s, kind, t, counts)
            s.timed(t)
        if len(s.missing) > MISSING_KEPT:
            s.missing = {q: i for q, i in s.missing.items() if s.index - i < MISSING_KEPT}
        return Verdict.NEW

    def _clock(self, s: _Stream, kind: str, t: float, counts: LinkCounts) -> None:
        """The message type's time since its previous packet: whole wraps the sequence
        could not show are added to the loss (_Kind.wraps_missed); a span with nothing
        lost measures the stream's rate and the type's period."""
        k = s.kinds.get(kind)
        if k is None:
            s.kinds[kind] = _Kind(t, s.index, s.gaps)
            return
        dt = t - k.t
        if dt <= SAME_TIME_S:
            return
        n_seq = s.index - k.index
        seconds = k.seconds
        # wraps_missed is 0 unless the rate says more than half a wrap more were sent
        # (round(x / 256) >= 1: x > 128); most packets end the test here, without a call
        if seconds >= RATE_EVIDENCE_S and k.packets / seconds * dt - n_seq > 128.0:
            wraps = k.wraps_missed(n_seq, dt)
            if wraps:
                s.gaps += 1
                s.index += 256 * wraps
                self._lose(s, counts, 256 * wraps)
        if s.gaps == k.gaps:  # nothing lost since its previous packet: _Kind.clean
            k.clean(n_seq, dt)
        k.t, k.index, k.gaps = t, s.index, s.gaps

    @staticmethod
    def _lose(s: _Stream, counts: LinkCounts, n: int) -> None:
        if s.counted:
            s.lost += n
            counts.lost += n

    def total(self) -> LinkCounts:
        out = LinkCounts()
        for c in self.links.values():
            out.add(c)
        return out

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = self.total().as_dict()
        if len(self.links) > 1:
            out["links"] = {k: c.as_dict() for k, c in self.links.items()}
        return out


def _forward(s: _Stream, seq: int, t: float | None, kind: str, at: int) -> bool:
    """Whether a packet whose sequence number was counted lost at index `at` is rather
    one a whole wrap later (after a gap): its message type's own time, at the rate
    measured between its packets, lies nearer the index it would have forward."""
    k = s.kinds.get(kind)
    if t is None or k is None or k.seconds < RATE_EVIDENCE_S:
        return False
    expected = (t - k.t) * k.packets / k.seconds
    ahead = s.index + ((seq - s.last_seq) & 0xFF) - k.index
    return abs(expected - ahead) < abs(expected - (at - k.index))


def _believed(s: _Stream, t: float | None) -> float | None:
    """The time to judge a packet by. One well ahead of the stream's newest is believed
    once CONFIRM_PACKETS in a row agree (a gap in the data); until then the packet is
    judged by its sequence number alone (None), so a single packet with an absurd time
    moves nothing."""
    if t is None:
        return None  # untimed packets between neither confirm nor deny
    if math.isnan(s.newest_t) or t <= s.newest_t + STALE_S:
        s.ahead = 0
        return t
    if s.ahead and abs(t - s.ahead_t) <= STALE_S:
        s.ahead += 1
    else:
        s.ahead = 1
    s.ahead_t = t
    if s.ahead < CONFIRM_PACKETS:
        return None
    s.ahead = 0
    return t
