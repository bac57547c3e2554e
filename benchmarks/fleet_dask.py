"""A fleet's logs through `batch` on Dask: speed, scheduler overhead, history size, trend.

    python benchmarks/fleet_dask.py [--flights 100] [--vehicles 3] [--seconds 180]

Simulates --flights short flights (.tlog, the NOC UAV) of --vehicles vehicles, each
known by its own autopilot UID (an AUTOPILOT_VERSION record first in its logs): vehicle
1 flies every other flight (50 of 100) and its true CD0 drifts by --drift (5 %) from its
first flight to its last; the others fly the rest in turn and their CD0 stays.
Then `gcs-estimator batch` over them (both filters, no refine):

- embedded, 1 worker and 2 workers: logs per minute, flight-hours per CPU-hour (CPU:
  workers x the wall-clock time from the first log submitted to the last done), the
  share of the tasks' time spent decoding, filtering and writing (target: 2 workers
  >= 1.8x 1 worker; >= 200 flight-hours per CPU-hour);
- through a separate scheduler process and two worker processes (`dask scheduler`,
  `dask worker`): the same figures;
- by CPU time (decision 0058: on a loaded machine the wall-clock figures count other
  processes' turns): each batch's flight-hours per CPU-hour charged to all its processes
  (start-up included), and one log estimated in this process as a task does it (the
  target's figure, the steady state), with and without the structure check;
- logs past filter.structure_check_max_frames (--long-seconds, 600: ten minutes at
  50 Hz), as most of a fleet's logs are, where the check is not made: one by CPU, and
  --long-flights (20) of them through a batch on 2 workers (decision 0070);
- the scheduler's overhead per task: (workers x wall - the tasks' own time) / logs
  (target <= 0.3 s; the tail, one worker finishing while the other waits, included);
- identical estimates: --check logs replayed alone (`gcs-estimator replay`) against
  their rows of the table;
- history size per vehicle-hour, Parquet (the batch's) against the CSV of the same log
  (target: at most a fifth);
- decoding alone (decision 0055), the compiled tlog reader against the record-by-record
  one, runs interleaved on the same logs (the machine's state the same for both):
  packets per second through the link to frames, and of reading alone (framing, CRC,
  the channel messages' fields); --reader python runs the batches with the latter;
- the trend: vehicle 1's CD0 flagged (drift), the others' not. CD0's sigma is about 4 %
  after a 60 s flight: a 5 % drift over 50 such flights is within the scatter (t = 3.0
  measured, 3.5 needed); the default 3 minutes (sigma about 2.3 %) is where the sigmas
  allow it.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import record  # benchmarks/record.py: the script's directory is on sys.path
from flights import repeated_manoeuvre

from gcs_estimator.config import load_config
from gcs_estimator.ingest.flightdata import Recording
from gcs_estimator.ingest.sources import TlogSource
from gcs_estimator.ingest.telemetry.decode import DecodeStats, SampleReader, ranges_of
from gcs_estimator.ingest.telemetry.link import MavlinkLink
from gcs_estimator.ingest.telemetry.mavlink import Codec, TlogStats, read_tlog, tlog_record
from gcs_estimator.ingest.telemetry.tlog_fast import (
    READER_VARIABLE,
    CompiledTlogSource,
    read_runs,
    table_of,
    warm_up,
)
from gcs_estimator.outputs.trend import charts
from gcs_estimator.runtime.logs import estimate_file
from gcs_estimator.stop import Stop
from gcs_estimator.uncertainty import weighting
from sim.truth import simulate
from sim.vehicle import SimulatedVehicle

ROOT = Path(__file__).resolve().parent.parent
UID_BASE = 0x1000
"""Vehicle k's autopilot UID is UID_BASE + k."""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--flights", type=int, default=100)
    ap.add_argument("--vehicles", type=int, default=3)
    ap.add_argument(
        "--seconds",
        type=float,
        default=180.0,
        help="each flight's length (whole minutes: the manoeuvre once a minute)",
    )
    ap.add_argument("--drift", type=float, default=0.05, help="vehicle 1's CD0 change")
    ap.add_argument("--check", type=int, default=3, help="logs compared with their replay")
    ap.add_argument("--no-external", action="store_true", help="skip the separate scheduler's run")
    ap.add_argument(
        "--trend-only",
        action="store_true",
        help="only the 2-worker batch: estimates, history size and the trend",
    )
    ap.add_argument("--keep", default=None, help="copy the 2-worker batch's tables here")
    ap.add_argument(
        "--reader",
        choices=("compiled", "python"),
        default="compiled",
        help="the batches' tlog reader (GCS_ESTIMATOR_TLOG_READER)",
    )
    ap.add_argument("--decode-rounds", type=int, default=3, help="interleaved runs of each reader")
    ap.add_argument(
        "--long-flights",
        type=int,
        default=20,
        help="a batch of this many --long-seconds logs on 2 workers as well (0: not)",
    )
    ap.add_argument(
        "--long-seconds",
        type=float,
        default=600.0,
        help="one log this long measured by CPU as well, with the default settings (0: "
        "not): a log over filter.structure_check_max_frames frames, as most of a fleet's "
        "are, is not checked (the regime of the issue's 136 flight-hours per CPU-hour)",
    )
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a config override for the batches and their replays (e.g. "
        "filter.structure_check=off: the check's replays run in threads, so one worker "
        "already uses every core, decision 0067)",
    )
    record.add_argument(ap, "fleet_dask")
    args = ap.parse_args(argv)
    os.environ[READER_VARIABLE] = args.reader  # the batches' and estimate_file's
    with record.recorded("fleet_dask", args.record, "Fleet: a batch of logs on Dask"):
        return run(args)


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _replayed(source_class: Any, path: Path, config: Any) -> tuple[int, float]:
    """(records, seconds) of one log through a tlog source and a link to frames."""
    link = MavlinkLink(config.link, log=io.StringIO(), ranges=ranges_of(config.data))
    source = source_class([path], link, log=io.StringIO())
    t0 = time.perf_counter()
    for _ in source.frames(Stop()):
        pass
    return source.done, time.perf_counter() - t0


