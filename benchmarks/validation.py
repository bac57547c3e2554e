"""A validation set too wide to tune to: ten JSBSim aircraft, HFB-320 and the NOC
simulator, split into a tuning half and a held-out half, each judged on its own.

    ./run bench validation [--seeds 1] [--jobs 2] [--set KEY=VALUE] [--refine METHOD|none]

The JSBSim flights (benchmarks/validation_flights.py: each aircraft calm and in light
turbulence, with and without sensor noise, the elevator as the model's FCS moves it and
as a step between two samples, sensors placed as the model places things) are flown
once per seed into out/validation/ and reused; the NOC simulator flies the same four
conditions (calm and light, noisy and noise-free); HFB-320 is its one flight test. The
estimator runs on every record from zero with its airframe file and the project's
defaults (no [filter] table; the NOC config's own), then `refine` (auto), in `--jobs`
processes.

Judged with the sigma and the marks the run shows its user (each filter's corrected
sigma and marks, `refine`'s sigma and marks), against the structure's best fit to the
noise-free calm flight with the surface as it moved (JSBSim), the reference (HFB-320) or
the truth (NOC):

- within 3σ: the share of the well-excited coefficients (realdata.WELL_EXCITED) whose
  error is within 3 of the sigma shown;
- mean z²: their squared error in sigmas, averaged (an honest sigma gives about 1); and
  the median over the records of each record's mean z²;
- identified beyond 3σ: of all coefficients marked "identified", how many lie more than
  3 shown sigmas from the target.

Per aircraft, per condition, and for the held-out half, the tuning half and the whole
set, against the targets of issue 52 (on the held-out half and the whole set: within 3σ
>= 90 %, mean z² <= 2, identified beyond 3σ <= 5 %). Which aircraft is in which half, and
why: docs/benchmarks.md ("The validation set") and docs/decisions/0043. Each record's
coefficient table is written to out/validation/tables/.
"""

from __future__ import annotations

import argparse
import math
import pickle
import re
import sys
import time
from collections.abc import Iterable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import record  # benchmarks/record.py: the script's directory is on sys.path
import validation_flights as vf
from realdata import WELL_EXCITED

from gcs_estimator.config import REFINE_METHODS, load_config
from gcs_estimator.estimation.estimator import FILTER_KINDS
from gcs_estimator.ingest.flightdata import load_recording
from gcs_estimator.refine import RefineError, refine_run
from gcs_estimator.refine.result import Refined
from gcs_estimator.runtime.session import run_recording
from gcs_estimator.uncertainty.metrics import IDENTIFIED
from gcs_estimator.uncertainty.result import VehicleResult

ESTIMATORS = (*FILTER_KINDS, "refine")
TARGET_WITHIN = 90.0
TARGET_MSZ = 2.0
TARGET_IDENTIFIED_OUT = 5.0
"""Issue 52's targets, on the held-out half and on the whole set."""
OTHERS = {
    "hfb320": ("HFB-320 Hansa Jet (flight test)", "business jet, real flight", vf.TUNING),
    "noc": ("NOC simulator (the project's own)", "small UAV, simulated", vf.TUNING),
}
"""The set's members that are not JSBSim aircraft: label, class, half."""
NOC_CONDITIONS = (("calm", "none"), ("light", "light"))
ZERO_NOISE = [f"simulation.sensors.noise_sigma.{c}=0" for c in ("V", "theta", "q", "qdot")]
ZERO_NOISE += ["simulation.sensors.noise_sigma.alpha=0", "simulation.sensors.noise_sigma.a_x=0"]
ZERO_NOISE += ["simulation.sensors.noise_sigma.a_z=0"]


@dataclass(frozen=True)
class Job:
    """One record to run: a JSBSim CSV with its airframe file, HFB-320, or a NOC flight."""

    name: str
    aircraft: str
    condition: str
    """timing_air_noise (JSBSim), air_noise (NOC), "flight test" (HFB-320)."""
    overrides: tuple[str, ...]
    refine: str
    goal: dict[str, float] | None = None
    """The target per coefficient (JSBSim: the best fit); None: the config's [truth]."""
    csv: str = ""
    seed: int = 1


