"""Every benchmark's standard run, one after another: docs/results/ regenerated at one revision.

    ./run bench all              # every record, the old ones removed first
    ./run bench all --list       # the plan: each record's command and its expected time
    ./run bench all --only NAME  # re-run one record (or one benchmark's) into the index

A whole run empties docs/results/, runs each command of PLAN at the tree's commit and
writes docs/results/README.md: the revision, the date, the machine, and each record's
exact command and duration. It refuses a tree with changes (other than its own outputs):
a record must be of one commit. `--only` re-runs some records into the same index, which
then says which revision each came from; the normal path is a whole run.

Run it on a quiet machine: the timing benchmarks measure the machine as much as the code.
"""

from __future__ import annotations

import argparse
import datetime
import json
import re
import shlex
import shutil
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import record  # benchmarks/record.py: the script's directory is on sys.path

BENCHMARKS = Path(__file__).resolve().parent
INDEX = record.RESULTS / "index.json"
README = record.RESULTS / "README.md"


@dataclass(frozen=True)
class Run:
    """One record: docs/results/NAME.md, written by `./run bench SCRIPT ARGS`."""

    name: str
    script: str
    args: tuple[str, ...] = ()
    minutes: float = 1.0
    """What it took in a whole run on the 2-core machine the plan was sized on, others'
    tests running beside it [min]: what `--list` expects."""
    needs: tuple[str, ...] = ()
    """Programs it needs one of (found on PATH), if any."""

    def argv(self) -> list[str]:
        """The benchmark's arguments, `--record NAME` included when NAME is not its default."""
        return [*self.args, *(["--record", self.name] if self.name != self.script else [])]

    def command(self) -> str:
        return " ".join(["./run bench", self.script, *map(shlex.quote, self.argv())])


