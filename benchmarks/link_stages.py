"""Where a tlog's decoding spends its CPU, part by part (decision 0058).

    python benchmarks/link_stages.py [--seconds 600] [--rounds 2] [--on-and-off N]

Simulates one flight of the NOC UAV (.tlog, the simulator's native message set), then
runs each part of the link alone over the same records in order, by the CPU time charged
to this process (the machine's load does not count, other than through its caches) with
the garbage collector off: the kernel reading (framing, CRC, fields, its columns as
lists), the per-record loop, SampleReader.of_fields, LinkHealth.on_packet, the channel
choice (VehicleSetup.prepare) and the vehicle and synchroniser, and apart what of
of_fields' work the run's columns do (SampleReader.columns, decision 0064: the replay
takes it in of_fields' place wherever a sample is whole); then the whole decoding
to frames (CompiledTlogSource) and one log estimated as a batch's task does it
(estimate_file). The minimum of --rounds for each. --on-and-off N: only decoding to
frames and the estimate with the run paths off, with decision 0064's and with 0069's
too, alternately, N rounds. --tlog PATH: that log (simulated as above, same --seconds)
instead of simulating one.
"""

from __future__ import annotations

import argparse
import gc
import io
import os
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from fleet_dask import _overrides, write_flight

from gcs_estimator.config import load_config
from gcs_estimator.ingest.telemetry import tlog_fast
from gcs_estimator.ingest.telemetry.channel_sources import ChannelSources
from gcs_estimator.ingest.telemetry.counters import LinkHealth
from gcs_estimator.ingest.telemetry.decode import Sample
from gcs_estimator.ingest.telemetry.link import MavlinkLink
from gcs_estimator.ingest.telemetry.mavlink import TlogStats
from gcs_estimator.ingest.telemetry.tlog_fast import (
    CompiledTlogSource,
    _columns,
    _with_text,
    read_runs,
    table_of,
    warm_up,
)
from gcs_estimator.runtime.logs import estimate_file
from gcs_estimator.stop import Stop

Item = tuple[bytes, float, Any]


def _cpu(work: Callable[[], Any], rounds: int) -> tuple[float, Any]:
    """The least CPU time of `rounds` runs, and the last run's result."""
    best, out = float("inf"), None
    for _ in range(rounds):
        c0 = time.process_time()
        out = work()
        best = min(best, time.process_time() - c0)
    return best, out


def _records(path: Path, config: Any) -> list[Item]:
    """Each record's packet, receive time and what of_fields takes (None: not a
    channel message the kernel read), as CompiledTlogSource._run_frames makes them."""
    table = table_of(config.link)
    items: list[Item] = []
    for run in read_runs(path, TlogStats(), table):
        for j, status in enumerate(run.status):
            t = run.times[j] * 1e-6
            packet = run.data[run.starts[j] : run.ends[j]]
            if status < 0:
                items.append((packet, t, None))
                continue
            msg = table.messages[status]
            fields = run.fields(j, msg.count)
            if msg.texts:
                fields = _with_text(packet, msg, fields)
            head = (msg.msgid, run.seq[j], run.system_id[j], run.component_id[j])
            items.append((packet, t, (*head, fields)))
    return items


def _on_columns(path: Path, config: Any, rounds: int) -> tuple[float, int]:
    """CPU seconds of SampleReader.columns over the log's runs, the samples made one by
    one as the replay takes them, and how many it read whole."""
    table = table_of(config.link)
    runs = list(read_runs(path, TlogStats(), table))

    def work() -> int:
        reader = MavlinkLink(config.link, log=io.StringIO()).samples
        n = 0
        for run in runs:
            got = _columns(run, table, reader)
            if got is not None:
                for c, k in zip(*got, strict=True):
                    n += c is not None and c.sample(k) is not None
        return n

    t, n = _cpu(work, rounds)
    return t, int(n)


def stages(path: Path, config: Any, rounds: int) -> list[tuple[str, float]]:
    """CPU seconds of each part, run alone over the log's records in order."""
    out = []
    table = table_of(config.link)
    t, _ = _cpu(lambda: list(read_runs(path, TlogStats(), table)), rounds)
    out.append(("reading (kernel, columns)", t))
    t, items = _cpu(lambda: _records(path, config), rounds)
    out.append(("+ per-record loop", t - out[0][1]))

    def decode() -> list[Any]:
        of = MavlinkLink(config.link, log=io.StringIO()).samples.of_fields
        return [of(a[0], a[1], a[2], a[3], a[4], t) if a else None for _, t, a in items]

    t, decoded = _cpu(decode, rounds)
    out.append(("SampleReader.of_fields", t))

    t_columns, n_columns = _on_columns(path, config, rounds)
    samples = [(p, d) for (p, _, _), d in zip(items, decoded, strict=True) if d is not None]

    def count() -> list[Sample]:
        health = MavlinkLink(config.link, log=io.StringIO()).health
        kept = []
        for packet, d in samples:
            e = d.event
            timed = isinstance(e, Sample)
            t_v, kind = (e.t_vehicle_s, e.message) if timed else (None, "")
            counted = health.on_packet(
                "recording", d.system_id, d.component_id, d.seq, packet, t_v, kind
            )
            if counted and timed:
                kept.append(e)
        return kept

    t, kept = _cpu(count, rounds)
    out.append(("LinkHealth.on_packet", t))

    def choose() -> list[Sample | None]:
        setup = MavlinkLink(config.link, log=io.StringIO()).setup(1)
        return [setup.prepare(s) for s in kept]

    t, prepared = _cpu(choose, rounds)
    out.append(("channel choice (prepare)", t))

    def synchronise() -> int:
        link = MavlinkLink(config.link, log=io.StringIO())
        v = link.fleet.vehicle(1)
        assert v is not None
        return sum(len(link.fleet.sample(v, s, 1)) for s in prepared if s is not None)

    out.append(("vehicle and synchroniser", _cpu(synchronise, rounds)[0]))
    out.append((f"(of_fields' {n_columns} on columns)", t_columns))
    return out