def _read(path: Path, config: Any, compiled: bool) -> tuple[int, float]:
    """(records, seconds) of reading alone: records framed, channel messages' fields."""
    t0 = time.perf_counter()
    n = 0
    if compiled:
        for run in read_runs(path, TlogStats(), table_of(config.link)):
            n += len(run.status)
    else:
        reader = SampleReader(config.link, DecodeStats())
        for rec in read_tlog(path):
            reader(rec.packet, rec.t_recv_us * 1e-6)
            n += 1
    return n, time.perf_counter() - t0


def decode_rates(args: argparse.Namespace, paths: list[Path]) -> None:
    """Packets per second of decoding alone, each reader's runs interleaved with the
    other's on the same logs; the median of --decode-rounds."""
    config = load_config("noc_uav", _overrides(args.seconds))
    logs = paths[:2]
    warm_up()
    rates: dict[str, list[float]] = {}
    for _ in range(args.decode_rounds):
        for name, source, compiled in (
            ("python, to frames", TlogSource, False),
            ("compiled, to frames", CompiledTlogSource, True),
            ("python, reading", None, False),
            ("compiled, reading", None, True),
        ):
            got = [
                _replayed(source, p, config) if source else _read(p, config, compiled) for p in logs
            ]
            rates.setdefault(name, []).append(sum(n for n, _ in got) / sum(t for _, t in got))
    med = {k: float(np.median(v)) for k, v in rates.items()}
    for what in ("to frames", "reading"):
        py, comp = med[f"python, {what}"], med[f"compiled, {what}"]
        print(
            f"decode alone: {what:<9}: python {py:,.0f} packets/s, compiled {comp:,.0f} "
            f"packets/s: {comp / py:.2f}x (median of {args.decode_rounds} interleaved runs "
            f"over {len(logs)} logs)"
        )


