"""A stretch of channel samples read whole from a run's columns goes through the link as a
run (decision 0069): the counters' common case (LinkHealth.on_common), the channel choice
where the sources have settled (ChannelSources.choose_common), then each sample into its
synchroniser. Each is what the packet-by-packet path does with the same packets: the same
verdicts and state on random streams (loss, copies, reorders, stale and absurd times,
reboots, untimed packets, two senders and components, several message types), and the
same frames, counters, notes and errors on replays of randomly damaged recordings."""

from __future__ import annotations

import itertools
import random
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gcs_estimator.config import load_config
from gcs_estimator.ingest.sources import TlogSource
from gcs_estimator.ingest.telemetry.channel_sources import ChannelSources
from gcs_estimator.ingest.telemetry.counters import LinkHealth
from gcs_estimator.ingest.telemetry.link import MavlinkLink
from gcs_estimator.ingest.telemetry.tlog_fast import CompiledTlogSource
from tests.telemetry.test_channel_settled import MESSAGES, _sample
from tests.telemetry.test_tlog_columns_damage import _random_damage, _rebooted
from tests.telemetry.test_tlog_compiled import SHORT, Records, _merged, _replay, _write
from tests.telemetry.test_tlog_compiled import flights as flights  # the module's fixture

PACKET = st.tuples(
    st.integers(1, 2),  # sender
    st.integers(1, 2),  # component
    st.sampled_from(
        ["next", "next", "next", "next", "next", "skip", "back", "same", "stale", "far", "spike"]
    ),
    st.sampled_from(["A", "B", "untimed"]),
    st.integers(0, 300),
)


def _stream(steps: list[tuple[int, int, str, str, int]]) -> list[tuple[Any, ...]]:
    """on_packet's arguments for each step (as test_counters_next makes them)."""
    seq: dict[tuple[int, int], int] = {}
    t: dict[tuple[int, int], float] = {}
    out: list[tuple[Any, ...]] = []
    for n, (sender, comp, what, kind, k) in enumerate(steps):
        key = (sender, comp)
        seq.setdefault(key, 0)
        t.setdefault(key, 100.0)
        if what == "next":
            seq[key] += 1
            t[key] += 0.01
        elif what == "skip":
            seq[key] += 1 + k
            t[key] += 0.01 * (1 + k)
        elif what == "back":
            seq[key] -= 1 + k % 5
        elif what == "stale":
            t[key] -= 2.0 + k
        elif what == "far":
            t[key] += 0.5 + k
        time = None if kind == "untimed" else t[key]
        if what == "spike" and time is not None:
            seq[key] += 1
            time += 5.0 + k
        packet = n.to_bytes(4, "little") + bytes([sender, comp])
        if what == "same" and n:
            packet = out[-1][4]  # a copy of the one before
        out.append(("recording", sender, comp, seq[key] & 0xFF, packet, time, kind))
    return out


def _by_run(health: LinkHealth, packets: list[tuple[Any, ...]], cuts: list[int]) -> list[bool]:
    """Each packet's verdict, the packets given to on_common in pieces (cut at `cuts`) and
    on_packet taking the first it does not take, as MavlinkLink.samples_common does."""
    verdicts: list[bool] = []
    bounds = sorted({0, len(packets), *[c % (len(packets) + 1) for c in cuts]})
    for a, b in itertools.pairwise(bounds):
        k = a
        while k < b:
            piece = packets[k:b]
            taken = health.on_common(
                "recording",
                [p[4] for p in packets],
                [p[3] for p in packets],
                (((p[1], p[2]), p[5], p[6]) for p in piece),
                k,
            )
            verdicts += [True] * taken
            k += taken
            if k < b:
                verdicts.append(health.on_packet(*packets[k]))
                k += 1
    return verdicts


@settings(max_examples=300, deadline=None)
@given(
    steps=st.lists(PACKET, max_size=400),
    cuts=st.lists(st.integers(0, 400), max_size=8),
)
def test_counting_a_run_is_counting_each_packet(
    steps: list[tuple[int, int, str, str, int]], cuts: list[int]
) -> None:
    packets = _stream(steps)
    each, run = LinkHealth(), LinkHealth()
    verdicts = [each.on_packet(*p) for p in packets]
    assert _by_run(run, packets, cuts) == verdicts
    assert run.as_dict() == each.as_dict()
    assert run._streams == each._streams
    assert run._copies == each._copies