@dataclass
class Outcome:
    """What one record gave: per estimator the error in shown sigmas and the marks."""

    job: Job
    names: tuple[str, ...]
    z: dict[str, list[float]] = field(default_factory=dict)
    marks: dict[str, tuple[str, ...]] = field(default_factory=dict)
    table: str = ""
    seconds: float = 0.0
    cpu_seconds: float = 0.0
    """The worker's CPU time on the record (all its threads)."""
    failed: str = ""
    parts: dict[str, dict[str, list[float]]] = field(default_factory=dict)
    """Per estimator, what each coefficient's shown sigma is made of (filters: the
    covariance, the movement factor, the structure check's parts; refine: Cramer-Rao,
    Morelli-Klein, its structure, the filter's structure floor, the difference)."""
    delay_ms: tuple[float, float] = (math.nan, math.nan)
    """refine's fitted elevator delay and its sigma [ms] (NaN: none fitted)."""
    hold: tuple[str, float] = ("", math.nan)
    """The run's hold between samples and the structure check's -2 log likelihood change
    with the other (NaN: no check)."""
    advice: dict[str, Any] = field(default_factory=dict)
    """The settings the run's warnings advised (diagnosis.advised_settings), where a
    benchmark asks for them (mission_accuracy --advised)."""
    advice_noise: dict[str, Any] = field(default_factory=dict)
    """Those with the process noise the filter-error fit found, advised or not."""
    advice_colour: float = math.nan
    """The fit's largest residual colour over the channels (NaN: no fit)."""


Found = dict[str, tuple[np.ndarray, np.ndarray, tuple[str, ...]]]
"""Per estimator (the filters, refine): estimates, the sigmas shown, the marks."""


def scored(
    job: Job, vehicle: VehicleResult, goal: np.ndarray
) -> tuple[Outcome, Found, Refined | None]:
    """A record's run against goal: each filter's (and, as job asks, refine's)
    estimates, sigmas shown and marks (a refine that fails is the outcome's failure), their
    z, and the sigma parts with the sigma shown and the estimate."""
    out = Outcome(job, vehicle.result.names)
    found: Found = {}
    for k in FILTER_KINDS:
        summary = vehicle.summaries[k].coefficients
        found[k] = (
            np.array([c.estimate for c in summary]),
            np.array([c.sigma for c in summary]),
            tuple(c.identifiability for c in summary),
        )
    try:
        oe = refine_run(vehicle, job.refine) if job.refine != "none" else None
    except RefineError as exc:
        oe, out.failed = None, f"refine failed: {exc}"
    if oe is not None:
        found["refine"] = (oe.coefficients, oe.sigma, oe.identifiability)
    for estimator, (est, sigma, marks) in found.items():
        out.z[estimator] = ((est - goal) / sigma).tolist()
        out.marks[estimator] = marks
    out.parts = sigma_parts(vehicle, oe)
    check = vehicle.structure
    if check is not None and not check.skipped:
        out.hold = (check.input_hold, check.hold_change)
    for estimator, (est, sigma, _) in found.items():
        out.parts.setdefault(estimator, {})["shown"] = sigma.tolist()
        out.parts[estimator]["estimate"] = est.tolist()
    return out, found, oe


def run_job(job: Job) -> Outcome:
    """Run the estimator and `refine` on one record and judge them."""
    start, cpu = time.perf_counter(), time.process_time()
    if job.aircraft == "hfb320":
        config = load_config("hfb320", list(job.overrides))
        t, u, y = (lambda r: (r.t_s, r.inputs, r.measurements))(
            load_recording("hfb320", config.data)[1]
        )
    elif job.aircraft == "noc":
        from sim.truth import simulate

        config = load_config("noc_uav", list(job.overrides))
        flight = simulate(config, seed=job.seed)
        t, u, y = flight.t_s, flight.inputs, flight.measurements
    else:
        config = load_config(Path(job.csv).with_suffix(".toml"), list(job.overrides))
        rec = load_recording(job.csv)[1]
        t, u, y = rec.t_s, rec.inputs, rec.measurements
    vehicle = run_recording(config, t, u, y)
    names = vehicle.result.names
    goal = np.array(config.truth if job.goal is None else [job.goal[n] for n in names])
    out, found, oe = scored(job, vehicle, goal)
    if oe is not None and "elevator" in oe.delay_names:
        i = oe.delay_names.index("elevator")
        out.delay_ms = (1e3 * float(oe.delays_s[i]), 1e3 * float(oe.delay_sigma_s[i]))
    out.table = _table(names, goal, found)
    out.seconds = time.perf_counter() - start
    out.cpu_seconds = time.process_time() - cpu
    return out


