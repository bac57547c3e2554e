"""LinkHealth's common case (the next sequence number on time, nothing missing: _next,
decision 0064) is what its full judgement (_judged) does with the same packet: the same
verdicts, counters and stream state on random streams (loss, copies, reorders, stale
and absurd times, one absurd time among good ones, reboots, untimed packets, several
message types and senders), and the same replays on randomly damaged recordings."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gcs_estimator.config import load_config
from gcs_estimator.ingest.telemetry.counters import LinkHealth
from gcs_estimator.ingest.telemetry.tlog_fast import CompiledTlogSource
from tests.telemetry.test_tlog_columns_damage import _random_damage, _rebooted
from tests.telemetry.test_tlog_compiled import SHORT, Records, _merged, _replay, _write
from tests.telemetry.test_tlog_compiled import flights as flights  # the module's fixture


class _Judged(LinkHealth):
    """Every packet through the full judgement."""

    def _judge(self, s, seq, t, kind, counts):  # type: ignore[no-untyped-def]
        return self._judged(s, seq, t, kind, counts)


STEP = st.tuples(
    st.integers(1, 2),  # sender
    st.sampled_from(
        ["next", "next", "next", "next", "skip", "back", "same", "stale", "far", "spike"]
    ),
    st.sampled_from(["A", "B", "untimed"]),
    st.integers(0, 300),
)


@settings(max_examples=300, deadline=None)
@given(steps=st.lists(STEP, max_size=400))
def test_the_common_case_is_the_full_judgement(steps: list[tuple[int, str, str, int]]) -> None:
    fast, full = LinkHealth(), _Judged()
    seq = {1: 0, 2: 0}
    t = {1: 100.0, 2: 100.0}
    for n, (sender, what, kind, k) in enumerate(steps):
        if what == "next":
            seq[sender] += 1
            t[sender] += 0.01
        elif what == "skip":
            seq[sender] += 1 + k
            t[sender] += 0.01 * (1 + k)
        elif what == "back":
            seq[sender] -= 1 + k % 5
        elif what == "stale":
            t[sender] -= 2.0 + k
        elif what == "far":
            t[sender] += 0.5 + k
        time = None if kind == "untimed" else t[sender]
        if what == "spike" and time is not None:  # one absurd time, the next ones not
            seq[sender] += 1
            time += 5.0 + k
        packet = n.to_bytes(4, "little") + bytes([sender])
        if what == "same" and n:
            packet = (n - 1).to_bytes(4, "little") + bytes([sender])  # a copy
        args = ("recording", sender, 1, seq[sender] & 0xFF, packet, time, kind)
        assert fast.on_packet(*args) == full.on_packet(*args)
    assert fast.as_dict() == full.as_dict()
    assert fast._streams == full._streams


@pytest.mark.parametrize("seed", [5, 6])
def test_replays_with_and_without_the_common_case_are_the_same(
    tmp_path: Path, flights: dict[str, Records], seed: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    config = load_config("noc_uav", SHORT)
    recs = _merged(_rebooted(flights["native1"]), flights["native2"], flights["arduplane"])
    path = _write(tmp_path / "f.tlog", _random_damage(recs, seed))
    fast = _replay(CompiledTlogSource, path, config)
    monkeypatch.setattr(LinkHealth, "_judge", _Judged._judge)
    full = _replay(CompiledTlogSource, path, config)
    assert fast == full
    assert fast["stats"]["lost"] and fast["stats"]["out_of_order"]