def test_a_clean_stream_is_counted_as_a_run() -> None:
    """The path under test is taken: a clean stream after its first packet goes whole."""
    packets = _stream([(1, 1, "next", "A", 0)] * 300)
    health = LinkHealth()
    health.on_packet(*packets[0])
    assert _by_run(health, packets[1:], []) == [True] * 299
    assert health.total().received == 300


CHOICE = st.tuples(
    st.sampled_from(MESSAGES),
    st.floats(-0.3, 0.6, allow_nan=False),
    st.one_of(st.just(0), st.just(0), st.just(0), st.integers(0, 255)),
)


@settings(max_examples=300, deadline=None)
@given(steps=st.lists(CHOICE, max_size=300), cuts=st.lists(st.integers(0, 300), max_size=8))
def test_choosing_for_a_run_is_choosing_for_each_sample(
    steps: list[tuple[str, float, int]], cuts: list[int]
) -> None:
    samples = []
    t = 1000.0
    for message, dt, missing in steps:
        t += dt
        samples.append(_sample(message, t, missing))
    each, run = ChannelSources(1), ChannelSources(1)
    chosen = [each.choose(s) for s in samples]
    got: list[Any] = []
    bounds = sorted({0, len(samples), *[c % (len(samples) + 1) for c in cuts]})
    for a, b in itertools.pairwise(bounds):
        k = a
        while k < b:
            taken = run.choose_common(samples[k:b])
            got += taken
            k += len(taken)
            if k < b:
                got.append(run.choose(samples[k]))
                k += 1
    assert got == chosen
    assert run.notes == each.notes
    assert run.dropped == each.dropped
    assert run.t_last == each.t_last
    assert run.report() == each.report()
    assert {m: (x.count, x.last, list(x.recent)) for m, x in run.meters.items()} == {
        m: (x.count, x.last, list(x.recent)) for m, x in each.meters.items()
    }


class _Taken:
    """Counts the samples MavlinkLink.samples_common takes (the path is exercised)."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.n = 0
        plain = MavlinkLink.samples_common

        def counted(link: MavlinkLink, *args: Any) -> tuple[int, list[Any]]:
            taken, out = plain(link, *args)
            self.n += taken
            return taken, out

        monkeypatch.setattr(MavlinkLink, "samples_common", counted)


def _damaged(recs: Records, seed: int) -> list[bytes]:
    """_random_damage, and at a random place copies of ten records from a few seconds
    later (the vehicles' clocks jump ahead, then back)."""
    out = _random_damage(recs, seed)
    k = random.Random(seed).randrange(len(out) // 2)
    return out[:k] + out[k + 1500 : k + 1510] + out[k:]


@pytest.mark.parametrize("seed", [11, 12, 13, 14])
def test_a_replay_by_runs_is_the_replay_packet_by_packet(
    tmp_path: Path, flights: dict[str, Records], seed: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    config = load_config("noc_uav", SHORT)
    recs = _merged(_rebooted(flights["native1"]), flights["native2"], flights["arduplane"])
    path = _write(tmp_path / "f.tlog", _damaged(recs, seed))
    taken = _Taken(monkeypatch)
    runs = _replay(CompiledTlogSource, path, config)
    packets = _replay(TlogSource, path, config)
    assert runs == packets
    assert taken.n > len(runs["frames"])  # most samples went by runs
    assert runs["stats"]["lost"] and runs["stats"]["duplicates"]


def test_a_clean_replay_by_runs_is_the_replay_packet_by_packet(
    tmp_path: Path, flights: dict[str, Records], monkeypatch: pytest.MonkeyPatch
) -> None:
    config = load_config("noc_uav", SHORT)
    path = _write(tmp_path / "f.tlog", flights["arduplane"])
    taken = _Taken(monkeypatch)
    runs = _replay(CompiledTlogSource, path, config)
    assert runs == _replay(TlogSource, path, config)
    assert taken.n > 5 * len(runs["frames"])
