"""Several recorded flights at once: `replay --each A.tlog B.tlog ...`.

Every file is a flight of its own (without --each, the files are one flight, in order).
Each is replayed by a `replay` process of its own, up to --jobs at a time (default: the
machine's cores), into a folder of its own under the run's folder, with its console
output in that folder's replay.log. When all have ended, what they wrote is merged: one
row per file and vehicle on stdout, and replays.json (every file's results in full, with
its exit status and time) and replays.md in the run's folder.

A stop (Ctrl-C, SIGTERM) starts no more files and passes the signal on to the running
ones, which end as a single replay does: with the results of what they had processed.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

from gcs_estimator.config import ConfigError
from gcs_estimator.stop import Stop

SUMMARY_COEFFICIENTS = ("CLa", "Cma", "Cmq", "Cmde")
"""Coefficients the summary table shows (IEKF estimate and corrected sigma) where the
config has them; replays.json has them all."""

VIEWS_ALLOWED = ("save", "off")
"""View outputs a batch can give its replays: a viewer each, or one port for all, cannot."""

LOG_FILE = "replay.log"
POLL_S = 0.05
"""How often the batch looks at its replays and at the stop request [s]."""


@dataclass
class Job:
    """One file's replay."""

    path: Path
    folder: Path
    proc: subprocess.Popen[bytes] | None = None
    started: float = math.nan
    seconds: float = math.nan
    status: int | None = None


def check_options(args: argparse.Namespace) -> None:
    """Refuse the options a batch cannot pass to each of its replays, naming the fix."""
    if args.jobs is not None and args.jobs < 1:
        raise ConfigError(f"--jobs {args.jobs}: must be at least 1")
    views = [] if args.view is None else [v.strip() for v in args.view.split(",")]
    wrong = [v for v in views if v not in VIEWS_ALLOWED]
    if wrong:
        raise ConfigError(
            f"--view {args.view}: with --each every file is replayed in a process of its own, "
            f"so the view can only be {' or '.join(VIEWS_ALLOWED)} (each file's .rrd in its "
            "folder); open the recordings afterwards"
        )
    for option, value in (("--rrd", args.rrd), ("--serve-port", args.serve_port)):
        if value is not None:
            raise ConfigError(f"{option}: not with --each (each file's replay has its own)")
    if args.speed:
        raise ConfigError("--speed: not with --each (the files are replayed as fast as possible)")


def folders(paths: Sequence[Path], out: Path) -> list[Path]:
    """A folder per file under out, named after the file (_2, _3 ... for a name taken)."""
    taken: set[str] = set()
    result = []
    for p in paths:
        name, k = p.stem, 1
        while name in taken:
            k += 1
            name = f"{p.stem}_{k}"
        taken.add(name)
        result.append(out / name)
    return result


