"""Link health: packets received, lost, duplicated, late and stale, per link and per vehicle.

Each (link, system, component) has its own 8-bit sequence. A jump of the sequence is
ambiguous by multiples of 256; where packets carry the vehicle's time, the gap is judged
by that time and the stream's packet rate, so a burst of more than 255 lost packets is
counted as such. A packet whose sequence number was counted lost a little earlier is a
late arrival (out of order): it is processed and the loss taken back. A copy of a packet
already received (the same bytes, on any link) is dropped. A packet with a vehicle time
well behind the stream's newest is stale (a copy from long ago, or a delayed one whose
frame has gone): dropped and counted, unless CONFIRM_PACKETS in a row say the vehicle
rebooted, which starts the stream afresh.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

STALE_S = 1.0
"""A packet this far behind its stream's newest vehicle time is stale [s]."""
CONFIRM_PACKETS = 3
"""Stale packets in a row that mean the vehicle's clock restarted (a reboot)."""
SAME_TIME_S = 0.002
"""Times this close are one time (time_boot_ms and time_usec of one instant differ by the
millisecond's rounding): their order is judged by sequence number."""
MISSING_KEPT = 128
"""A sequence number counted lost can arrive late within this many packets."""
COPIES_KEPT = 1024
"""Packets of a stream remembered to recognise copies. The same bytes more than 255
packets apart are a copy only if they carry a vehicle time not after the newest (an
untimed message, such as a heartbeat, can repeat itself byte for byte)."""


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
    """Messages the dialect does not know (framed, their checksum cannot be checked)."""
    foreign: int = 0
    """Packets under a known vehicle's system id from another address: dropped."""
    unsigned: int = 0
    """With signing on: packets without a signature, dropped."""
    bad_signature: int = 0
    """With signing on: packets whose signature is wrong (forged, or another key)."""
    replayed: int = 0
    """With signing on: signed packets whose timestamp is not newer than their stream's."""

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)

    def add(self, other: LinkCounts) -> None:
        for k, v in other.__dict__.items():
            setattr(self, k, getattr(self, k) + v)


@dataclass
class _Stream:
    """One sequence: a (link, system, component)."""

    last_seq: int
    index: int = 0
    """Packets sent up to the newest (received and lost)."""
    newest_t: float = math.nan
    t_first: float = math.nan
    index_first: int = 0
    missing: dict[int, int] = field(default_factory=dict)
    """Sequence numbers counted lost -> the index they were counted at."""
    behind: int = 0
    """Stale packets in a row."""
    ahead: int = 0
    """Packets in a row with a time well ahead of the newest (a gap, or a bad time)."""
    ahead_t: float = math.nan
    ahead_extra: int = 0
    """Packets the time says were lost in the gap beyond what the sequence says."""

    def restart(self, seq: int, t: float) -> None:
        """The vehicle restarted: this stream begins again at this packet."""
        self.last_seq, self.index, self.behind = seq, 0, 0
        self.newest_t = self.t_first = math.nan
        self.missing.clear()
        self.timed(t)

    def rate(self) -> float:
        """Packets per second of vehicle time (NaN until a second has passed)."""
        span = self.newest_t - self.t_first
        return (self.index - self.index_first) / span if span >= 1.0 else math.nan

    def timed(self, t: float) -> None:
        if math.isnan(self.t_first):
            self.t_first, self.index_first = t, self.index
        self.newest_t = t if math.isnan(self.newest_t) else max(self.newest_t, t)


def _gap(stream: _Stream, d: int, t: float | None) -> int:
    """How many packets on from the newest this one is (d + 256 k); 0: not forward."""
    if t is not None and not math.isnan(stream.newest_t):
        dt = t - stream.newest_t
        if dt > SAME_TIME_S:
            rate = stream.rate()
            k = 0 if math.isnan(rate) else max(0, round((rate * dt - d) / 256.0))
            return d + 256 * k if d + 256 * k > 0 else 256
        if dt < -SAME_TIME_S:
            return 0
    return d if 0 < d < 128 else 0


@dataclass(slots=True)
class _Copies:
    """One (system, component)'s recent packets, to recognise copies."""

    seen: OrderedDict[bytes, int] = field(default_factory=OrderedDict)
    """Recent packets -> their number among its packets."""
    taken: int = 0
    """Its packets taken so far."""
    newest: float = -math.inf
    """The newest vehicle time among them [s]."""