def run_job_kept(job: Job) -> Outcome:
    """run_job, with an error of the record's own kept as its outcome (the run goes on with
    the other records; the report lists it) rather than ending the whole run."""
    start = time.perf_counter()
    try:
        return run_job(job)
    except Exception as exc:  # any record's failure is reported, not fatal
        out = Outcome(job, ())
        out.failed = f"{type(exc).__name__}: {exc}"
        out.seconds = time.perf_counter() - start
        return out


def sigma_parts(vehicle: VehicleResult, oe: Refined | None) -> dict[str, dict[str, list[float]]]:
    """What each estimator's shown sigma is made of, per coefficient (Outcome.parts)."""
    out: dict[str, dict[str, list[float]]] = {}
    check = vehicle.structure
    for k in FILTER_KINDS:
        coefficients = vehicle.summaries[k].coefficients
        parts = {
            "covariance": [c.sigma_parts.covariance for c in coefficients],
            "movement": [c.sigma_parts.movement_factor for c in coefficients],
            "structure": [c.sigma_parts.structure for c in coefficients],
        }
        if check is not None and not check.skipped:
            for label, per_filter in check.parts.items():
                if k in per_filter:
                    parts[label] = np.asarray(per_filter[k], float).tolist()
        out[k] = parts
    if oe is not None:
        fit = oe.sigma_parts
        out["refine"] = {
            "cramer_rao": fit.cramer_rao.tolist(),
            "morelli_klein": fit.morelli_klein.tolist(),
            "structure": fit.structure.tolist(),
        }
        if fit.filter_structure is not None:
            out["refine"]["filter_structure"] = np.asarray(fit.filter_structure).tolist()
        if fit.difference is not None:
            out["refine"]["difference"] = np.asarray(fit.difference).tolist()
    return out


def _table(
    names: tuple[str, ...],
    goal: np.ndarray,
    found: dict[str, tuple[np.ndarray, np.ndarray, tuple[str, ...]]],
) -> str:
    """One record's coefficients: target, and per estimator estimate, σ shown, z, mark."""
    head = ["coefficient", "target"]
    head += [f"{k} {c}" for k in found for c in ("estimate", "σ", "z", "mark")]
    rows = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for i, n in enumerate(names):
        row = [n, f"{goal[i]:.5g}"]
        for est, sigma, marks in found.values():
            z = (est[i] - goal[i]) / sigma[i]
            row += [f"{est[i]:.5g}", f"{sigma[i]:.2g}", f"{z:+.1f}", marks[i]]
        rows.append("| " + " | ".join(row) + " |")
    return "\n".join(rows)


def jobs(args: argparse.Namespace) -> list[Job]:
    """Every record of the set: the JSBSim flights (flown here where out/ lacks them),
    then the NOC simulator's and HFB-320's."""
    seeds = tuple(range(1, args.seeds + 1))
    wanted = chosen(args)
    units = vf.generate(seeds, args.jobs, Path(args.out), [m for m in wanted if m not in OTHERS])
    over = tuple(args.set)
    found: list[Job] = []
    for unit in units.values():
        goal = unit["best_fit"]
        records = unit["records"]
        assert isinstance(goal, dict) and isinstance(records, list)
        for name in records:
            model, timing, air, noise = vf.parse_name(name)
            csv = str(Path(args.out) / f"{name}.csv")
            seed = int(found_seed[1]) if (found_seed := re.search(r"_s(\d+)$", name)) else 1
            found.append(
                Job(name, model, f"{timing}_{air}_{noise}", over, args.refine, goal, csv, seed)
            )
    for seed in seeds if "noc" in wanted else ():
        for air, preset in NOC_CONDITIONS:
            for noise in vf.NOISES:
                sim = [f'simulation.turbulence.preset="{preset}"']
                sim += ZERO_NOISE if noise == "clean" else []
                name = f"noc_{air}_{noise}" + ("" if seed == 1 else f"_s{seed}")
                found.append(
                    Job(name, "noc", f"{air}_{noise}", (*over, *sim), args.refine, seed=seed)
                )
    if "hfb320" in wanted:
        found.append(Job("hfb320", "hfb320", "flight test", over, args.refine))
    return [j for j in found if all(word in j.condition for word in args.condition)]


