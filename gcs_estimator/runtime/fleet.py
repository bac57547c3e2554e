"""A fleet's logs on Dask: `gcs-estimator batch LOGS...` (decision 0042).

Every log is a task that runs logs.estimate_file on a Dask worker, as `replay` or
`offline` would run it alone. The cluster is an embedded LocalCluster (one worker
process per core, one thread each) unless the command line names a scheduler
(--scheduler tcp://HOST:PORT, --scheduler-file FILE) or the environment does
(DASK_SCHEDULER_ADDRESS, Dask's own convention). On a cluster, the logs and --out must
be paths every worker can reach (a shared file system), and the workers must have
gcs-estimator installed.

A log that fails (unreadable, nothing estimated, over --timeout) is a failed row; an
exception on a worker is retried --retries times; a worker that dies has its tasks run
on another by the scheduler. Each finished log is appended to OUT/done.jsonl at once, so
a batch that is stopped or killed keeps what it did, and `--resume` skips the logs whose
(log hash, config hash) are there already. At the end: OUT/coefficients.parquet,
OUT/flights.parquet (outputs/tables.py) and the trend of each vehicle (outputs/trend.py).
"""

from __future__ import annotations

import argparse
import fnmatch
import glob
import json
import math
import os
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any, TextIO

from gcs_estimator import blas
from gcs_estimator.config import AircraftConfig, ConfigError, load_config
from gcs_estimator.outputs.tables import (
    COEFFICIENT_COLUMNS,
    SUMMARY_COLUMNS,
    failed_row,
    read_rows,
    write_table,
)
from gcs_estimator.outputs.trend import write_trend
from gcs_estimator.runtime import options
from gcs_estimator.runtime.batch import folders
from gcs_estimator.runtime.logs import (
    LOG_SUFFIXES,
    LogOutcome,
    config_sha256,
    estimate_file,
    sha256_of,
    version,
)
from gcs_estimator.stop import PROCESS_STOP, Stop
from gcs_estimator.uncertainty import weighting

DONE_FILE = "done.jsonl"
COEFFICIENTS_FILE = "coefficients.parquet"
FLIGHTS_FILE = "flights.parquet"
LOGS_FOLDER = "logs"
POLL_S = 0.02
"""How often the batch looks for finished logs and a stop request [s]."""
SCHEDULER_VARIABLE = "DASK_SCHEDULER_ADDRESS"


def find_logs(paths: Sequence[str]) -> list[Path]:
    """The logs named: files as given, a folder as the logs in it and below (by
    LOG_SUFFIXES, in name order), a glob pattern as its matches; a name that matches
    nothing is refused."""
    out: list[Path] = []
    for text in paths:
        p = Path(text)
        if p.is_dir():
            found = sorted(f for f in p.rglob("*") if f.is_file() and _is_log(f))
            if not found:
                raise ConfigError(f"{text}: a folder with no log in it ({', '.join(LOG_SUFFIXES)})")
            out += found
        elif p.is_file():
            out.append(p)
        elif glob.has_magic(text):
            found = sorted(Path(f) for f in glob.glob(text, recursive=True) if Path(f).is_file())
            if not found:
                raise ConfigError(f"{text}: the pattern matches no file")
            out += found
        else:
            raise ConfigError(f"{text}: no such file or folder")
    return list(dict.fromkeys(out))


def _is_log(path: Path) -> bool:
    return path.suffix.lower() in LOG_SUFFIXES


def load_vehicle_map(path: str | None) -> dict[str, str]:
    """A vehicle map: a TOML file whose [vehicles] table names vehicles by a log path
    pattern ("logs/plane_a/*.tlog" = "plane A") or by an identity the logs give
    ("uid:0123abcd..." or "sys3" = "plane B")."""
    if path is None:
        return {}
    import tomllib

    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"--vehicle-map {path}: {exc}") from exc
    table = data.get("vehicles")
    if not isinstance(table, dict) or not all(isinstance(v, str) for v in table.values()):
        raise ConfigError(
            f'--vehicle-map {path}: needs a [vehicles] table of "PATTERN or IDENTITY" = "NAME"'
        )
    return dict(table)