PLAN = (
    # Accuracy and honesty: the NOC flight at each turbulence level over the 20 seeds the
    # estimates are held to; the data no filter was tuned on, on the first seed and
    # pooled over five (the filters and `refine`); what the structure can hold.
    Run("accuracy_none", "accuracy", ("--seeds", "20"), 1.3),
    Run("accuracy_light", "accuracy", ("--seeds", "20", "--turbulence", "light"), 0.6),
    Run("accuracy_moderate", "accuracy", ("--seeds", "20", "--turbulence", "moderate"), 0.4),
    Run("realdata", "realdata", (), 1.5),
    Run("realdata_seeds", "realdata", ("--seeds", "5"), 4.2),
    # The wide validation set (issue 52): ten JSBSim aircraft, HFB-320 and NOC, the
    # held-out half reported apart from the half defaults are chosen on (decision 0043).
    Run("validation", "validation", (), 15),
    # JSBSim's pa28, c172x and J3Cub, kept out of the set for independent checks
    # (decision 0071): a change is judged on them apart from both halves.
    Run("validation_independent", "validation", ("--half", "independent"), 5),
    Run("refine_hfb", "refine_hfb", (), 1),
    Run("input_delay", "input_delay", (), 5),
    Run("structure_gap", "structure_gap", (), 0.1),
    Run("advice", "advice", ("--seeds", "3"), 1),
    Run("pitch_gust_share", "pitch_gust_share", ("--seeds", "3"), 0.1),
    Run("turbulence_models", "turbulence_models", ("--seeds", "5", "--noc-seeds", "20"), 2.6),
    # Issue 53's NOC targets: the mission (turns, climb, descent), vane and no vane.
    Run("noc_mission", "noc_mission", ("--seeds", "20"), 60),
    # Calm air without a vane: Cm0's sigma against the vane's is the climb rate's noise
    # (decision 0081): the calm mission with a climb rate four times quieter.
    Run(
        "noc_mission_climb_rate_noise",
        "noc_mission",
        (
            "--seeds",
            "6",
            "--cases",
            "calm",
            "--set",
            "simulation.sensors.noise_sigma.h_dot=0.075",
            "--set",
            "filter.measurement_sigma.h_dot=0.075",
        ),
        8,
    ),
    # Its light turbulence with a vane: the NEES above its band, with the vane ten times
    # quieter (decision 0092).
    Run(
        "noc_mission_quiet_vane",
        "noc_mission",
        (
            "--seeds",
            "5",
            "--cases",
            "light",
            "--set",
            "simulation.sensors.noise_sigma.alpha_deg=0.03",
            "--set",
            "filter.measurement_sigma.alpha_deg=0.03",
        ),
        4,
    ),
    # Why its light turbulence without a vane is not identified: the pass likelihood held
    # at the estimates and at the truth, passes started at the truth (decision 0075), and
    # the whole-record fit over that pass from the EKF's end (decision 0080).
    Run("vertical_wind", "vertical_wind", ("--seeds", "2", "--fit", "EKF"), 40),
    # Its calm NEES over the seeds noc_mission scores against the output-error fit on the
    # same flights (the efficient estimator), and over 100 further seeds (decision 0082).
    Run("calm_nees", "calm_nees", (), 18),
    # Issue 53's JSBSim targets: the mission set, no vane, spec-sheet propellers; turns
    # included against the level legs only (flies the set where out/missions lacks it).
    # Both filters only (refine on every flight would take hours on 2 cores).
    Run("mission_accuracy", "mission_accuracy", ("--seeds", "5", "--refine", "none"), 33),
    # The same flights' turns as a user following the warnings flies them: the
    # filter-error fit, then the filters with what it advises (decision 0087).
    Run(
        "mission_accuracy_advised",
        "mission_accuracy",
        ("--seeds", "1", "--cases", "turns", "--advised"),
        30,
    ),
    # A link whose servo outputs come slower than its sensors, and the real ArduPlane
    # flight (where ../shared holds it) as given and as its warnings advise (decision 0084).
    Run(
        "slow_inputs",
        "slow_inputs",
        ("--seeds", "3", "--alfa", "../shared/data/real/alfa_carbonz_t28"),
        2,
    ),
    # Following the warnings' advice where the answer is known: the NOC UAV in light
    # turbulence told calm, in light turbulence as shipped, and in calm air (decision 0088).
    Run("follow_advice", "follow_advice", ("--seeds", "10"), 15),
    # Speed and the live link: one core's filter steps, a long replay, a station's
    # vehicles over UDP (10, and 50 to load it), its memory, endurance, stop and start.
    Run("speed", "speed", (), 0.4),
    Run("read_logs", "read_logs", (), 0.5),
    Run("replay", "replay", ("--minutes", "60", "--boot-s", "4000", "--view"), 4),
    Run("replay_vehicles", "replay_vehicles", ("--vehicles", "10", "--minutes", "5"), 3.5),
    Run("live", "live", ("--vehicles", "10", "--seconds", "30"), 0.6),
    Run("live_50", "live", ("--vehicles", "50", "--seconds", "60", "--repeat", "3"), 3.7),
    Run("fleet", "fleet", (), 0.3),
    Run("fleet_dask", "fleet_dask", (), 15),
    Run("hour", "hour", (), 3.6),
    Run("stop", "stop", (), 1.7),
    Run("startup", "startup", (), 0.2),
    Run("startup_cold", "startup", ("--cold", "--runs", "2"), 1.3),
    Run("webview", "webview", (), 7.5, needs=("chromium", "chromium-browser")),
)
NOT_IN_PLAN = {
    "formats": "prints how long the simulator's autopilot-format writers take "
    "(docs/decisions/0040); no record",
    "log_agreement": "prints how a DataFlash log's estimates lie against the native "
    "stream's and truth over seeds (docs/decisions/0045); no record",
    "jsbsim_flights": "writes the validation set, not a record; the benchmarks that use "
    "it fly it themselves",
    "validation_flights": "writes the wide validation set's flights, not a record; "
    "`validation` flies them itself (once per seed, then reuses them)",
    "link_stages": "prints where a tlog's decoding spends its CPU, part by part "
    "(docs/decisions/0058); no record",
    "jsbsim_missions": "writes the validation set flown as a mission (turns, wind, no vane) "
    "in the autopilots' formats, not a record (docs/decisions/0053)",
    "filter_blocks": "prints the filters' CPU per log frame by frame and in blocks "
    "(docs/decisions/0065); no record",
}
"""Benchmark scripts `all` does not run, and why."""