@dataclass
class LinkHealth:
    """Counters per link, and the copies seen per vehicle stream across links."""

    links: dict[str, LinkCounts] = field(default_factory=dict)
    _streams: dict[tuple[str, int, int], _Stream] = field(default_factory=dict)
    _copies: dict[tuple[int, int], _Copies] = field(default_factory=dict)
    """Per (system, component): what recognises copies of its packets."""

    def counts(self, link: str) -> LinkCounts:
        c = self.links.get(link)
        if c is None:
            c = self.links[link] = LinkCounts()
        return c

    def on_packet(
        self,
        link: str,
        system_id: int,
        component_id: int,
        seq: int,
        packet: bytes,
        t_vehicle_s: float | None = None,
    ) -> bool:
        """Count a packet; False if it is to be dropped (a copy, or stale).

        t_vehicle_s: the vehicle time it carries, if its clock does not wrap within days."""
        counts = self.counts(link)
        if self._is_copy((system_id, component_id), packet, t_vehicle_s):
            counts.duplicates += 1
            return False
        key = (link, system_id, component_id)
        stream = self._streams.get(key)
        if stream is None:
            self._streams[key] = stream = _Stream(seq)
            if t_vehicle_s is not None:
                stream.timed(t_vehicle_s)
            counts.received += 1
            return True
        verdict = self._judge(stream, seq, t_vehicle_s, counts)
        if verdict == Verdict.STALE:
            counts.stale += 1
            return False
        counts.received += 1
        return True

    def _is_copy(self, key: tuple[int, int], packet: bytes, t: float | None) -> bool:
        c = self._copies.get(key)
        if c is None:
            c = self._copies[key] = _Copies()
        seen, n = c.seen, c.taken
        at = seen.get(packet)
        if at is not None:
            if n - at < 255 or (t is not None and t <= c.newest):
                return True
            seen.move_to_end(packet)  # a new packet goes in at the end anyway
        seen[packet] = n
        if len(seen) > COPIES_KEPT:
            seen.popitem(last=False)
        c.taken = n + 1
        if t is not None and t > c.newest:
            c.newest = t
        return False

    def _judge(self, s: _Stream, seq: int, t: float | None, counts: LinkCounts) -> str:
        if t is not None and not math.isnan(s.newest_t) and t < s.newest_t - STALE_S:
            s.behind += 1
            if s.behind < CONFIRM_PACKETS:
                return Verdict.STALE
            s.restart(seq, t)  # the vehicle's clock restarted
            return Verdict.NEW
        s.behind = 0
        ahead = t is not None and not math.isnan(s.newest_t) and t > s.newest_t + STALE_S
        if ahead and t is not None:
            t = self._ahead(s, seq, t, counts)
        else:
            s.ahead = 0
        at = s.missing.pop(seq, None)
        newer = ahead or (t is not None and t > s.newest_t + SAME_TIME_S)
        if at is not None and s.index - at < MISSING_KEPT and not newer:
            counts.out_of_order += 1
            counts.lost -= 1
            return Verdict.LATE
        d = (seq - s.last_seq) & 0xFF
        n = (d or 256) if ahead else _gap(s, d, t)
        if n == 0:
            # Behind the newest by its sequence but no longer remembered as lost (delayed
            # beyond MISSING_KEPT packets): processed, counted late.
            counts.out_of_order += 1
            counts.lost = max(0, counts.lost - 1)
            return Verdict.LATE
        counts.lost += n - 1
        for k in range(max(1, n - MISSING_KEPT), n):
            s.missing[(s.last_seq + k) & 0xFF] = s.index + k
        s.index += n
        s.last_seq = seq
        if t is not None:
            s.timed(t)
        if len(s.missing) > MISSING_KEPT:
            s.missing = {q: i for q, i in s.missing.items() if s.index - i < MISSING_KEPT}
        return Verdict.NEW

    @staticmethod
    def _ahead(s: _Stream, seq: int, t: float, counts: LinkCounts) -> float | None:
        """A time well ahead of the stream's newest is believed once CONFIRM_PACKETS in a
        row agree (a gap: the losses its time implies are then counted); until then the
        packet is judged by its sequence number alone, and a single packet with an absurd
        time moves nothing. The packet itself is the next in sequence (its time says it
        is not behind). Returns the time to judge the packet by (None: none)."""
        if s.ahead and abs(t - s.ahead_t) <= STALE_S:
            s.ahead += 1
        else:
            d = (seq - s.last_seq) & 0xFF
            s.ahead, s.ahead_extra = 1, _gap(s, d, t) - (d or 256)
        s.ahead_t = t
        if s.ahead < CONFIRM_PACKETS:
            return None
        counts.lost += max(0, s.ahead_extra)
        s.index += max(0, s.ahead_extra)
        s.ahead = 0
        s.timed(t)
        return None

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
