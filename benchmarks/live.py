"""Live link: latency from packet arrival to updated estimate, and load with many vehicles.

    python benchmarks/live.py --vehicles 1 --seconds 30
    python benchmarks/live.py --vehicles 10 --seconds 30 [--view] [--repeat N] [--link-worker]
        [--filter-workers K]

The simulated vehicles fly in real time in their own process (`gcs-sim --vehicles N`),
streaming MAVLink 2 over UDP on loopback to one port; the ground station listens in this
process exactly as `gcs-estimator listen` does. For every frame it measures the time
from the kernel's arrival time of the packet that completed the frame (SO_TIMESTAMPNS:
time queued in the socket's buffer counts) to the end of both filters' update (and the
view's, with --view). Prints median, p99 and max latency per vehicle and overall (target
p99 <= 5 ms with 10 vehicles; p99 <= 20 ms and max <= 100 ms with 50), the station's CPU
time, the datagrams the kernel dropped for a full socket buffer, and frames received
against frames flown (target: none lost). link.max_vehicles is raised to the vehicles
flown. With --repeat N the flight is flown N times in a row into a new station each time
(this machine is shared and its speed varies between runs): the figures of every run, and
the worst of each. With --link-worker the link runs in a second process, as
`listen --link-worker` runs it (gcs_estimator/runtime/link_worker.py), and its CPU is printed
beside the station's. With --filter-workers K the vehicles' filters run in K processes, as
`listen --filter-workers K` runs them (gcs_estimator/runtime/filter_worker.py): the latency is
then to the moment both filters' outputs are back in the station, and the processes' CPU
is printed too.
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import record  # benchmarks/record.py: the script's directory is on sys.path
from speed import small_matrix_gflops

from gcs_estimator import blas
from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.estimation.estimator import FilterKind, StepOutput
from gcs_estimator.estimation.restarts import GRACE_PER_PEER
from gcs_estimator.frames import Frame
from gcs_estimator.ingest.sources import UdpSource, open_udp
from gcs_estimator.ingest.telemetry.link import MavlinkLink
from gcs_estimator.outputs.view.live import RerunView, ViewSink
from gcs_estimator.outputs.view.outlets import LocalOutlet
from gcs_estimator.runtime.decode_worker import LinkArgs
from gcs_estimator.runtime.filter_worker import ShardedSession
from gcs_estimator.runtime.link_worker import LiveJob, WorkerUdpSource
from gcs_estimator.runtime.session import Session, warm_up
from gcs_estimator.uncertainty.result import VehicleResult
from sim.cli import command as vehicle_command
from sim.scenario import scenario_of

ROOT = Path(__file__).resolve().parent.parent


class Latency:
    """A session sink that times each frame from the arrival of the packet that
    completed it (the kernel's time) to the end of every sink before it (both filters,
    the view), per vehicle."""

    def __init__(self) -> None:
        self.complete: dict[int, list[float]] = {}
        self.partial: list[float] = []
        self.flight_s: dict[int, list[float]] = {}
        """Each complete frame's time into its vehicle's flight [s] (where the slow
        frames were: at the restarts or elsewhere)."""
        self._t0: dict[int, float] = {}

    def on_frame(self, frame: Frame, outs: Mapping[FilterKind, StepOutput]) -> None:
        late = time.time() - frame.t_recv_s
        if np.all(np.isfinite(frame.y)):
            self.complete.setdefault(frame.system_id, []).append(late)
            t0 = self._t0.setdefault(frame.system_id, frame.t_vehicle_s)
            self.flight_s.setdefault(frame.system_id, []).append(frame.t_vehicle_s - t0)
        else:
            self.partial.append(late)

    def tick(self) -> None:
        pass

    def finish(self, results: Mapping[int, VehicleResult], link: Mapping[str, Any] | None) -> None:
        pass


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--vehicles", type=int, default=10)
    ap.add_argument("--seconds", type=float, default=30.0, help="flight duration")
    ap.add_argument("--config", default="noc_uav")
    ap.add_argument("--view", action="store_true", help="with the Rerun view saving an .rrd")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config")
    ap.add_argument(
        "--link-worker",
        action="store_true",
        help="the link in a second process, as `listen --link-worker` runs it",
    )
    ap.add_argument(
        "--filter-workers",
        type=int,
        default=0,
        metavar="K",
        help="the vehicles' filters in K processes, as `listen --filter-workers K` runs them",
    )
    ap.add_argument(
        "--repeat",
        type=int,
        default=1,
        help="runs in a row (the machine's noise shows between them); with more than one, "
        "a table over the runs and the worst of each figure",
    )
    record.add_argument(ap, "live")
    args = ap.parse_args(argv)
    if args.repeat < 1:
        ap.error(f"--repeat {args.repeat}: at least 1 run")
    blas.one_thread()  # as listen does (gcs_estimator/cli.py)
    with record.recorded("live", args.record, "Live link: latency and load on loopback UDP"):
        return run(args)


@dataclass(frozen=True)
class RunFigures:
    """What one run measured, for the table over repeated runs."""

    frames_lost: int
    socket_drops: int
    p99_ms: float
    max_ms: float
    station_cpu: float
    """The station's CPU time over the run's wall time (share of one core)."""
    link_cpu: float
    """Its link process's, with --link-worker (else 0)."""
    filters_cpu: float
    """Its filter processes', with --filter-workers (else 0)."""


