"""Replay speed: a long simulated flight's .tlog through decode, sync and both filters.

    python benchmarks/replay.py --minutes 10 [--view]

Prints messages/s, frames/s and the multiple of real time (target >= 200x), for the
whole pipeline and for decoding alone; each timed --runs times, alternating, and given
as the best with the median beside it (this machine's speed swings between runs; a
swing only ever slows a run down). With --view it replays twice more with the Rerun
view saving an .rrd: once batched as a replay does (flush every wall-clock second), to
give the speed with the view and its cost next to the estimator (target >= 150x), and
once batched
as a live session does (a flush per second of flight), to give the recording size of a
live flight, scaled to one hour.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import record  # benchmarks/record.py: the script's directory is on sys.path
from flights import repeated_manoeuvre

from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.ingest.flightdata import Recording
from gcs_estimator.ingest.sources import TlogSource
from gcs_estimator.ingest.telemetry.link import MavlinkLink
from gcs_estimator.ingest.telemetry.mavlink import Decoder, read_tlog
from gcs_estimator.outputs.view.live import RerunView, ViewSink
from gcs_estimator.outputs.view.outlets import LocalOutlet
from gcs_estimator.runtime.decode_worker import WorkerTlogSource, tlog_source
from gcs_estimator.runtime.session import Session, warm_up
from sim.truth import simulate
from sim.vehicle import SimulatedVehicle


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--minutes", type=int, default=10)
    ap.add_argument("--config", default="noc_uav")
    ap.add_argument("--view", action="store_true", help="also time the Rerun view")
    ap.add_argument(
        "--runs",
        type=int,
        default=3,
        choices=range(1, 21),
        metavar="1..20",
        help="timings of each case (the best is given)",
    )
    ap.add_argument(
        "--boot-s",
        type=float,
        default=5.0,
        help="the vehicle's uptime at the start (over 4295 - flight: its 32-bit servo clock "
        "wraps during the flight)",
    )
    ap.add_argument(
        "--files",
        type=int,
        default=0,
        help="also replay this many copies of the flight as separate flights "
        "(`replay --each`), one at a time and then on all cores",
    )
    record.add_argument(ap, "replay")
    args = ap.parse_args(argv)
    with record.recorded("replay", args.record, "Replay: .tlog to estimates, as fast as possible"):
        return run(args)


def run(args: argparse.Namespace) -> int:
    seconds = args.minutes * 60
    config = load_config(args.config, repeated_manoeuvre(args.minutes))
    fl = simulate(config, seed=1)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "long.tlog"
        rec = Recording(fl.t_s, fl.inputs, fl.measurements, "throttle")
        SimulatedVehicle(
            rec, config.link, ("127.0.0.1", 9), speed=0.0, tlog=path, boot_s=args.boot_s
        ).run()
        records = list(read_tlog(path))
        n = len(records)

        dec = Decoder()
        t_decode = []
        for _ in range(args.runs):
            t0 = time.perf_counter()
            for r in records:
                dec.decode(r.packet)
            t_decode.append(time.perf_counter() - t0)

        warm_up(config)  # kernels compiled here, outside the timing
        t_one, t_all, t_view = [], [], []
        for _ in range(args.runs):
            t_one.append(_timed_replay(config, path, workers=False)[0])
            t, results, link_stats = _timed_replay(config, path, workers=True)
            t_all.append(t)
            if args.view:
                t, size = replay_with_view(config, path, Path(tmp) / "replay.rrd", live=False)
                t_view.append(t)

        base_mb, replay_mb, worker_mb, worker_peak_mb = _in_child(_replay_memory, config, path)
        if args.view:
            _, size_live = replay_with_view(config, path, Path(tmp) / "live.rrd", live=True)
        if args.files > 0:
            batch = _batches(args, path, Path(tmp))
    frames = results[1].result.frames
    print(f"flight {seconds:.0f} s, {n} packets, {frames} frames (both filters each frame)")
    clock = link_stats["vehicles"]["1"]
    print(
        f"vehicle clock: boot {args.boot_s:g} s, {clock['clock_wraps']} wraps, "
        f"{clock['clock_resets']} resets, {clock['time_jumps']} jumps; "
        f"{len(fl.t_s) - frames} of {len(fl.t_s)} frames missing; "
        f"IEKF {results[1].result.filters['IEKF'].health.divergences} divergences"
    )
    one, full = min(t_one), min(t_all)
    print(f"timings     : best of {args.runs} runs each (median in brackets)")
    print(f"decode only : {n / min(t_decode):,.0f} messages/s ({n / _median(t_decode):,.0f})")
    print(
        f"one process : {one:.2f} s ({_median(t_one):.2f}), {n / one:,.0f} messages/s, "
        f"{frames / one:,.0f} frames/s, {seconds / one:.0f}x real time "
        f"({seconds / _median(t_one):.0f}x)"
    )
    print(
        f"full replay : {full:.2f} s ({_median(t_all):.2f}), {n / full:,.0f} messages/s, "
        f"{frames / full:,.0f} frames/s, {seconds / full:.0f}x real time "
        f"({seconds / _median(t_all):.0f}x; target >= 200x; decoding in a worker process, "
        f"{os.cpu_count()} cores)"
    )
    hours = seconds / 3600
    growth = (replay_mb - base_mb) + (worker_peak_mb - worker_mb)
    print(
        f"memory      : resident {base_mb:.0f} MB with the kernels loaded, at most "
        f"{replay_mb:.0f} MB replaying (every history kept; the end reads it all); "
        f"decoding worker {worker_mb:.0f} MB started, at most {worker_peak_mb:.0f} MB: "
        f"{growth / hours:.0f} MB per vehicle-hour above the bases (target <= 50)"
    )
    if args.view:
        view = min(t_view)
        print(
            f"with view   : {view:.2f} s ({_median(t_view):.2f}), {seconds / view:.0f}x real "
            f"time ({seconds / _median(t_view):.0f}x), {100 * (view / full - 1):+.1f} % against "
            f"no view (target >= 150x); .rrd {size / 1e6:.1f} MB"
        )
        hour = size_live * 3600 / seconds
        print(
            f"live chunks : .rrd {size_live / 1e6:.1f} MB for {seconds:.0f} s "
            f"-> {hour / 1e6:.0f} MB per hour of flight"
        )
    if args.files > 0:
        for jobs, wall in batch:
            print(
                f"{args.files} files, {jobs} at a time: {wall:.2f} s for "
                f"{args.files * seconds / 60:.0f} min of flight, "
                f"{args.files * seconds / wall:.0f}x real time (`replay --each --jobs {jobs}`,"
                " the command line's own start-up included)"
            )
    return 0


def _median(values: list[float]) -> float:
    return float(sorted(values)[len(values) // 2])


def _batches(args: argparse.Namespace, tlog: Path, tmp: Path) -> list[tuple[int, float]]:
    """(jobs, wall-clock seconds) of `replay --each` over args.files copies of the tlog,
    one at a time and on every core."""
    import shutil
    import subprocess

    copies = []
    for k in range(args.files):
        copies.append(tmp / f"copy{k}" / "flight.tlog")
        copies[-1].parent.mkdir()
        shutil.copy(tlog, copies[-1])
    out = []
    for jobs in sorted({1, os.cpu_count() or 1}):
        cmd = [sys.executable, "-m", "gcs_estimator", "replay", "--each", "--jobs", str(jobs),
               *map(str, copies), "--config", args.config, "--view", "off",
               "--out", str(tmp / f"each{jobs}")]  # fmt: skip
        for item in repeated_manoeuvre(args.minutes):
            cmd += ["--set", item]
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, capture_output=True)
        out.append((jobs, time.perf_counter() - t0))
    return out


def _timed_replay(
    config: AircraftConfig, tlog: Path, workers: bool
) -> tuple[float, dict[int, Any], dict[str, Any]]:
    """(wall-clock seconds, results, link counters) of a replay with no output."""
    session = Session(config)
    source = (WorkerTlogSource if workers else TlogSource)([tlog], MavlinkLink(config.link))
    t0 = time.perf_counter()
    results = session.run(source)
    return time.perf_counter() - t0, results, source.link_stats()


def _rss_mb(pid: int | str = "self") -> float:
    """Resident memory of a process now [MB] (Linux /proc); 0 once it has gone."""
    try:
        pages = int(Path(f"/proc/{pid}/statm").read_text().split()[1])
    except (OSError, ValueError):
        return 0.0
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


def _children() -> list[int]:
    """Process ids of this process's children (the decoding worker)."""
    out = []
    for task in Path("/proc/self/task").iterdir():
        with contextlib.suppress(OSError):
            out += [int(p) for p in (task / "children").read_text().split()]
    return out