@dataclass
class Entry:
    """One record in the index."""

    name: str
    command: str
    seconds: float
    revision: str
    date: str
    status: str
    """"ok", "failed (exit N)", "skipped: WHY", or "ok, but ..." when the record has a
    problem (an absolute path, a simulator's start-up output)."""


def now() -> str:
    return datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")


CHATTER = re.compile(r"JSBSim Flight Dynamics Model|JSBSim startup|Could not bind to")
"""A simulator's start-up output: it belongs on stderr, not in a record."""


def problems(text: str) -> list[str]:
    """What a record should not hold: the machine's absolute paths, start-up chatter."""
    found = []
    home = str(Path.home())
    if str(record.ROOT) in text or (home != "/" and home in text) or "/tmp/" in text:
        found.append("an absolute path")
    if CHATTER.search(text):
        found.append("a simulator's start-up output")
    return found


def execute(run: Run, revision: str) -> Entry:
    """Run one benchmark as `./run bench` would, and check what it wrote."""
    date = now()
    if run.needs and not any(shutil.which(program) for program in run.needs):
        why = f"skipped: needs {' or '.join(run.needs)}"
        return Entry(run.name, run.command(), 0.0, revision, date, why)
    path = record.RESULTS / f"{run.name}.md"
    path.unlink(missing_ok=True)
    start = time.perf_counter()
    script = BENCHMARKS / f"{run.script}.py"
    code = subprocess.run([sys.executable, str(script), *run.argv()], cwd=record.ROOT).returncode
    seconds = time.perf_counter() - start
    if code != 0:
        status = f"failed (exit {code})"
    elif not path.exists():
        status = "failed (no record written)"
    else:
        found = problems(path.read_text(encoding="utf-8"))
        status = "ok" + (f", but it holds {' and '.join(found)}" if found else "")
    return Entry(run.name, run.command(), round(seconds, 1), revision, date, status)


def load_index() -> dict[str, Entry]:
    if not INDEX.exists():
        return {}
    return {e["name"]: Entry(**e) for e in json.loads(INDEX.read_text(encoding="utf-8"))}


def write_index(entries: dict[str, Entry], machine: str) -> None:
    """docs/results/index.json (what `--only` reads back) and README.md, in PLAN's order."""
    order = [run.name for run in PLAN if run.name in entries]
    INDEX.write_text(
        json.dumps([asdict(entries[n]) for n in order], indent=1) + "\n", encoding="utf-8"
    )
    README.write_text(render([entries[n] for n in order], machine), encoding="utf-8")


def _minutes(seconds: float) -> str:
    return f"{seconds / 60:.1f} min"


def render(entries: list[Entry], machine: str) -> str:
    """The index: where the records came from, then one row per record."""
    revisions = sorted({e.revision for e in entries})
    dates = sorted(e.date for e in entries)
    missing = [run.name for run in PLAN if run.name not in {e.name for e in entries}]
    dirty = any("local changes" in r for r in revisions)
    clean = "" if dirty or not revisions else " (no uncommitted changes)"
    lines = [
        "# Benchmark records",
        "",
        "Written by `./run bench all` (benchmarks/all.py); what each benchmark measures is in",
        "[docs/benchmarks.md](../benchmarks.md). Each record starts with its command, date,",
        "revision and machine.",
        "",
        f"- revision: {', '.join(revisions) or 'none'}{clean}",
        f"- date: {dates[0] if dates else 'none'} (the first record started) to "
        f"{dates[-1] if dates else 'none'} (the last)",
        f"- machine: {machine}",
        f"- total: {_minutes(sum(e.seconds for e in entries))}",
    ]
    if len(revisions) > 1:
        lines.append(
            "- **these records are of more than one revision** (re-runs with `--only`): "
            "see the revision column; `./run bench all` makes them one"
        )
    if dirty:
        lines.append("- **the tree had uncommitted changes**: these records are of no commit")
    if missing:
        lines.append(
            f"- **not in this index**: {', '.join(missing)} (not run, or the run did not finish)"
        )
    lines += ["", "| record | command | duration | revision | status |", "|---|---|---|---|---|"]
    for e in entries:
        link = f"[{e.name}.md]({e.name}.md)" if e.status.startswith("ok") else e.name
        lines.append(
            f"| {link} | `{e.command}` | {_minutes(e.seconds)} | {e.revision} | {e.status} |"
        )
    return "\n".join(lines) + "\n"