def child_command(args: argparse.Namespace, path: Path, folder: Path, width: int = 1) -> list[str]:
    """The `replay` command of one file: the batch's options, its own folder; with
    `width` replays at a time, each replay's structure check in its share of the cores
    (--check-threads, where not given: the replays already use the cores between them)."""
    cmd = [sys.executable, "-m", "gcs_estimator", "replay", str(path), "--out", str(folder)]
    threads = args.check_threads or max(1, (os.cpu_count() or 1) // max(width, 1))
    cmd += ["--check-threads", str(threads)]
    if args.config is not None:
        cmd += ["--config", args.config]
    for item in args.set:
        cmd += ["--set", item]
    for option, value in (
        ("--refine", args.refine),
        ("--reference", args.reference),
        ("--truth", args.truth),
        ("--filter-workers", args.filter_workers),
        ("--validate", args.validate),
    ):
        if value is not None:
            cmd += [option, str(value)]
    for window in args.window or []:
        cmd += ["--window", window]
    cmd += ["--view", args.view or "save", "--history", args.history]
    if args.hold_noise:
        cmd.append("--hold-noise")
    if args.no_advice:
        cmd.append("--no-advice")
    if args.force:
        cmd.append("--force")
    return cmd


def run_each(args: argparse.Namespace, stop: Stop, log: TextIO | None = None) -> int:
    """Replay every file of args.tlogs as a flight of its own; 0 when all succeeded, else
    the first failing replay's exit status."""
    log = sys.stderr if log is None else log
    check_options(args)
    out = Path(args.out)
    paths = [Path(p) for p in args.tlogs]
    missing = [str(p) for p in paths if not p.is_file()]
    if missing:
        raise ConfigError(f"no such file: {', '.join(missing)}")
    jobs = [Job(p, f) for p, f in zip(paths, folders(paths, out), strict=True)]
    width = args.jobs or os.cpu_count() or 1
    print(
        f"replaying {len(jobs)} files as separate flights, {min(width, len(jobs))} at a time, "
        f"into {out}/ (each file's console output in its folder's {LOG_FILE})",
        file=log,
        flush=True,
    )
    out.mkdir(parents=True, exist_ok=True)
    _drive(args, jobs, width, stop, log)
    summary = summarise(jobs)
    (out / "replays.json").write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    table = summary_markdown(summary)
    (out / "replays.md").write_text("# Replays\n\n" + table, encoding="utf-8")
    print(table, end="")
    print(f"results: {out / 'replays.json'}, {out / 'replays.md'}")
    failed = [j.status for j in jobs if j.status]  # None: never started (a stop came first)
    if not failed:
        return 0
    first = failed[0]
    assert first is not None
    return first if first > 0 else 2  # a replay ended by a signal


def _drive(args: argparse.Namespace, jobs: list[Job], width: int, stop: Stop, log: TextIO) -> None:
    """Keep up to width replays running until every file is done (or a stop)."""
    waiting = list(jobs)
    running: list[Job] = []
    done = 0
    forwarded = 0
    while waiting or running:
        while waiting and len(running) < width and not stop.requested:
            job = waiting.pop(0)
            _start(args, job, min(width, len(jobs)))
            running.append(job)
            print(f"started {job.path} -> {job.folder}", file=log, flush=True)
        if stop.requested:
            waiting.clear()  # never started: no status, said in the summary
            if stop.count > forwarded:
                forwarded = stop.count
                for job in running:
                    assert job.proc is not None
                    job.proc.send_signal(signal.SIGINT)
        for job in list(running):
            assert job.proc is not None
            try:
                job.status = job.proc.wait(timeout=POLL_S / max(len(running), 1))
            except subprocess.TimeoutExpired:
                continue
            job.seconds = time.perf_counter() - job.started
            running.remove(job)
            done += 1
            _said(job, done, len(jobs), log)


def _start(args: argparse.Namespace, job: Job, width: int) -> None:
    job.folder.mkdir(parents=True, exist_ok=True)
    with open(job.folder / LOG_FILE, "wb") as out:
        job.started = time.perf_counter()
        # Own session: a Ctrl-C at the terminal reaches the replays once, from the batch.
        # SIGINT ignored until the replay installs its handler (first thing it does): a
        # stop forwarded during its start never kills it with a traceback.
        job.proc = subprocess.Popen(
            child_command(args, job.path, job.folder, width),
            stdout=out,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
            preexec_fn=_ignore_interrupts,
        )


def _ignore_interrupts() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _said(job: Job, done: int, total: int, log: TextIO) -> None:
    """A line when a replay ends; the end of its log when it failed."""
    line = f"[{done}/{total}] {job.path}: exit {job.status} after {job.seconds:.1f} s"
    print(line, file=log, flush=True)
    if job.status != 0:
        tail = (job.folder / LOG_FILE).read_text(encoding="utf-8", errors="replace")
        for text in tail.strip().splitlines()[-5:]:
            print(f"    {text}", file=log)


def summarise(jobs: Sequence[Job]) -> dict[str, Any]:
    """Each file's exit status, time and every vehicle's results (as its replay wrote
    them)."""
    files = []
    for job in jobs:
        results = []
        for p in sorted(job.folder.glob("results_sys*.json"), key=_system_id):
            results.append(json.loads(p.read_text(encoding="utf-8")))
        files.append(
            {
                "file": str(job.path),
                "folder": str(job.folder),
                "exit_status": job.status,
                "seconds": None if math.isnan(job.seconds) else round(job.seconds, 3),
                "vehicles": results,
            }
        )
    return {"files": files}


def _system_id(path: Path) -> int:
    digits = path.stem.removeprefix("results_sys")
    return int(digits) if digits.isdigit() else 0


def summary_markdown(summary: dict[str, Any]) -> str:
    """One row per file and vehicle: frames, the key coefficients (IEKF, estimate ±
    corrected sigma, with its identifiability where not identified) and warnings."""
    head = ["file", "exit", "s", "vehicle", "frames", *SUMMARY_COEFFICIENTS, "warnings"]
    rows = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for f in summary["files"]:
        status = "not run" if f["exit_status"] is None else str(f["exit_status"])
        seconds = "" if f["seconds"] is None else f"{f['seconds']:.1f}"
        name = Path(f["file"]).name
        if not f["vehicles"]:
            blanks = [""] * (len(SUMMARY_COEFFICIENTS) + 1)
            rows.append("| " + " | ".join([name, status, seconds, "-", *blanks, ""]) + " |")
        for v in f["vehicles"]:
            cells = [name, status, seconds, str(v.get("system_id", ""))]
            cells.append(str(v["diagnostics"]["frames"]))
            estimates = v["filters"].get("IEKF", {}).get("estimates", {})
            cells += [_cell(estimates.get(n)) for n in SUMMARY_COEFFICIENTS]
            cells.append(str(len(v.get("warnings", []))))
            rows.append("| " + " | ".join(cells) + " |")
    return "\n".join(rows) + "\n"


def _cell(c: dict[str, Any] | None) -> str:
    if c is None:
        return "-"
    if c.get("estimate") is None:
        return "-"
    sigma = c.get("sigma")  # the sigma to trust
    text = f"{c['estimate']:.4g}" + ("" if sigma is None else f" ± {sigma:.2g}")
    mark = c.get("identifiability")
    return text if mark in (None, "identified") else f"{text} ({mark})"