def rename_vehicles(rows: list[dict[str, Any]], mapping: Mapping[str, str]) -> None:
    """Each row's vehicle as the map names it: by its identity, else by its log's path
    matching a pattern (the first that matches)."""
    for row in rows:
        ident = str(row.get("vehicle"))
        if ident in mapping:
            row["vehicle"] = mapping[ident]
            continue
        for pattern, name in mapping.items():
            if fnmatch.fnmatch(str(row.get("log", "")), pattern):
                row["vehicle"] = name
                break


def run_log(
    path: str,
    config: AircraftConfig,
    folder: str,
    base: dict[str, Any],
    timeout_s: float | None,
    history_format: str,
) -> LogOutcome:
    """The task of one log on a worker: logs.estimate_file, with the worker's address.
    Its structure check replays in the task's one thread: a worker runs as many tasks
    at once as it has threads, so the cores are the workers' to share out (decision
    0070)."""
    blas.one_thread()
    try:
        from distributed import get_worker

        base = {**base, "worker": get_worker().address}
    except ValueError:  # not on a worker
        pass
    with weighting.replay_threads(1):
        return estimate_file(path, config, folder, base, timeout_s, history_format)


@dataclass
class Job:
    """One log of the batch."""

    path: Path
    key: str
    """Its log hash and config hash: what --resume recognises."""
    folder: Path
    base: dict[str, Any]


def plan(paths: Sequence[Path], config: AircraftConfig, out: Path) -> list[Job]:
    """Every log's job: its hash (read once here), its folder, its rows' base columns."""
    c_hash = config_sha256(config)
    ver = version()
    jobs = []
    for p, folder in zip(paths, folders(paths, out / LOGS_FOLDER), strict=True):
        try:
            l_hash = sha256_of(p)
        except OSError as exc:
            l_hash = f"unreadable: {exc.strerror}"
        base = {
            "log": str(p),
            "log_sha256": l_hash,
            "config_sha256": c_hash,
            "version": ver,
            "folder": str(folder),
        }
        jobs.append(Job(p, f"{l_hash[:32]}-{c_hash[:32]}", folder, base))
    return jobs


def read_done(out: Path) -> dict[str, dict[str, Any]]:
    """The logs an earlier batch in `out` finished well, by key (a line cut short by a
    kill is skipped)."""
    done: dict[str, dict[str, Any]] = {}
    path = out / DONE_FILE
    if not path.is_file():
        return done
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            entry = json.loads(line)
        except json.JSONDecodeError:
            continue
        if entry.get("error") is None:
            done[entry["key"]] = entry
    return done


class Progress:
    """A line per finished log: logs done, failed, rate and time left."""

    def __init__(self, total: int, out: TextIO, clock: Any = time.monotonic) -> None:
        self.total = total
        self.out = out
        self.clock = clock
        self.start = clock()
        self.done = 0
        self.failed = 0

    def line(self, outcome: LogOutcome) -> str:
        self.done += 1
        self.failed += outcome.error is not None
        elapsed = self.clock() - self.start
        rate = self.done / elapsed if elapsed > 0 else math.inf
        left = (self.total - self.done) / rate if rate > 0 else math.inf
        what = "ok" if outcome.error is None else f"FAILED: {outcome.error}"
        return (
            f"[{self.done}/{self.total}] {outcome.log}: {what} ({outcome.seconds:.1f} s); "
            f"failed {self.failed}, {60 * rate:.1f} logs/min, {_duration(left)} left"
        )

    def said(self, outcome: LogOutcome) -> None:
        print(self.line(outcome), file=self.out, flush=True)


