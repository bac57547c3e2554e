"""Link health against a reference count: gaps of any length, copies, reorders, wraps.

A sender numbers its packets 0..N-1 (sequence = number mod 256, one packet every
1/300 s of vehicle time, as a vehicle's component streaming seven messages at 50 Hz
does). A channel loses runs of packets (some longer than the 256 sequence numbers),
copies packets (at once, or a copy of one from up to 1,000 packets before), and swaps
neighbours. The reference count follows from what was delivered.

What the counters cannot know is not asked of them: a burst longer than 255 is counted
from the vehicle's time once three packets after it agree on that time; a packet reordered
by more than MISSING_KEPT packets is no longer recognised as one counted lost.
"""

from __future__ import annotations

from dataclasses import dataclass

from hypothesis import given, settings
from hypothesis import strategies as st

from gcs_estimator.ingest.telemetry.counters import LinkHealth

RATE_HZ = 300.0


def _packet(i: int) -> tuple[int, bytes, float]:
    """(sequence, bytes, vehicle time) of the sender's packet i."""
    return i % 256, i.to_bytes(4, "little"), 10.0 + i / RATE_HZ


Op = tuple[str, int]
ops = st.lists(
    st.one_of(
        st.tuples(st.just("send"), st.integers(1, 200)),
        st.tuples(st.just("lose"), st.integers(1, 700)),
        st.tuples(st.just("copy"), st.integers(0, 999)),
        st.tuples(st.just("swap"), st.integers(1, 5)),
    ),
    max_size=40,
)


@dataclass
class Reference:
    delivered: list[int]

    def counts(self) -> dict[str, int]:
        seen: set[int] = set()
        newest = -1
        late = copies = 0
        for i in self.delivered:
            if i in seen:
                copies += 1
                continue
            if i < newest:
                late += 1
            seen.add(i)
            newest = max(newest, i)
        span = max(seen) - min(seen) + 1
        return {
            "received": len(seen),
            "lost": span - len(seen),
            "duplicates": copies,
            "out_of_order": late,
        }


def _deliveries(plan: list[Op]) -> list[int]:
    """Indices delivered: the first 400 packets arrive (the stream's rate is known), then
    the plan."""
    out = list(range(400))
    nxt = 400
    for op, n in plan:
        if op == "send":
            out += range(nxt, nxt + n)
            nxt += n
        elif op == "lose":
            # A loss is seen when the packets after it arrive (a gap in time longer than
            # STALE_S is believed once three packets agree).
            nxt += n
            out += range(nxt, nxt + 3)
            nxt += 3
        elif op == "copy":
            out.append(out[max(0, len(out) - 1 - n)])
        else:  # swap the next packet with the one n after it (both arrive)
            block = list(range(nxt, nxt + n + 1))
            block[0], block[-1] = block[-1], block[0]
            out += block
            nxt += n + 1
    return out


@settings(max_examples=300, deadline=None)
@given(plan=ops, other_vehicle=st.booleans())
def test_counts_match_the_reference_for_any_pattern(plan: list[Op], other_vehicle: bool) -> None:
    delivered = _deliveries(plan)
    h = LinkHealth()
    kept = []
    for i in delivered:
        seq, data, t = _packet(i)
        if h.on_packet("link", 1, 1, seq, data, t):
            kept.append(i)
        if other_vehicle:
            # Another vehicle on the link, with the same pattern: its numbering is its own.
            h.on_packet("link", 2, 1, seq, b"other" + data, t)
    expected = Reference(delivered).counts()
    counts = h.counts("link").as_dict()
    times = 2 if other_vehicle else 1
    assert {k: counts[k] for k in expected} == {k: times * v for k, v in expected.items()}
    # Every packet delivered at least once is processed exactly once.
    assert sorted(kept) == sorted(set(delivered))


def test_untimed_packets_judged_by_sequence_and_links_apart() -> None:
    h = LinkHealth()
    for seq in [*range(250, 256), *range(0, 5)]:
        assert h.on_packet("a", 1, 1, seq, bytes([seq]))
    assert h.counts("a").lost == 0 and h.counts("a").received == 11
    assert h.on_packet("a", 1, 1, 8, b"8")  # 5, 6, 7 lost
    assert h.counts("a").lost == 3
    assert not h.on_packet("a", 1, 1, 8, b"8")  # a copy: dropped
    assert h.on_packet("a", 1, 1, 6, b"6")  # one counted lost arrived late
    a = h.counts("a")
    assert (a.duplicates, a.out_of_order, a.lost) == (1, 1, 2)
    # The same vehicle over a second link: its copies of packets already taken are
    # dropped; its own losses are its own.
    assert not h.on_packet("b", 1, 1, 8, b"8")
    assert h.on_packet("b", 1, 1, 9, b"9") and h.on_packet("b", 1, 1, 12, b"12")
    assert h.counts("b").lost == 2 and h.counts("a").lost == 2
    assert h.total().lost == 4
    assert set(h.as_dict()["links"]) == {"a", "b"}


def test_a_stale_packet_is_dropped_and_a_reboot_starts_the_stream_again() -> None:
    h = LinkHealth()
    for i in range(600):
        seq, data, t = _packet(i)
        assert h.on_packet("l", 1, 1, seq, data, t)
    # A packet from 1.5 s ago that is no copy of anything kept: stale.
    assert not h.on_packet("l", 1, 1, 7, b"old", 8.0)
    assert h.counts("l").stale == 1
    seq, data, t = _packet(600)
    assert h.on_packet("l", 1, 1, seq, data, t)
    # The vehicle reboots: its time starts again; three packets in a row confirm it.
    verdicts = [
        h.on_packet("l", 1, 1, k, b"boot" + bytes([k]), 0.1 + k / RATE_HZ) for k in range(6)
    ]
    assert verdicts == [False, False, True, True, True, True]
    assert h.counts("l").lost == 0