def chosen(args: argparse.Namespace) -> list[str]:
    """The members to run: those of --half, narrowed to --aircraft where given."""
    members = [m for m in ORDER if membership(m)[2] == args.half] if args.half != "all" else SET
    unknown = set(args.aircraft) - set(ORDER)
    if unknown:
        raise SystemExit(f"--aircraft: no member {sorted(unknown)}; the set: {ORDER}")
    return [m for m in members if not args.aircraft or m in args.aircraft]


def membership(aircraft: str) -> tuple[str, str, str]:
    """(label, class, half) of a member of the set."""
    if aircraft in OTHERS:
        return OTHERS[aircraft]
    m = vf.member(aircraft)
    return m.aircraft.label, m.aircraft.kind, m.half


@dataclass
class Tally:
    """Pooled figures of one estimator over some records."""

    z_well: list[float] = field(default_factory=list)
    record_msz: list[float] = field(default_factory=list)
    identified: int = 0
    identified_out: int = 0
    records: int = 0

    def add(self, o: Outcome, k: str) -> None:
        if k not in o.z:
            return
        z = np.array(o.z[k])
        well = [i for i, n in enumerate(o.names) if n in WELL_EXCITED]
        self.z_well += z[well].tolist()
        self.record_msz.append(float(np.mean(z[well] ** 2)))
        ident = [i for i, mark in enumerate(o.marks[k]) if mark == IDENTIFIED]
        self.identified += len(ident)
        self.identified_out += int(np.sum(np.abs(z[ident]) > 3.0))
        self.records += 1

    @property
    def within(self) -> float:
        return 100.0 * float(np.mean(np.abs(self.z_well) < 3.0)) if self.z_well else math.nan

    @property
    def msz(self) -> float:
        return float(np.mean(np.square(self.z_well))) if self.z_well else math.nan

    @property
    def out_share(self) -> float:
        return 100.0 * self.identified_out / self.identified if self.identified else 0.0

    def cells(self) -> list[str]:
        return [
            f"{self.within:.0f} %",
            f"{self.msz:.3g}",
            f"{np.median(self.record_msz):.3g}" if self.record_msz else "-",
            f"{self.identified_out}/{self.identified} ({self.out_share:.0f} %)",
        ]

    def meets(self) -> str:
        checks = (
            self.within >= TARGET_WITHIN,
            self.msz <= TARGET_MSZ,
            self.out_share <= TARGET_IDENTIFIED_OUT,
        )
        return "yes" if all(checks) else "no"


def tally(outcomes: Iterable[Outcome], k: str) -> Tally:
    t = Tally()
    for o in outcomes:
        t.add(o, k)
    return t