def run(args: argparse.Namespace) -> int:
    override = f"simulation.manoeuvre.duration_s={args.seconds}"
    config = load_config(args.config, [override, *args.set])
    if config.link.max_vehicles < args.vehicles:  # every vehicle flown is estimated
        config = load_config(
            args.config, [override, f"link.max_vehicles={args.vehicles}", *args.set]
        )

    # The yardstick of this machine on the day: the speed records print it too, so
    # figures from different days can be compared.
    print(f"small-matrix rate of this machine: {small_matrix_gflops():.2f} GFLOP/s")
    ft = config.filter
    times = ", ".join(f"{t:g}" for t in ft.restart_times_s) or "none"
    print(
        f"restarts at {times} s; a re-run waits for idle time for {GRACE_PER_PEER} frames "
        "for each other vehicle restarting when it begins (restarts.GRACE_PER_PEER), then "
        f"steps at least {ft.restart_frames_per_step} frames per new frame "
        "(filter.restart_frames_per_step)"
    )
    warm_up(config)  # compiles the kernels before binding
    runs = []
    for k in range(args.repeat):
        if args.repeat > 1:
            print(f"\n### Run {k + 1} of {args.repeat}\n")
        runs.append(one_run(args, config, override, vehicle_table=args.repeat == 1))
    if args.repeat > 1:
        print(
            "\n### Over the runs\n\n| run | frames lost | socket drops | p99 ms | max ms | "
            "station CPU (one core) | link process CPU | filter processes CPU |\n"
            "|---|---|---|---|---|---|---|---|"
        )
        for k, r in enumerate(runs):
            print(
                f"| {k + 1} | {r.frames_lost} | {r.socket_drops} | {r.p99_ms:.3f} | "
                f"{r.max_ms:.3f} | {r.station_cpu:.0%} | {r.link_cpu:.0%} | "
                f"{r.filters_cpu:.0%} |"
            )
        print(
            f"\nworst of {len(runs)} runs: p99 {max(r.p99_ms for r in runs):.3f} ms, max "
            f"{max(r.max_ms for r in runs):.3f} ms, frames lost "
            f"{max(r.frames_lost for r in runs)}, socket drops "
            f"{max(r.socket_drops for r in runs)} ({_target(args.vehicles)})"
        )
    return 0