def _overrides(seconds: float) -> list[str]:
    """A flight of whole minutes flies the manoeuvre once a minute; else once."""
    if seconds >= 60 and seconds % 60 == 0:
        return repeated_manoeuvre(int(seconds // 60))
    return [f"simulation.manoeuvre.duration_s={seconds}"]


def make_flights(args: argparse.Namespace, folder: Path) -> list[Path]:
    """The flights, vehicle by vehicle in turn; vehicle 1's CD0 drifting."""
    config = load_config("noc_uav", _overrides(args.seconds))
    assert config.truth is not None
    names = config.coefficient_names
    paths = []
    owner = [_vehicle_of(k, args.vehicles) for k in range(args.flights)]
    per_vehicle = [0] * args.vehicles
    flights_of = [owner.count(v) for v in range(args.vehicles)]
    for k, v in enumerate(owner):
        truth = np.array(config.truth, float)
        if v == 0:
            share = per_vehicle[v] / max(flights_of[v] - 1, 1)
            truth[names.index("CD0")] *= 1 + args.drift * share
        per_vehicle[v] += 1
        path = folder / f"v{v + 1}_{per_vehicle[v]:03d}.tlog"
        write_flight(config, path, 100 + k, truth)
        _with_uid(path, UID_BASE + v + 1)
        paths.append(path)
    return paths


def write_flight(config: Any, path: Path, seed: int, truth: Any = None) -> None:
    """One simulated flight of the config's aircraft written as a .tlog (the simulator's
    own message set, as fast as it goes): the log the fleet and speed benchmarks read."""
    fl = simulate(config, seed=seed, truth=truth)
    rec = Recording(fl.t_s, fl.inputs, fl.measurements, "throttle")
    SimulatedVehicle(rec, config.link, ("127.0.0.1", 9), speed=0.0, tlog=path).run()


def _vehicle_of(k: int, vehicles: int) -> int:
    """Vehicle 1 (index 0) flies every other flight, the others the rest in turn."""
    if vehicles == 1 or k % 2 == 0:
        return 0
    return 1 + (k // 2) % (vehicles - 1)


def _with_uid(path: Path, uid: int) -> None:
    """The log with the autopilot's AUTOPILOT_VERSION (its UID) as its first record."""
    codec = Codec(1, 1)
    z = [0] * 8
    msg = codec.mav.autopilot_version_encode(0, 0, 0, 0, 0, z, z, z, 0, 0, uid)
    data = path.read_bytes()
    path.write_bytes(tlog_record(int.from_bytes(data[:8], "big"), codec.pack(msg)) + data)


def batch(
    args: argparse.Namespace, logs: Path, out: Path, where: list[str], seconds: float = 0.0
) -> dict[str, Any]:
    """One `batch` run (of flights `seconds` long; default --seconds): its wall-clock
    time over the tasks and its tables."""
    cmd = [sys.executable, "-m", "gcs_estimator", "batch", str(logs), "--config", "noc_uav",
           "--out", str(out), "--view", "off", "--no-trend", *where]  # fmt: skip
    for item in _overrides(seconds or args.seconds) + args.set:
        cmd += ["--set", item]
    t0, cpu0 = time.perf_counter(), _children_cpu()
    done = subprocess.run(cmd, env=_env(), capture_output=True, text=True)
    total = time.perf_counter() - t0
    cpu = _children_cpu() - cpu0
    if done.returncode != 0:
        raise SystemExit(f"batch failed ({done.returncode}):\n{done.stderr[-3000:]}")
    found = re.search(r"ran (\d+) logs in ([\d.]+) s", done.stderr)
    assert found, done.stderr
    return {
        "wall": float(found[2]),
        "total": total,
        "cpu": cpu,
        "flights": pq.read_table(out / "flights.parquet").to_pylist(),
        "rows": pq.read_table(out / "coefficients.parquet").to_pylist(),
    }


def _children_cpu() -> float:
    """CPU seconds charged to this process's children that have ended (and to theirs
    they waited for): a batch's client, scheduler and workers."""
    used = resource.getrusage(resource.RUSAGE_CHILDREN)
    return used.ru_utime + used.ru_stime


def figures(label: str, workers: int, run: dict[str, Any]) -> float:
    """Print one run's figures; return its logs per minute."""
    flights = run["flights"]
    n = len(flights)
    wall = float(run["wall"])
    task = sum(f["seconds"] for f in flights)
    hours = sum(f["flight_s"] for f in flights) / 3600
    per_min = 60 * n / wall
    cpu_h = workers * wall / 3600
    shares = {k: sum(f[k] for f in flights) / task for k in ("decode_s", "filter_s", "write_s")}
    overhead = (workers * wall - task) / n
    print(
        f"{label:<24}: {n} logs in {wall:.1f} s ({run['total']:.1f} s with start-up): "
        f"{per_min:.1f} logs/min, {hours / cpu_h:.0f} flight-hours per CPU-hour "
        f"({hours / (task / 3600):.0f} per task-hour); overhead {overhead:.2f} s per task; "
        f"decode {100 * shares['decode_s']:.0f} %, filter {100 * shares['filter_s']:.0f} %, "
        f"write {100 * shares['write_s']:.0f} %"
    )
    if "cpu" in run:
        print(
            f"{'':<24}  by CPU time charged: {run['cpu']:.1f} s, {hours / (run['cpu'] / 3600):.0f} "
            "flight-hours per CPU-hour (every process of the batch, start-up included)"
        )
    return per_min


def cpu_per_log(args: argparse.Namespace, paths: list[Path], tmp: Path) -> None:
    """One log estimated as a batch's task does (estimate_file: both filters, its history
    written), by the CPU time charged to this process: the figure a loaded machine
    leaves meaningful (wall-clock ones count the other processes' turns). The median of
    --decode-rounds after one warm-up run; the parts' shares by the run's own clocks
    (decode_s, filter_s, write_s: wall-clock, the load spread over all three alike).
    Then the same log with the structure check off: a run of at most
    filter.structure_check_max_frames frames replays its final pass once per channel and
    per undecided quantity (decision 0047), which on a short log is most of its CPU."""
    overrides = _overrides(args.seconds)
    for label, extra in (("", []), (", structure check off", ["filter.structure_check=off"])):
        config = load_config("noc_uav", overrides + extra)
        _print_cpu(args, label, args.seconds, *_median_cpu(args, config, paths[0], tmp))
    if args.long_seconds > 0:
        config = load_config("noc_uav", _overrides(args.long_seconds))
        path = tmp / "long.tlog"
        write_flight(config, path, 99)
        cpu, shares, checked = _median_cpu(args, config, path, tmp)
        _print_cpu(args, ", a long log", args.long_seconds, cpu, shares, checked)


def long_batch(args: argparse.Namespace, tmp: Path) -> None:
    """--long-flights logs of --long-seconds through `batch` on 2 workers: the batch's
    figures where, as in most of a fleet's logs, the structure check is not made."""
    if args.long_seconds <= 0 or args.long_flights <= 0:
        return
    config = load_config("noc_uav", _overrides(args.long_seconds))
    logs = tmp / "long_logs"
    logs.mkdir()
    for k in range(args.long_flights):
        write_flight(config, logs / f"long_{k + 1:02d}.tlog", 200 + k)
    run = batch(args, logs, tmp / "long_batch", ["--workers", "2"], args.long_seconds)
    label = "long logs, 2 workers"
    figures(label, 2, run)


def _print_cpu(
    args: argparse.Namespace,
    label: str,
    seconds: float,
    cpu: float,
    shares: dict[str, float],
    checked: str,
) -> None:
    print(
        f"one log, CPU{label}: {seconds:g} s flight in {cpu:.2f} s CPU: "
        f"{seconds / cpu:.0f} flight-hours per CPU-hour (target 200; median of "
        f"{args.decode_rounds}); the parts' shares of its wall-clock time: decode "
        f"{100 * shares['decode_s']:.0f} %, filter (the structure check's replays in it) "
        f"{100 * shares['filter_s']:.0f} %, write {100 * shares['write_s']:.0f} %; "
        f"structure check: {checked}"
    )


def _median_cpu(
    args: argparse.Namespace, config: Any, path: Path, tmp: Path
) -> tuple[float, dict[str, float], str]:
    """The median CPU time of --decode-rounds estimates of one log, its parts' shares,
    and whether its structure check was made ("made", or why not). As a batch's task
    runs it: the check's replays in this thread (fleet.run_log)."""
    with weighting.replay_threads(1):
        estimate_file(path, config, tmp / "cpu_warm")  # kernels loaded, first-use costs paid
        runs = []
        for k in range(args.decode_rounds):
            c0 = time.process_time()
            out = estimate_file(path, config, tmp / f"cpu_{k}")
            cpu = time.process_time() - c0
            row = out.summaries[0]
            wall = sum(row[p] for p in ("decode_s", "filter_s", "write_s")) or 1.0
            runs.append((cpu, {p: row[p] / wall for p in ("decode_s", "filter_s", "write_s")}))
    cpu, shares = sorted(runs, key=lambda r: r[0])[len(runs) // 2]
    results = json.loads(next((tmp / "cpu_0").glob("results_sys*.json")).read_text())
    skipped = results["diagnostics"]["structure_check"].get("skipped", "")
    return cpu, shares, f"not made ({skipped})" if skipped else "made"


def external(args: argparse.Namespace, logs: Path, tmp: Path) -> dict[str, Any]:
    """The batch through a scheduler process and two worker processes."""
    import importlib

    client_class: Any = importlib.import_module("distributed").Client
    file = tmp / "scheduler.json"
    py = [sys.executable, "-m"]
    cpu0 = _children_cpu()
    procs = [
        subprocess.Popen(
            [*py, "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0",
             "--dashboard-address", "127.0.0.1:0", "--scheduler-file", str(file)],
            env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )
    ]  # fmt: skip
    try:
        while not file.exists():
            if procs[0].poll() is not None:
                raise SystemExit("the scheduler did not start")
            time.sleep(0.05)
        for _ in range(2):
            procs.append(
                subprocess.Popen(
                    [*py, "distributed.cli.dask_worker", "--scheduler-file", str(file),
                     "--nthreads", "1", "--host", "127.0.0.1", "--no-dashboard"],
                    env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                )
            )  # fmt: skip
        with client_class(scheduler_file=str(file), timeout="60s") as client:
            client.wait_for_workers(2, timeout=300)
        run = batch(args, logs, tmp / "external", ["--scheduler-file", str(file)])
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            p.wait(timeout=60)
    run["cpu"] = _children_cpu() - cpu0  # the client's, the scheduler's, the workers'
    return run


def same_as_replay(
    args: argparse.Namespace, run: dict[str, Any], logs: list[Path], tmp: Path
) -> str:
    """Whether --check logs' rows equal their replay alone."""
    same = 0
    for path in logs[: args.check]:
        out = tmp / f"replay_{path.stem}"
        cmd = [sys.executable, "-m", "gcs_estimator", "replay", str(path), "--config", "noc_uav",
               "--out", str(out), "--view", "off"]  # fmt: skip
        for item in _overrides(args.seconds) + args.set:
            cmd += ["--set", item]
        subprocess.run(cmd, env=_env(), capture_output=True, check=True)
        own = json.loads((out / "results_sys1.json").read_text())
        expected = {
            (k, n): c["estimate"]
            for k, f in own["filters"].items()
            for n, c in f["estimates"].items()
        }
        mine = {
            (r["filter"], r["coefficient"]): r["estimate"]
            for r in run["rows"]
            if r["log"] == str(path)
        }
        same += mine == expected
    return f"{same} of {min(args.check, len(logs))} logs identical to their replay alone"


def history_sizes(args: argparse.Namespace, run: dict[str, Any], log: Path, tmp: Path) -> None:
    """History bytes per vehicle-hour: the batch's Parquet files, and the CSV of one log."""
    parquet = sum(
        Path(f["folder"], "results_sys1_history.parquet").stat().st_size for f in run["flights"]
    )
    hours = sum(f["flight_s"] for f in run["flights"]) / 3600
    config = load_config("noc_uav", _overrides(args.seconds))
    for fmt in ("parquet", "csv"):
        estimate_file(log, config, tmp / f"one_{fmt}", history_format=fmt)
    one = {
        fmt: (tmp / f"one_{fmt}" / f"results_sys1_history.{fmt}").stat().st_size
        for fmt in ("parquet", "csv")
    }
    print(
        f"history     : Parquet {parquet / hours / 1e6:.0f} MB per vehicle-hour; on one log "
        f"Parquet {one['parquet'] / 1e3:.0f} kB against CSV {one['csv'] / 1e3:.0f} kB: "
        f"{one['parquet'] / one['csv']:.3f} of the CSV (target <= 0.2)"
    )


def trend(run: dict[str, Any], vehicles: int) -> None:
    found = [c for c in charts(run["rows"]) if c.coefficient == "CD0"]
    for c in found:
        rel = float(np.median(c.sigma / np.abs(c.estimate)))
        change = c.slope * (len(c.estimate) - 1) / abs(c.centre) if c.centre else float("nan")
        print(
            f"trend {c.vehicle}: CD0 over {len(c.estimate)} flights, sigma {100 * rel:.1f} % "
            f"per flight, fitted change {100 * change:+.1f} %, drift z {c.drift_z:+.2f}: "
            f"{'FLAGGED' if c.flagged else 'not flagged'}"
        )
    drifting = f"uid:{UID_BASE + 1:016x}"  # vehicle 1
    others = [c for c in charts(run["rows"]) if c.vehicle != drifting]
    print(
        f"trend       : other vehicles' charts flagged: {sum(c.flagged for c in others)} of "
        f"{len(others)} (target 0); vehicle 1's CD0 drifted, the rest did not"
    )
    flagged = [f"{c.vehicle} {c.coefficient}" for c in charts(run["rows"]) if c.flagged]
    print(f"trend       : every chart flagged: {', '.join(flagged) or 'none'}")


def run(args: argparse.Namespace) -> int:
    load = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp_dir:
        tmp = Path(tmp_dir)
        logs = tmp / "logs"
        logs.mkdir()
        t0 = time.perf_counter()
        paths = make_flights(args, logs)
        print(
            f"{args.flights} flights of {args.seconds:g} s, {args.vehicles} vehicles (vehicle 1's "
            f"CD0 +{100 * args.drift:g} % over its flights), simulated in "
            f"{time.perf_counter() - t0:.0f} s; load average {load[0]:.1f} at the start, "
            f"{os.cpu_count()} cores"
        )
        decode_rates(args, paths)
        cpu_per_log(args, paths, tmp)
        print(f"batches     : the {args.reader} tlog reader")
        two = batch(args, logs, tmp / "two", ["--workers", "2"])
        rate2 = figures("embedded, 2 workers", 2, two)
        if args.keep:
            import shutil

            Path(args.keep).mkdir(parents=True, exist_ok=True)
            for name in ("coefficients.parquet", "flights.parquet"):
                shutil.copy(tmp / "two" / name, Path(args.keep) / name)
        if not args.trend_only:
            one = batch(args, logs, tmp / "one", ["--workers", "1"])
            rate1 = figures("embedded, 1 worker", 1, one)
            print(f"speed-up    : 2 workers {rate2 / rate1:.2f}x 1 worker (target >= 1.8)")
            same = [r["estimate"] for r in one["rows"]] == [r["estimate"] for r in two["rows"]]
            print(f"estimates   : 1 and 2 workers {'identical' if same else 'DIFFER'}")
        if not args.trend_only:
            long_batch(args, tmp)
        if not (args.no_external or args.trend_only):
            ext = external(args, logs, tmp)
            figures("scheduler process, 2 w.", 2, ext)
        print(f"estimates   : {same_as_replay(args, two, paths, tmp)}")
        history_sizes(args, two, paths[0], tmp)
        trend(two, args.vehicles)
        print(f"load average at the end {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