def print_halves(outcomes: list[Outcome]) -> None:
    groups = {
        "held-out half": [o for o in outcomes if membership(o.job.aircraft)[2] == vf.HELD_OUT],
        "tuning half": [o for o in outcomes if membership(o.job.aircraft)[2] == vf.TUNING],
        "whole set": [o for o in outcomes if o.job.aircraft in SET],
    }
    independent = [o for o in outcomes if membership(o.job.aircraft)[2] == vf.INDEPENDENT]
    if independent:
        groups["independent check (not in the set)"] = independent
    print(
        "\n## The halves and the whole set\n\nwell-excited coefficients within 3 shown σ, "
        "their mean z² (pooled; and the median of the records' own), coefficients marked "
        "identified that lie beyond 3 shown σ; targets (issue 52, held-out half and whole "
        f"set): within 3σ >= {TARGET_WITHIN:.0f} %, mean z² <= {TARGET_MSZ:g}, identified "
        f"beyond 3σ <= {TARGET_IDENTIFIED_OUT:.0f} %\n"
    )
    print(
        "| group | records | estimator | within 3σ | mean z² | median record mean z² "
        "| identified beyond 3σ | targets met |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for group, members in groups.items():
        for k in ESTIMATORS:
            t = tally(members, k)
            print(f"| {group} | {t.records} | {k} | " + " | ".join(t.cells()) + f" | {t.meets()} |")


def print_by(outcomes: list[Outcome], key: str) -> None:
    """One row per aircraft (key "aircraft") or per condition (key "condition")."""
    values = list(dict.fromkeys(getattr(o.job, key) for o in outcomes))
    title = "aircraft" if key == "aircraft" else "condition (JSBSim: timing_air_noise)"
    print(f"\n## By {title}\n")
    head = [key] + (["class", "half"] if key == "aircraft" else [])
    head += ["records"] + [
        f"{k} {c}" for k in ESTIMATORS for c in ("within 3σ", "mean z²", "identified beyond 3σ")
    ]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for v in values:
        members = [o for o in outcomes if getattr(o.job, key) == v]
        row = [v if key != "aircraft" else membership(v)[0]]
        row += list(membership(v)[1:]) if key == "aircraft" else []
        row.append(str(len(members)))
        for k in ESTIMATORS:
            t = tally(members, k)
            row += [t.cells()[0], t.cells()[1], t.cells()[3]]
        print("| " + " | ".join(row) + " |")


def print_misses(outcomes: list[Outcome]) -> None:
    """Every coefficient marked identified beyond 3 shown sigma, with what its sigma is
    made of (each part in the shown sigma's units: a part's share of the sigma)."""
    print("\n## Identified beyond 3σ: z and the sigma's parts\n")
    print("| record | estimator | coefficient | z | σ shown | parts (σ units) |")
    print("|---|---|---|---|---|---|")
    for o in outcomes:
        for k, marks in o.marks.items():
            for i, mark in enumerate(marks):
                z = o.z[k][i]
                if mark != IDENTIFIED or abs(z) <= 3.0:
                    continue
                print(f"| {o.job.name} | {k} | {o.names[i]} | {z:+.1f} | " + _parts(o, k, i))
    counts: dict[tuple[str, str], list[int]] = {}
    for o in outcomes:
        for k, zs in o.z.items():
            for i, n in enumerate(o.names):
                c = counts.setdefault((k, n), [0, 0])
                c[0] += int(abs(zs[i]) > 3.0)
                c[1] += 1
    print("\n## Beyond 3σ, by coefficient (any mark)\n")
    print("| estimator | coefficient | beyond 3σ | records |")
    print("|---|---|---|---|")
    for (k, n), (bad, total) in counts.items():
        print(f"| {k} | {n} | {bad} | {total} |")


def _parts(o: Outcome, k: str, i: int) -> str:
    parts = o.parts.get(k, {})
    shown = parts["shown"][i]
    text = ", ".join(
        f"{label} {v[i]:.2g}" if label == "movement" else f"{label} {v[i] / shown:.2g}"
        for label, v in parts.items()
        if label != "shown"
    )
    return f"{shown:.2g} | {text} |"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seeds", type=int, default=1, help="turbulence and noise seeds 1..N")
    ap.add_argument("--jobs", type=int, default=2, help="processes (flying and estimating)")
    ap.add_argument("--out", default=str(vf.OUT), help="where the flights are kept")
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a config override for every record (the defaults under trial)",
    )
    ap.add_argument("--refine", choices=(*REFINE_METHODS, "none"), default="auto")
    ap.add_argument(
        "--half",
        choices=(vf.TUNING, vf.HELD_OUT, "all", vf.INDEPENDENT),
        default="all",
        help="run one half only (defaults are chosen on the tuning half alone); "
        f"'{vf.INDEPENDENT}': the aircraft held out of the set for independent checks "
        "(pa28, c172x, J3Cub; never in 'all')",
    )
    ap.add_argument(
        "--aircraft",
        nargs="+",
        default=[],
        metavar="MODEL",
        help="run these members only (JSBSim model names, hfb320, noc)",
    )
    ap.add_argument(
        "--condition",
        action="append",
        default=[],
        metavar="WORD",
        help="run the records whose condition holds WORD only (fcs, step, calm, light, "
        "noisy, clean; repeat: all of them)",
    )
    ap.add_argument(
        "--again",
        action="store_true",
        help="report the outcomes the last runs kept in --out (out/validation/ and the "
        "--outcomes folders), as far as they got, without running anything",
    )
    ap.add_argument(
        "--resume",
        action="store_true",
        help="keep the outcomes the first --outcomes folder holds and run only the records "
        "it lacks (a run stopped early is finished, not started again)",
    )
    ap.add_argument(
        "--outcomes",
        nargs="+",
        default=["outcomes"],
        metavar="NAME",
        help="folders under --out the outcomes are kept in as they come (the first; it is "
        "emptied first) and --again reads (all of them: e.g. a tuning and a held-out run)",
    )
    record.add_argument(ap, "validation")
    args = ap.parse_args(argv)
    with record.recorded("validation", args.record, "The validation set: held out and tuned on"):
        return run(args)