def show_plan(runs: list[Run]) -> None:
    for run in runs:
        needs = f" (needs {' or '.join(run.needs)})" if run.needs else ""
        print(f"{run.minutes:5.1f} min  {run.command()}{needs}")
    print(
        f"{sum(run.minutes for run in runs):5.1f} min  in all (as measured on 2 cores, not quiet)"
    )


def chosen(only: list[str]) -> list[Run]:
    """The plan, or the runs named (by record or by benchmark) in `only`."""
    if not only:
        return list(PLAN)
    runs = [run for run in PLAN if run.name in only or run.script in only]
    unknown = set(only) - {run.name for run in runs} - {run.script for run in runs}
    if unknown:
        raise SystemExit(f"all: not in the plan: {', '.join(sorted(unknown))} (see --list)")
    return runs


def clear_results() -> None:
    """A whole run starts from an empty folder: nothing of another revision stays."""
    for path in record.RESULTS.glob("*"):
        if path.is_file():
            path.unlink()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--list", action="store_true", help="print the plan and run nothing")
    ap.add_argument(
        "--only",
        nargs="+",
        default=[],
        metavar="NAME",
        help="re-run these records (or every record of these benchmarks) into the index",
    )
    ap.add_argument(
        "--allow-dirty",
        action="store_true",
        help="run on a tree with uncommitted changes (the index says so): for trying, "
        "never for the records kept",
    )
    args = ap.parse_args(argv)
    runs = chosen(args.only)
    if args.list:
        show_plan(runs)
        return 0
    return run_all(runs, whole=not args.only, allow_dirty=args.allow_dirty)


def run_all(runs: list[Run], whole: bool, allow_dirty: bool) -> int:
    head, changed = record.tree_revision()
    if changed and not allow_dirty:
        print(
            "all: the tree has uncommitted changes, so the records would be of no commit:\n  "
            + "\n  ".join(changed[:20])
            + "\ncommit them (or run with --allow-dirty to try, never to keep)",
            file=sys.stderr,
        )
        return 2
    revision = head + (" with local changes" if changed else "")
    if changed:
        print(f"all: WARNING: {len(changed)} uncommitted changes; records marked", file=sys.stderr)
    if whole:
        clear_results()
    record.RESULTS.mkdir(parents=True, exist_ok=True)
    entries = {} if whole else load_index()
    machine = record.machine()
    for i, run in enumerate(runs, 1):
        print(f"\n== [{i}/{len(runs)}] {run.command()} (about {run.minutes:g} min)", flush=True)
        entries[run.name] = execute(run, revision)
        write_index(entries, machine)
        now_head, now_changed = record.tree_revision()
        if now_head != head or (now_changed and not changed):
            print(
                f"all: the tree changed during the run ({head} -> {now_head}, "
                f"{len(now_changed)} uncommitted changes); stopping: the records would "
                "mix revisions",
                file=sys.stderr,
            )
            return 1
    return report(entries, runs)


def report(entries: dict[str, Entry], runs: list[Run]) -> int:
    """Say what went wrong, loudly; 1 if any record failed or has a problem."""
    bad = [entries[run.name] for run in runs if entries[run.name].status != "ok"]
    total = sum(entries[run.name].seconds for run in runs)
    print(f"\nall: {len(runs)} records in {_minutes(total)}; index in docs/results/README.md")
    for e in bad:
        print(f"all: {e.name}: {e.status}", file=sys.stderr)
    return 1 if any(not e.status.startswith("skipped") for e in bad) else 0


if __name__ == "__main__":
    sys.exit(main())