def _switch(setting: str) -> None:
    """The link's run paths by setting: "off", record by record as before decision 0064
    (every value judged, the counters' full judgement); "0064", that decision's paths
    on (the columns, ATTITUDE's remembered values, the counters' common case); "on",
    decision 0069's too (a stretch of whole samples through the link as a run)."""
    off: tuple[Any, ...] = (
        lambda run, table, reader: None,
        lambda self, shape, message: None,
        LinkHealth._judged,
        lambda self, *args: (0, []),
    )
    first = {"off": 0, "0064": 3, "on": 4}[setting]
    for k, ((owner, name), path, plain) in enumerate(zip(_WHERE, _PATHS, off, strict=True)):
        setattr(owner, name, path if k < first else plain)


_WHERE: tuple[tuple[Any, str], ...] = (
    (tlog_fast, "_columns"),
    (ChannelSources, "_remember"),
    (LinkHealth, "_judge"),
    (MavlinkLink, "samples_common"),
)
_PATHS: tuple[Any, ...] = tuple(getattr(owner, name) for owner, name in _WHERE)
SETTINGS = ("off", "0064", "on")


def on_and_off(path: Path, config: Any, rounds: int, tmp_dir: str, seconds: float) -> None:
    """Decoding to frames and the whole estimate with the run paths off, with decision
    0064's on, and with 0069's too, alternately in this process (the load moves all
    alike); the frames and link statistics asserted the same."""
    got: dict[str, Any] = {}
    cpu: dict[str, dict[str, list[float]]] = {"decoding": {}, "estimate": {}}

    def frames() -> Any:
        link = MavlinkLink(config.link, log=io.StringIO())
        source = CompiledTlogSource([path], link, log=io.StringIO())
        done = [
            (f.t_vehicle_s, f.y.tobytes(), f.inputs.tobytes())
            for f in source.frames(Stop())
            if f is not None
        ]
        return done, source.link_stats()

    for _ in range(rounds):
        for setting in SETTINGS:
            _switch(setting)
            c0 = time.process_time()
            got[setting] = frames()
            cpu["decoding"].setdefault(setting, []).append(time.process_time() - c0)
            c0 = time.process_time()
            estimate_file(path, config, Path(tmp_dir) / f"ab{setting}")
            cpu["estimate"].setdefault(setting, []).append(time.process_time() - c0)
    _switch("on")
    assert all(v == got["off"] for v in got.values()), "a run path changed the frames or counters"
    for part, runs in cpu.items():
        least = {k: min(v) for k, v in runs.items()}
        line = ", ".join(f"{k} {t:.2f} s" for k, t in least.items())
        print(f"  {part} (min of {rounds}): {line}; off/on {least['off'] / least['on']:.2f}x")
        if part == "estimate":
            rates = ", ".join(f"{k} {seconds / t:.0f}" for k, t in least.items())
            print(f"  flight-hours per CPU-hour: {rates}")
    print(f"  load average {os.getloadavg()[0]:.1f}; frames and counters the same")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seconds", type=float, default=600.0)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument(
        "--on-and-off",
        type=int,
        default=0,
        metavar="N",
        help="only compare the run paths off, decision 0064's, and 0069's too (N rounds)",
    )
    ap.add_argument("--tlog", type=Path, help="a log this script simulated before")
    args = ap.parse_args(argv)
    config = load_config("noc_uav", _overrides(args.seconds))
    with tempfile.TemporaryDirectory() as tmp_dir:
        path = args.tlog or Path(tmp_dir) / "flight.tlog"
        if args.tlog is None:
            write_flight(config, path, 100)
        warm_up()
        estimate_file(path, config, Path(tmp_dir) / "warm")
        print(f"{args.seconds:g} s flight; load average {os.getloadavg()[0]:.1f}; CPU s:")
        if args.on_and_off:
            on_and_off(path, config, args.on_and_off, tmp_dir, args.seconds)
            return 0
        gc.disable()
        parts = stages(path, config, args.rounds)
        gc.enable()
        for name, t in parts:
            print(f"  {name:<28} {t:6.2f}")
        print(f"  {'sum of the parts':<28} {sum(t for _, t in parts[:-1]):6.2f}")

        def frames() -> int:
            link = MavlinkLink(config.link, log=io.StringIO())
            source = CompiledTlogSource([path], link, log=io.StringIO())
            return sum(f is not None for f in source.frames(Stop()))

        t_frames, n = _cpu(frames, args.rounds)
        t_all, one = _cpu(lambda: estimate_file(path, config, Path(tmp_dir) / "run"), args.rounds)
        row = one.summaries[0]
        print(
            "  the estimate's own clocks [s]: "
            + ", ".join(f"{k} {row[k]:.2f}" for k in ("seconds", "decode_s", "filter_s", "write_s"))
        )
        print(f"  {'decoding to frames':<28} {t_frames:6.2f} ({n} frames)")
        print(
            f"  {'the estimate':<28} {t_all:6.2f}: {args.seconds / t_all:.0f} flight-hours per "
            f"CPU-hour (target 200); the rest (filters, the structure check where the "
            f"run is within filter.structure_check_max_frames, writing) {t_all - t_frames:.2f}"
        )
        print(f"load average at the end {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