def one_run(
    args: argparse.Namespace, config: AircraftConfig, override: str, vehicle_table: bool
) -> RunFigures:
    """The simulated vehicles into a station on loopback once; its figures printed."""
    latency = Latency()
    session: Session | ShardedSession
    if args.filter_workers:
        session = ShardedSession(config, args.filter_workers, None)
        session.start()  # as listen does before it says it listens
    else:
        session = Session(config)
    link = MavlinkLink(config.link)
    with tempfile.TemporaryDirectory() as tmp:
        if args.view:
            view = RerunView([LocalOutlet("bench", save=Path(tmp) / "live.rrd")], config)
            session.add_sink(ViewSink(view, lambda: link.t_first_recv))
        session.add_sink(latency)  # after the view: the time includes its work
        sock = open_udp("127.0.0.1", 0)
        port = sock.getsockname()[1]
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        sim = subprocess.Popen(
            vehicle_command(args.config, f"127.0.0.1:{port}", 1.0, [override], args.vehicles),
            cwd=ROOT,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        start = time.time()
        cpu = time.process_time()
        source: UdpSource | WorkerUdpSource
        if args.link_worker:
            args_ = LinkArgs(link.config, link.linear_inputs, link.ranges)
            job = LiveJob(sock.fileno(), args_, None, None, 2.0, args.seconds * 3, None)
            source = WorkerUdpSource(sock, job, link)
        else:
            source = UdpSource(sock, link, idle_exit_s=2.0, max_seconds=args.seconds * 3)
        results = session.run(source)
        wall = time.time() - start
        cpu = time.process_time() - cpu
        dropped = source.link_stats()["dropped_by_this_machine"]  # ends the link worker
        link_cpu = source.worker_cpu_s if isinstance(source, WorkerUdpSource) else 0.0
        filters_cpu = session.workers_cpu_s if isinstance(session, ShardedSession) else 0.0
        sim.wait(timeout=30)
        used = resource.getrusage(resource.RUSAGE_CHILDREN)
        # The simulator: this process's children in the run but the link and filter workers.
        sim_cpu = used.ru_utime + used.ru_stime - before.ru_utime - before.ru_stime
        sim_cpu -= link_cpu + filters_cpu

    per_vehicle = round(args.seconds * scenario_of(config).sample_rate_hz) + 1
    flown = per_vehicle * args.vehicles
    got = sum(v.result.frames for v in results.values())
    by_vehicle = {sid: np.array(v) * 1e3 for sid, v in sorted(latency.complete.items())}
    lat = np.concatenate(list(by_vehicle.values())) if by_vehicle else np.zeros(0)
    partial = latency.partial
    h = link.health.total()
    worker = (
        f" and its link process {link_cpu:.1f} s ({link_cpu / wall:.0%})"
        if args.link_worker
        else ""
    )
    if args.filter_workers:
        worker += (
            f"{',' if worker else ''} and its {args.filter_workers} filter processes "
            f"{filters_cpu:.1f} s ({filters_cpu / wall:.0%})"
        )
    print(
        f"{args.vehicles} vehicle(s) x {args.seconds:.0f} s at the default rates on one port"
        f"{' with the view' if args.view else ''}: {h.received} packets in {wall:.1f} s; "
        f"the station used {cpu:.1f} s of CPU ({cpu / wall:.0%} of one core){worker}, the "
        f"simulated vehicles {sim_cpu:.1f} s ({sim_cpu / wall:.0%}), on {os.cpu_count()} cores"
    )
    print(
        f"frames: {got} of {flown} flown ({flown - got} lost); packets lost {h.lost} (of "
        f"them dropped by this machine's socket buffer: {dropped}), out of order "
        f"{h.out_of_order}, corrupt {h.corrupt}; partial frames {len(partial)}"
    )
    p99 = peak = math.nan
    if len(lat):
        p99, peak = float(np.percentile(lat, 99)), float(lat.max())
        print(
            f"latency, packet arrival (kernel time) -> both filters updated, over {len(lat)} "
            f"complete frames: median {np.median(lat):.3f} ms, p99 "
            f"{p99:.3f} ms, max {peak:.3f} ms ({_target(args.vehicles)})"
        )
        _slow_frames(lat, np.concatenate([latency.flight_s[sid] for sid in by_vehicle]))
        if vehicle_table:
            print("\n| vehicle | frames | median ms | p99 ms | max ms |\n|---|---|---|---|---|")
            for sid, v in by_vehicle.items():
                print(
                    f"| {sid} | {len(v)} | {np.median(v):.3f} | {np.percentile(v, 99):.3f} | "
                    f"{v.max():.3f} |"
                )
    return RunFigures(
        flown - got, int(dropped), p99, peak, cpu / wall, link_cpu / wall, filters_cpu / wall
    )


def _slow_frames(lat_ms: FloatArray, flight_s: FloatArray, over_ms: float = 20.0) -> None:
    """Where in the flights the frames slower than over_ms were: by whole second of
    each vehicle's flight, the seconds with most of them."""
    slow = lat_ms > over_ms
    if not slow.any():
        print(f"frames slower than {over_ms:g} ms: none")
        return
    seconds, counts = np.unique(np.floor(flight_s[slow]).astype(int), return_counts=True)
    top = np.argsort(counts)[::-1][:5]
    where = ", ".join(f"{seconds[i]}-{seconds[i] + 1} s: {counts[i]}" for i in sorted(top))
    print(
        f"frames slower than {over_ms:g} ms: {int(slow.sum())}, by second of their "
        f"vehicle's flight (the busiest): {where}"
    )


def _target(vehicles: int) -> str:
    if vehicles <= 10:
        return "target p99 <= 5 ms"
    return "target with 50 vehicles: p99 <= 20 ms, max <= 100 ms"


if __name__ == "__main__":
    sys.exit(main())