def run(args: argparse.Namespace) -> int:
    start = time.perf_counter()
    kept = Path(args.out) / args.outcomes[0]
    if args.again:
        folders = [Path(args.out) / name for name in args.outcomes]
        outcomes = [pickle.loads(p.read_bytes()) for f in folders for p in f.glob("*.pickle")]
        flown = 0.0
    else:
        todo = sorted(jobs(args), key=_priority)
        flown = time.perf_counter() - start
        outcomes = estimate(todo, args.jobs, kept, args.resume)
    outcomes.sort(key=lambda o: (ORDER.index(o.job.aircraft), o.job.name))
    tables = Path(args.out) / "tables"
    tables.mkdir(parents=True, exist_ok=True)
    for o in outcomes:
        (tables / f"{o.job.name}.md").write_text(o.table + "\n", encoding="utf-8")
    failed = [f"{o.job.name}: {o.failed}" for o in outcomes if o.failed]
    print(f"{len(outcomes)} records; overrides: {' '.join(args.set) or 'none (the defaults)'}")
    print_halves(outcomes)
    print_by(outcomes, "aircraft")
    print_by([o for o in outcomes if o.job.aircraft not in OTHERS], "condition")
    print_misses(outcomes)
    delays = [f"{o.job.name} {o.delay_ms[0]:.1f}±{o.delay_ms[1]:.1f}" for o in outcomes]
    print("\nrefine's elevator delay [ms]: " + "; ".join(delays))
    holds = [f"{o.job.name} {o.hold[0]} {o.hold[1]:+.0f}" for o in outcomes]
    print(
        "\nthe hold between samples (the run's, and the -2 log likelihood change with the "
        "other; below -4 the other fits better, decision 0071): " + "; ".join(holds)
    )
    if failed:
        print("\n" + "\n".join(failed))
    print(
        f"\n({time.perf_counter() - start:.0f} s wall, of which {flown:.0f} s flying or "
        f"reading the flights; {sum(o.seconds for o in outcomes):.0f} s of estimation over "
        f"{args.jobs} processes, {sum(o.cpu_seconds for o in outcomes):.0f} s of CPU; each "
        "record's table in out/validation/tables/)"
    )
    return 0


SET = [m.aircraft.model for m in vf.SET] + list(OTHERS)
"""The set's members, in the order reports list them."""
ORDER = SET + [m.aircraft.model for m in vf.INDEPENDENT_SET]
"""The aircraft in the order the tables list them."""


def _priority(job: Job) -> tuple[bool, str, int]:
    """The noisy records first, a condition at a time over every aircraft: a run stopped
    early (its outcomes are kept one by one) has covered the set evenly."""
    return "clean" in job.condition, job.condition, ORDER.index(job.aircraft)


def estimate(todo: list[Job], workers: int, kept: Path, resume: bool = False) -> list[Outcome]:
    """Run the records in `workers` processes, each outcome kept in `kept` as it comes
    (what an earlier run kept there is removed first, so that `--again` reports the runs
    of the folders it is given; with `resume`, the outcomes kept there of records in
    `todo` are taken as they are and only the others run)."""
    kept.mkdir(parents=True, exist_ok=True)
    outcomes: list[Outcome] = []
    names = {job.name for job in todo}
    for old in kept.glob("*.pickle"):
        if resume and old.stem in names:
            outcomes.append(pickle.loads(old.read_bytes()))
        else:
            old.unlink()
    done_names = {o.job.name for o in outcomes}
    todo = [job for job in todo if job.name not in done_names]
    with ProcessPoolExecutor(workers) as pool:
        for done in as_completed([pool.submit(run_job_kept, job) for job in todo]):
            outcome = done.result()
            (kept / f"{outcome.job.name}.pickle").write_bytes(pickle.dumps(outcome))
            outcomes.append(outcome)
    return outcomes


if __name__ == "__main__":
    sys.exit(main())