def _replay_memory(config: AircraftConfig, tlog: Path) -> tuple[float, ...]:
    """Resident memory [MB], sampled every 20 ms in a fresh process (the compilers' own
    peak at warm-up is not the replay's): this process with the kernels loaded and at
    most while replaying the tlog and writing nothing; the decoding worker once it has
    started (the median over the third tenth of its life, its imports long done) and at
    most."""
    import threading

    warm_up(config)
    base = _rss_mb()
    peak = [base]
    worker: list[float] = []
    done = threading.Event()

    def sample() -> None:
        while not done.wait(0.02):
            peak[0] = max(peak[0], _rss_mb())
            worker.extend(m for m in (_rss_mb(pid) for pid in _children()) if m > 0)

    sampler = threading.Thread(target=sample)
    sampler.start()
    session = Session(config)
    session.run(tlog_source([tlog], MavlinkLink(config.link)))
    session.results()  # the end of a run reads every history
    peak[0] = max(peak[0], _rss_mb())
    done.set()
    sampler.join()
    n = len(worker)
    settled = sorted(worker[n // 5 : max(n // 5 + 1, 3 * n // 10)])
    return base, peak[0], settled[len(settled) // 2], max(worker)


def _in_child(fn: Callable[..., tuple[float, ...]], *args: Any) -> tuple[float, ...]:
    """fn(*args) in a fresh process (its own memory)."""
    import multiprocessing

    with multiprocessing.get_context("spawn").Pool(1) as pool:
        out: tuple[float, ...] = pool.apply(fn, args)
        return out


def replay_with_view(
    config: AircraftConfig, tlog: Path, path: Path, live: bool
) -> tuple[float, int]:
    """Replay with the view saving to path; live=True flushes once per second of receive
    time, as a live session at real time does (in one process: a worker's link clock
    reaches this process a batch at a time). Returns (seconds, file size)."""
    session = Session(config)
    link = MavlinkLink(config.link)
    clock = (lambda: link.t_last_recv) if live else time.monotonic
    view = RerunView(
        [LocalOutlet("bench", save=path)],
        config,
        link_source=lambda: (link.session_time(), link.health.as_dict()),
        clock=clock,
    )
    session.add_sink(ViewSink(view, lambda: link.t_first_recv))
    t0 = time.perf_counter()
    session.run(TlogSource([tlog], link) if live else WorkerTlogSource([tlog], link))
    elapsed = time.perf_counter() - t0
    return elapsed, path.stat().st_size


if __name__ == "__main__":
    sys.exit(main())