def _duration(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "?"
    if seconds < 60:
        return f"{seconds:.0f} s"
    if seconds < 3600:
        return f"{seconds // 60:.0f} min {seconds % 60:02.0f} s"
    return f"{seconds // 3600:.0f} h {seconds % 3600 // 60:02.0f} min"


def _distributed() -> Any:
    """Dask's distributed package (imported when a batch starts: about a second)."""
    import importlib

    return importlib.import_module("distributed")


def connect(args: argparse.Namespace, log: TextIO) -> tuple[Any, Any]:
    """(client, the embedded cluster or None): the scheduler the command line names, or
    the environment's (DASK_SCHEDULER_ADDRESS), else a LocalCluster of --workers
    processes (default: one per core), one thread each."""
    import logging

    from gcs_estimator.runtime.fleet_worker import PrepareWorker, prepare

    dist = _distributed()
    Client, LocalCluster = dist.Client, dist.LocalCluster
    config = load_config(args.config, args.set)
    # Compiled (or loaded) once here: the workers then load the kernels from the cache
    # instead of each compiling them at once (fleet_worker.PrepareWorker).
    prepare(config)

    address = args.scheduler or os.environ.get(SCHEDULER_VARIABLE) or None
    if args.scheduler_file:
        client = Client(scheduler_file=args.scheduler_file, timeout="30s")
        where = f"the scheduler in {args.scheduler_file}"
        cluster = None
    elif address:
        client = Client(address, timeout="30s")
        where = f"scheduler {address}"
        cluster = None
    else:
        workers = args.workers or os.cpu_count() or 1
        cluster = LocalCluster(
            n_workers=workers,
            threads_per_worker=1,
            processes=True,
            dashboard_address="127.0.0.1:0",
            silence_logs=logging.ERROR,
        )
        client = Client(cluster)
        where = f"a local cluster of {workers} worker processes"
    client.register_plugin(PrepareWorker(config))
    n = len(client.scheduler_info().get("workers", {}))
    print(f"batch on {where}, {n} workers now", file=log, flush=True)
    services = client.scheduler_info().get("services", {})
    if "dashboard" in services:
        print(f"dashboard: {client.dashboard_link}", file=log, flush=True)
    else:
        print("dashboard: none (the scheduler has no dashboard: it needs bokeh)", file=log)
    return client, cluster


def check_options(args: argparse.Namespace) -> None:
    """Refuse numbers a batch cannot use, naming the option."""
    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers {args.workers}: at least 1")
    if args.retries < 0:
        raise ConfigError(f"--retries {args.retries}: 0 or more")
    if args.timeout is not None and not args.timeout > 0:
        raise ConfigError(f"--timeout {args.timeout:g}: seconds, more than 0")
    if args.scheduler and args.scheduler_file:
        raise ConfigError("--scheduler and --scheduler-file: give one of them")
    if args.config is None:  # one airframe's logs; never the simulator's borrowed
        raise ConfigError(
            "batch: no airframe file: give --config (the airframe file of the aircraft "
            "whose logs these are; `gcs-estimator airframe FILE` writes a starter)"
        )


def run_batch(args: argparse.Namespace, stop: Stop, log: TextIO | None = None) -> int:
    """Every log of args.logs estimated on Dask; the tables and trend written. 0 when
    every log gave estimates, 1 when some failed, 2 when stopped before the end."""
    log = sys.stderr if log is None else log
    check_options(args)
    out = Path(args.out)
    if (out / DONE_FILE).exists() and not (args.resume or args.force):
        raise ConfigError(
            f"--out {out}: holds a batch already; --resume to finish it, --force to start "
            "it again, or another folder"
        )
    config = load_config(args.config, args.set)
    mapping = load_vehicle_map(args.vehicle_map)
    jobs = plan(find_logs(args.logs), config, out)
    out.mkdir(parents=True, exist_ok=True)
    if args.force and not args.resume:
        (out / DONE_FILE).unlink(missing_ok=True)
    earlier = read_done(out) if args.resume else {}
    kept = {j.key: earlier[j.key] for j in jobs if j.key in earlier}
    todo = [j for j in jobs if j.key not in kept]
    if args.resume:
        print(f"resume: {len(kept)} of {len(jobs)} logs done already, {len(todo)} to run",
              file=log, flush=True)  # fmt: skip
    outcomes: dict[str, dict[str, Any]] = {}
    for job in jobs:
        if job.key in kept:
            outcomes[job.key] = _moved(kept[job.key], job)
    stopped = False
    if todo:
        stopped = _run_jobs(args, config, todo, outcomes, out, stop, log)
    return _finish(args, jobs, outcomes, mapping, out, stopped, log)


def _moved(entry: dict[str, Any], job: Job) -> dict[str, Any]:
    """An earlier run's entry of the same log (hash), its rows naming the log as now."""
    for rows in (entry["coefficients"], entry["summaries"]):
        for row in rows:
            row["log"] = str(job.path)
    return entry


def _run_jobs(
    args: argparse.Namespace,
    config: AircraftConfig,
    todo: list[Job],
    outcomes: dict[str, dict[str, Any]],
    out: Path,
    stop: Stop,
    log: TextIO,
) -> bool:
    """Run the jobs on the cluster, each outcome appended to DONE_FILE as it comes;
    True when a stop ended it early."""
    as_completed = _distributed().as_completed
    client, cluster = connect(args, log)
    progress = Progress(len(todo), log)
    stopped = False
    try:
        started = time.perf_counter()
        # The config as a task's result, not scattered data: the scheduler computes a lost
        # result again, while scattered data lost with the only worker holding it cancels
        # every log that needs it (tests/test_fleet.py's killed-worker test once saw all
        # its logs cancelled so).
        config_future = client.submit(_given, config, pure=False)  # a key of its own
        futures = {
            client.submit(
                run_log,
                str(j.path),
                config_future,
                str(j.folder),
                j.base,
                args.timeout,
                args.history,
                key=f"log-{j.key}-{i}",
                retries=args.retries,
                pure=False,
            ): j
            for i, j in enumerate(todo)
        }
        pending = as_completed(list(futures))
        with open(out / DONE_FILE, "a", encoding="utf-8") as done_file:
            while not pending.is_empty():
                if stop.requested:
                    stopped = True
                    client.cancel(list(futures))
                    break
                batch = pending.next_batch(block=False)
                if not batch:
                    time.sleep(POLL_S)
                    continue
                for future in batch:
                    job = futures[future]
                    outcome = _outcome(future, job)
                    progress.said(outcome)
                    entry = _entry(job, outcome)
                    outcomes[job.key] = entry
                    done_file.write(json.dumps(entry, default=_json_default) + "\n")
                    done_file.flush()
        wall = time.perf_counter() - started
        print(f"ran {progress.done} logs in {wall:.2f} s (first submitted to last done)", file=log)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return stopped


def _given(value: Any) -> Any:
    """The value itself: a task whose result the workers share (the batch's config)."""
    return value


def _outcome(future: Any, job: Job) -> LogOutcome:
    """A finished task's outcome; a task that raised (after its retries, or its worker
    killed too often) is a failed row with the exception; one the scheduler cancelled,
    a failed row that says so."""
    if future.status == "finished":
        outcome: LogOutcome = future.result()
        return outcome
    try:
        exc = future.exception()
        error = (
            f"{type(exc).__name__}: {exc}"
            if exc is not None
            else f"the scheduler dropped the task ({future.status})"
        )
    except Exception as other:
        error = f"{type(other).__name__}: {other}"
    row = failed_row(job.base, error)
    return LogOutcome(str(job.path), [row], [dict(row)], error, 0.0)


def _entry(job: Job, outcome: LogOutcome) -> dict[str, Any]:
    return {
        "key": job.key,
        "log": str(job.path),
        "error": outcome.error,
        "coefficients": outcome.coefficients,
        "summaries": outcome.summaries,
    }


def _json_default(value: Any) -> Any:
    if isinstance(value, datetime):
        return value.isoformat()
    raise TypeError(f"not JSON: {type(value).__name__}")


def _finish(
    args: argparse.Namespace,
    jobs: list[Job],
    outcomes: dict[str, dict[str, Any]],
    mapping: Mapping[str, str],
    out: Path,
    stopped: bool,
    log: TextIO,
) -> int:
    """The tables of every log done (this run's and, with --resume, the earlier's), the
    trend, and the exit status."""
    coefficients: list[dict[str, Any]] = []
    summaries: list[dict[str, Any]] = []
    for job in jobs:
        entry = outcomes.get(job.key)
        if entry is not None:
            coefficients += entry["coefficients"]
            summaries += entry["summaries"]
    rename_vehicles(coefficients, mapping)
    rename_vehicles(summaries, mapping)
    c_path = write_table(coefficients, COEFFICIENT_COLUMNS, out / COEFFICIENTS_FILE)
    s_path = write_table(summaries, SUMMARY_COLUMNS, out / FLIGHTS_FILE)
    failed = sum(1 for e in outcomes.values() if e["error"] is not None)
    not_run = len(jobs) - len(outcomes)
    print(f"{len(outcomes) - failed} logs estimated, {failed} failed, {not_run} not run")
    print(f"tables: {c_path}, {s_path}")
    if not args.no_trend and coefficients:
        write_trend(read_rows(c_path), out, args.view, log)
    if stopped or not_run:
        print(f"stopped: {not_run} logs not run; `--resume --out {out}` runs them", file=log)
        return 2
    return 1 if failed else 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of `batch` but --config (add_commands)."""
    p.add_argument(
        "logs",
        nargs="+",
        help="log files, folders (every log in them and below) or glob patterns "
        f"('logs/**/*.tlog'); formats: {', '.join(LOG_SUFFIXES)}",
    )
    options.set_option(p)
    options.out_options(
        p,
        "the batch's folder (default: out/batch_UTCTIME): its tables, trend, and a folder of "
        "results per log",
        "start again in an --out that has a batch",
    )
    p.add_argument(
        "--resume",
        action="store_true",
        help="in --out's batch, skip the logs done already (same log and config hash)",
    )
    where = p.add_argument_group("where the logs run (Dask)")
    where.add_argument(
        "--scheduler",
        default=None,
        metavar="tcp://HOST:PORT",
        help=f"a running Dask scheduler (default: ${SCHEDULER_VARIABLE} if set, else a local "
        "cluster)",
    )
    where.add_argument(
        "--scheduler-file",
        default=None,
        metavar="FILE",
        help="the scheduler a Dask scheduler file names (as dask-scheduler --scheduler-file "
        "and dask-jobqueue write)",
    )
    where.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="N",
        help="worker processes of the local cluster (default: one per core)",
    )
    where.add_argument(
        "--timeout",
        type=float,
        default=None,
        metavar="S",
        help="a log not done after S seconds is a failed row (default: no limit)",
    )
    where.add_argument(
        "--retries",
        type=int,
        default=1,
        metavar="N",
        help="times a log whose task raised is tried again (default: %(default)s)",
    )
    options.history_option(p, "each log's")
    t = p.add_argument_group("the trend of each vehicle across its flights")
    options.vehicle_map_option(t)
    t.add_argument("--no-trend", action="store_true", help="no trend report at the end")
    options.trend_view_option(t)


def run_trend(args: argparse.Namespace) -> int:
    """`gcs-estimator trend TABLE`: the charts of a batch's coefficient table, written
    beside it (or into --out)."""
    table = Path(args.table)
    if table.is_dir():
        table = table / COEFFICIENTS_FILE
    if not table.is_file():
        raise ConfigError(f"{table}: no such table; give a batch's {COEFFICIENTS_FILE}")
    try:
        rows = read_rows(table)
    except ValueError as exc:
        raise ConfigError(str(exc)) from exc
    rename_vehicles(rows, load_vehicle_map(args.vehicle_map))
    out = Path(args.trend_out) if args.trend_out else table.parent
    found = write_trend(rows, out, args.view, filter_kind=args.filter)
    return 0 if found else 1


def add_trend_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("table", help=f"a batch's {COEFFICIENTS_FILE} (or its folder)")
    p.add_argument(
        "--out",
        dest="trend_out",
        default=None,
        metavar="FOLDER",
        help="where to write the report, its figures and trend.rrd (default: beside the table)",
    )
    p.add_argument(
        "--filter",
        choices=("IEKF", "EKF"),
        default="IEKF",
        help="whose estimates to chart (default: %(default)s)",
    )
    options.vehicle_map_option(p)
    options.trend_view_option(p)


def cmd_batch(args: argparse.Namespace) -> int:
    return run_batch(args, PROCESS_STOP.install())


def add_commands(sub: Any) -> None:
    """`batch` and `trend` in the command line's subcommands."""
    p = sub.add_parser(
        "batch",
        help="estimate many logs (a fleet's) on a Dask cluster, local or remote: one table of "
        "every log's coefficients, and each vehicle's trend",
    )
    options.config_option(p, None, "needed: the airframe of the aircraft whose logs these are")
    add_arguments(p)
    p.set_defaults(func=cmd_batch)
    p = sub.add_parser(
        "trend",
        help="chart each vehicle's coefficients across its flights from a batch's table, and "
        "flag a shift beyond what their sigmas allow",
    )
    add_trend_arguments(p)
    p.set_defaults(func=run_trend)
