"""The JSBSim mission set through the estimator as a user would run it: no vane, thrust not
logged, airframe files of geometry and a spec-sheet propeller (issue 53's JSBSim targets).

    ./run bench mission_accuracy [--seeds 1] [--jobs 2] [--models ...] [--air windy calm]
                                 [--log bin|ulg] [--level-bank-deg 5] [--thrust spec|logged]
                                 [--refine auto|none|...] [--cases turns level]
                                 [--advised] [--resume] [--again]

The flights are benchmarks/jsbsim_missions.py's (flown here where --out lacks them): six
aircraft, windy and calm, each an 8-minute circuit of legs and turns of 20-35 degrees,
multisteps on some legs, a climb and a descent on the throttle. Each flight's DataFlash
log (or PX4 log: --log ulg) is read as `offline` reads it, the AHRS's angle of attack
dropped (no vane: alpha from the climb rate, decision 0049; a PX4 log has none), and
estimated with its airframe file as written (no [filter] table: the project's defaults),
both filters and `refine` (auto), twice:

- "turns": every frame the defaults use (segments within [filter] bank_limit_deg);
- "level": the wings-level legs only (--level-bank-deg: the bank limit that cuts the
  flight into its level segments, `filter.bank_limit_deg` set to it).

Judged with the sigma and the marks the run shows its user against the structure's best
fit (benchmarks/best_fit.py) to the calm flight's noise-free signals with JSBSim's thrust
(NAME.clean.npz): output error over the calm flight in 60 s pieces, each from its own
fitted state (fit_in_pieces), its inputs as flown, the windy flight judged against its
calm twin's (the gusts are not in the structure). One target for both cases: what the
structure holds over the mission. The same figures against the reference ([truth]:
JSBSim's coefficients fitted sample by sample) follow. Per estimator and case:

- within 3σ: the share of the coefficients whose error is within 3 of the sigma shown
  (all ten; and the well-excited ones, realdata.WELL_EXCITED, as the validation set);
- mean z²: their squared error in sigmas, averaged;
- identified beyond 10 %: of the coefficients marked "identified", how many lie more than
  10 % from the best fit (coefficients of the best fit within realdata.NEAR_ZERO of zero:
  judged by 3σ instead);
- turns against level: per coefficient, the median over the flights of the ratio of the
  sigmas shown and of the absolute errors (below 1: the turns helped).

Targets (issue 53): within 3σ >= 90 %, mean z² <= 2, no identified coefficient beyond
10 %; the turns at least as accurate as the level legs, with smaller sigma where they add
information. Outcomes are kept in --out/accuracy_spec/ (accuracy_logged/ with --thrust
logged) as they come; --again reports them, --resume runs only the rest. Decision 0061
has the figures and what the misses come from.

--advised runs each flight as a user who follows the warnings would: first with the
filter-error fit, then the filters again with every setting that run advises (the JSON's
diagnostics.advised_settings, decision 0085), judged as "EKF advised" and "IEKF advised"
beside the first run's figures, and once more with the process noise the fit found
whether advised or not ("FE noise": it is advised only where the fit's residuals are
white, decision 0087); kept in accuracy_spec_advised/.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
import pickle
import sys
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jsbsim_missions as jm  # benchmarks/: the script's dir is on sys.path
import numpy as np
import record
from best_fit import _outputs
from realdata import NEAR_ZERO, WELL_EXCITED
from scipy.optimize import least_squares
from validation import Found, Job, Outcome, _table, scored

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import REFINE_METHODS, AircraftConfig, load_config
from gcs_estimator.estimation.estimator import FILTER_KINDS
from gcs_estimator.ingest.logs.reader import load_flight
from gcs_estimator.model import compiled  # noqa: F401  (registers the equations with numba)
from gcs_estimator.model.aircraft import build_model
from gcs_estimator.model.channels import N_FLIGHT, Channel
from gcs_estimator.outputs.diagnosis import (
    COLOUR_LIMIT,
    advised_settings,
    process_noise_settings,
    set_arguments,
    set_argv,
)
from gcs_estimator.runtime.flights import limits_of, source_of
from gcs_estimator.runtime.session import Session
from gcs_estimator.uncertainty.metrics import IDENTIFIED
from gcs_estimator.uncertainty.result import VehicleResult

ADVISED = tuple(f"{k} advised" for k in FILTER_KINDS)
"""--advised: each filter of the run made with every setting the first run advised."""
FE_NOISE = tuple(f"{k} FE noise" for k in FILTER_KINDS)
"""--advised: each filter run with the advice and the process noise the filter-error fit
found, advised or not (diagnosis.process_noise_settings; decision 0087)."""
ESTIMATORS = (*FILTER_KINDS, "refine", *ADVISED, *FE_NOISE)
CASES = ("turns", "level")
TARGET_WITHIN = 90.0
TARGET_MSZ = 2.0
TARGET_CLOSE_PCT = 10.0
"""Issue 53's JSBSim mission targets: within 3σ, mean z², identified within 10 %."""
LEVEL_BANK_DEG = 5.0
"""The bank limit that leaves the wings-level legs only (the autopilot's legs hold the
bank within about a degree; its turns pass 5 degrees within a second or two)."""
MEASURED_THRUST = 'propulsion.model="measured"'
"""--thrust logged: the filters take JSBSim's thrust as a measured input (a diagnosis:
what the spec sheet's propeller costs)."""
BEST_FIT_VERSION = 1
"""Bump when the best fit changes: NAME.best_fit.json is keyed on it and the flight's."""


# ------------------------------------------------------------------------- the best fit


def best_fit_config_overrides() -> list[str]:
    """The airframe file as the best fit reads it: JSBSim's thrust as the input (not the
    spec sheet's propeller), sensors at the CG without biases (the clean signals')."""
    return [MEASURED_THRUST, "sensors.vane_x_m=0", "sensors.bias_states=[]"]


PIECE_S = 60.0
"""The best fit's pieces [s]: each flies from its own initial state (fitted), the
coefficients shared (best_fit's output error, in pieces)."""


def fit_in_pieces(
    config: AircraftConfig,
    t: FloatArray,
    inputs: FloatArray,
    clean: FloatArray,
    start: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """The structure's best fit to a calm flight's noise-free observations `clean` [N x 8]
    (best_fit.best_fit's output error, each channel weighted by its sensor sigma) over
    pieces of PIECE_S (and apart where frames are left out between), each piece's
    initial state free: over the whole eight minutes the
    open-loop model drifts from the flight the autopilot held (on the c182 a whole-flight
    fit left V and theta 1.2 and 1.6 sensor sigmas RMS and put CLa at 7.1, the pieces'
    fit 0.9 and 1.0 and 5.9, the sample-by-sample reference 5.4), and that drift says
    nothing of the coefficients. inputs [N x 6]: elevator, thrust [N], density, bank, roll
    and yaw rate; `start`: the coefficients the fit starts from. Returns the coefficients
    and the RMS residual per channel in sensor sigmas."""
    model = build_model(config, gust_states=False)
    u = np.ascontiguousarray(np.array([model.inputs(row) for row in inputs]))
    g = np.zeros((len(t), 2))
    step = np.diff(t, prepend=-np.inf)
    gap = step > 1.5 * np.median(step[1:])  # frames left out between (a piece each side)
    firsts = np.flatnonzero((np.diff(np.floor((t - t[0]) / PIECE_S), prepend=-1.0) > 0) | gap)
    bounds = [*firsts.tolist(), len(t)]
    pieces = list(itertools.pairwise(bounds))
    beta0 = np.asarray(start, float)
    nc, nf = len(beta0), N_FLIGHT
    z_scale = np.concatenate(
        [np.maximum(np.abs(beta0), 1e-3)]
        + [np.maximum(np.abs(clean[a, :nf]), 1e-3) for a, _ in pieces]
    )
    z0 = np.concatenate([beta0] + [clean[a, :nf] for a, _ in pieces]) / z_scale
    weight = 1.0 / np.array(config.filter.measurement_sigma)
    tt = np.ascontiguousarray(t, dtype=float)

    def residual(z: FloatArray) -> FloatArray:
        x = z * z_scale
        out = []
        for j, (a, b) in enumerate(pieces):
            x0 = model.augment(x[nc + nf * j : nc + nf * (j + 1)], x[:nc])
            y = _outputs(x0, tt[a:b], u[a:b], g[a:b], model.arrays)
            out.append(((clean[a:b] - y) * weight).ravel())
        return np.concatenate(out)

    sparsity = np.zeros((clean.size, len(z0)), bool)
    sparsity[:, :nc] = True
    width = clean.shape[1]
    for j, (a, b) in enumerate(pieces):
        sparsity[a * width : b * width, nc + nf * j : nc + nf * (j + 1)] = True
    sol = least_squares(
        residual, z0, jac_sparsity=sparsity, x_scale="jac", method="trf", xtol=1e-10
    )
    rms = np.sqrt(np.mean(residual(sol.x).reshape(clean.shape) ** 2, axis=0))
    return sol.x[:nc] * z_scale[:nc], rms


def fit_flight(out: Path, name: str) -> dict[str, Any]:
    """The structure's best fit to flight `name`'s noise-free signals (fit_in_pieces;
    cached in NAME.best_fit.json, keyed on the flight's key and BEST_FIT_VERSION)."""
    summary = json.loads((out / f"{name}.json").read_text(encoding="utf-8"))
    key = f"{summary.get('key')}:{BEST_FIT_VERSION}"
    cached = out / f"{name}.best_fit.json"
    if cached.exists():
        kept: dict[str, Any] = json.loads(cached.read_text(encoding="utf-8"))
        if kept.get("key") == key:
            return kept
    start = time.perf_counter()
    config = load_config(out / f"{name}.toml", best_fit_config_overrides())
    c = np.load(out / f"{name}.clean.npz")
    inputs = np.column_stack([c[k] for k in ("de", "thrust", "rho", "phi", "p", "r")])
    clean = np.column_stack([c[k] for k in OBS_KEYS])
    best, rms = fit_in_pieces(config, c["t"], inputs, clean, np.array(config.truth))
    fitted = {
        "key": key,
        "best_fit": dict(zip(config.coefficient_names, best.tolist(), strict=True)),
        "residual_sigmas": rms.tolist(),
        "reference": dict(zip(config.coefficient_names, config.truth or (), strict=True)),
        "seconds": time.perf_counter() - start,
    }
    cached.write_text(json.dumps(fitted, indent=1), encoding="utf-8")
    return fitted


OBS_KEYS = ("V", "alpha", "theta", "q", "qdot", "a_x", "a_z", "h_dot")
"""NAME.clean.npz's arrays in the observation channels' order."""


# ------------------------------------------------------------------------------ the runs


@dataclass(frozen=True)
class Flight:
    """One mission flight to estimate: its log, airframe file and target."""

    name: str
    model: str
    air: str
    seed: int
    log: str
    goal: dict[str, float]


def jobs_of(flights: list[Flight], args: argparse.Namespace) -> list[Job]:
    """Each flight in each case, as the validation set's Job (condition: AIR_CASE)."""
    out = []
    for f in flights:
        for case in args.cases:
            over = list(args.set)
            if args.thrust == "logged":
                over.append(MEASURED_THRUST)
            if case == "level":
                over.append(f"filter.bank_limit_deg={args.level_bank_deg:g}")
            name = f"{f.name}_{case}"
            condition = f"{f.air}_{case}"
            out.append(
                Job(name, f.model, condition, tuple(over), args.refine, f.goal, f.log, f.seed)
            )
    return out


def _estimated(job: Job, extra: list[str]) -> tuple[VehicleResult, str]:
    """The filters over one flight's log with the job's overrides and `extra`, its alpha
    dropped, its segments as the defaults (or the level case's bank limit) find them; the
    vehicle's result and the segment plan's summary."""
    airframe = Path(job.csv).with_name(Path(job.csv).stem + ".toml")
    config = load_config(airframe, [*job.overrides, *extra])
    _, rec, _ = load_flight(job.csv, config)
    rec.measurements[:, Channel.ALPHA] = np.nan  # no vane: the AHRS's estimate dropped
    if config.propulsion.model == "measured":  # --thrust logged: JSBSim's, as if logged
        clean = np.load(Path(job.csv).with_name(Path(job.csv).stem + ".clean.npz"))
        rec.inputs[:, 1] = np.interp(rec.t_s, clean["t"], clean["thrust"])
    source = source_of([rec], [Path(job.csv).name], limits_of(config))
    session = Session(config)
    session.run(source)
    plan = source.plan
    return session.results()[1], "" if plan is None else plan.summary()


def run_job(job: Job) -> Outcome:
    """The filters and `refine` over one flight's log (_estimated); judged as
    validation's."""
    start, cpu = time.perf_counter(), time.process_time()
    vehicle, note = _estimated(job, [])
    names = vehicle.result.names
    assert job.goal is not None
    goal = np.array([job.goal[n] for n in names])
    out, found, _ = scored(job, vehicle, goal)
    out.table = note + "\n\n" + _table(names, goal, found)
    out.seconds = time.perf_counter() - start
    out.cpu_seconds = time.process_time() - cpu
    return out


def run_advised(job: Job) -> Outcome:
    """--advised: the flight as run_job runs it with the filter-error fit, then the
    filters again with every setting that run's warnings advise (its JSON's
    diagnostics.advised_settings: sensor biases, noisier channels' sigmas, the process
    noise and input delay the fit finds; decision 0085), judged as "EKF advised" and
    "IEKF advised" (the first run's figures where nothing is advised); and once more with
    the process noise the fit found added, advised or not ("EKF FE noise", "IEKF FE
    noise"; decision 0087: it is advised only where the fit's residuals are white)."""
    start, cpu = time.perf_counter(), time.process_time()
    first = dataclasses.replace(job, refine="filter-error")
    vehicle, note = _estimated(first, [])
    names = vehicle.result.names
    assert job.goal is not None
    goal = np.array([job.goal[n] for n in names])
    out, found, refined = scored(first, vehicle, goal)
    out.advice = advised_settings(vehicle, refined)
    noise = out.advice | process_noise_settings(vehicle, refined)
    out.advice_noise = noise
    if refined is not None:
        out.advice_colour = float(np.nanmax(refined.residual_colour))
    runs = {"advised": out.advice, "FE noise": noise}
    by_settings: dict[str, tuple[Outcome, Found]] = {}  # the same settings: the same run
    made: dict[str, tuple[Outcome, Found]] = {}
    for label, settings in runs.items():
        key = json.dumps(settings, sort_keys=True)
        if key not in by_settings and settings:
            vehicle, _ = _estimated(job, set_argv(settings)[1::2])
            again, advised, _ = scored(dataclasses.replace(job, refine="none"), vehicle, goal)
            by_settings[key] = again, advised
        elif key not in by_settings:
            by_settings[key] = out, {k: found[k] for k in FILTER_KINDS}
        made[label] = by_settings[key]
    for label, (again, advised) in made.items():
        for k in FILTER_KINDS:
            out.z[f"{k} {label}"] = again.z[k]
            out.marks[f"{k} {label}"] = again.marks[k]
            out.parts[f"{k} {label}"] = again.parts[k]
            found[f"{k} {label}"] = advised[k]
    text = "".join(f"{label}: {set_arguments(s) or 'nothing'}\n" for label, s in runs.items())
    out.table = f"{note}\n\n{text}\n" + _table(names, goal, found)
    out.seconds = time.perf_counter() - start
    out.cpu_seconds = time.process_time() - cpu
    return out


# --------------------------------------------------------------------------- the figures


@dataclass
class Scores:
    """One estimator's figures over some outcomes."""

    z: list[float]
    z_well: list[float]
    identified: int
    identified_far: int
    records: int

    @property
    def within(self) -> float:
        return 100.0 * float(np.mean(np.abs(self.z) < 3.0)) if self.z else math.nan

    @property
    def within_well(self) -> float:
        return 100.0 * float(np.mean(np.abs(self.z_well) < 3.0)) if self.z_well else math.nan

    @property
    def msz(self) -> float:
        return float(np.mean(np.square(self.z))) if self.z else math.nan

    @property
    def msz_well(self) -> float:
        return float(np.mean(np.square(self.z_well))) if self.z_well else math.nan

    def meets(self) -> str:
        ok = self.within >= TARGET_WITHIN and self.msz <= TARGET_MSZ and self.identified_far == 0
        return "yes" if ok else "no"


def _far(o: Outcome, k: str, i: int) -> bool:
    """Whether coefficient i lies beyond TARGET_CLOSE_PCT of its target (beyond 3σ for a
    target near zero)."""
    goal = o.job.goal
    assert goal is not None
    g = goal[o.names[i]]
    if abs(g) <= NEAR_ZERO:
        return abs(o.z[k][i]) > 3.0
    est = o.parts[k]["estimate"][i]
    return bool(abs(est - g) > TARGET_CLOSE_PCT / 100.0 * abs(g))


def scores(outcomes: list[Outcome], k: str) -> Scores:
    s = Scores([], [], 0, 0, 0)
    for o in outcomes:
        if k not in o.z:
            continue
        s.records += 1
        s.z += o.z[k]
        s.z_well += [z for n, z in zip(o.names, o.z[k], strict=True) if n in WELL_EXCITED]
        ident = [i for i, m in enumerate(o.marks[k]) if m == IDENTIFIED]
        s.identified += len(ident)
        s.identified_far += sum(_far(o, k, i) for i in ident)
    return s


def against_reference(outcomes: list[Outcome], out: Path) -> list[Outcome]:
    """The outcomes judged against JSBSim's coefficients fitted sample by sample on the
    structure's regressors (the airframe file's [truth], kept beside each calm flight's
    best fit) instead of the best fit: where the structure misses JSBSim's aerodynamics
    the two targets differ, and the first says what the trajectories hold, the second
    what the aerodynamics are."""
    rescored = []
    for o in outcomes:
        twin = jm.record_name(o.job.aircraft, "calm", o.job.seed)
        path = out / f"{twin}.best_fit.json"
        if not path.exists():
            continue
        ref = json.loads(path.read_text(encoding="utf-8"))["reference"]
        r = Outcome(dataclasses.replace(o.job, goal=ref), o.names)
        r.marks, r.parts = o.marks, o.parts
        g = np.array([ref[n] for n in o.names])
        for k, parts in o.parts.items():
            if k in o.z:
                est, shown = np.array(parts["estimate"]), np.array(parts["shown"])
                r.z[k] = ((est - g) / shown).tolist()
        rescored.append(r)
    return rescored


def print_targets(outcomes: list[Outcome], target: str = "the best fit") -> None:
    print(
        f"\n## Against {target}\n\nall ten coefficients (and the well-excited ones) within "
        "3 shown σ of it, their mean z², coefficients marked identified that lie "
        f"beyond {TARGET_CLOSE_PCT:g} % of it; targets: within 3σ >= {TARGET_WITHIN:g} %, "
        f"mean z² <= {TARGET_MSZ:g}, none identified beyond {TARGET_CLOSE_PCT:g} %\n"
    )
    print(
        "| case | air | records | estimator | within 3σ | mean z² | within 3σ (well-excited) "
        f"| mean z² (well-excited) | identified beyond {TARGET_CLOSE_PCT:g} % | targets met |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    airs = sorted({o.job.condition.split("_")[0] for o in outcomes})
    for case in CASES:
        for air in [*airs, "both"]:
            group = [
                o
                for o in outcomes
                if o.job.condition.endswith(case)
                and (air == "both" or o.job.condition.startswith(air))
            ]
            for k in ESTIMATORS:
                s = scores(group, k)
                if not s.records:
                    continue
                print(
                    f"| {case} | {air} | {s.records} | {k} | {s.within:.0f} % | {s.msz:.3g} | "
                    f"{s.within_well:.0f} % | {s.msz_well:.3g} | "
                    f"{s.identified_far}/{s.identified} | {s.meets()} |"
                )


STRICTER = (0.10, 0.05, 0.10 / 3.0)
"""sigma / |estimate| an "identified" mark could require: the mark's own (a tenth), two
sigma within a tenth, three sigma within a tenth (decision 0076)."""


def print_stricter_marks(outcomes: list[Outcome]) -> None:
    """Against the best fit, per case and filter: the coefficients marked identified, and
    those of them beyond TARGET_CLOSE_PCT or beyond 3 sigma, had "identified" required
    each of STRICTER (a mark identified now, with its shown sigma within the share: the
    other conditions of the mark are the same)."""
    print(
        '\n## Had "identified" asked for a smaller sigma\n\nagainst the best fit: of the '
        "coefficients marked identified whose shown σ is at most the share of the estimate "
        f"named, how many lie beyond {TARGET_CLOSE_PCT:g} % of it and how many beyond 3σ "
        "(beyond 10 % / beyond 3σ / identified)\n"
    )
    heads = " | ".join(f"σ ≤ {100 * th:.3g} %" for th in STRICTER)
    print(f"| case | estimator | {heads} |")
    print("|---|---|" + "---|" * len(STRICTER))
    for case in CASES:
        group = [o for o in outcomes if o.job.condition.endswith(case)]
        for k in ESTIMATORS:
            cells = []
            for th in STRICTER:
                n = far = wide = 0
                for o in group:
                    if k not in o.z:
                        continue
                    est = np.asarray(o.parts[k]["estimate"])
                    shown = np.asarray(o.parts[k]["shown"])
                    for i, mark in enumerate(o.marks[k]):
                        if mark == IDENTIFIED and shown[i] <= th * abs(est[i]):
                            n += 1
                            far += _far(o, k, i)
                            wide += abs(o.z[k][i]) > 3.0
                cells.append(f"{far} / {wide} / {n}")
            if any(k in o.z for o in group):
                print(f"| {case} | {k} | " + " | ".join(cells) + " |")


def print_by_aircraft(outcomes: list[Outcome]) -> None:
    print("\n## By aircraft (turns case)\n")
    present = [k for k in ESTIMATORS if any(k in o.z for o in outcomes)]
    head = ["aircraft", "records"]
    head += [f"{k} {c}" for k in present for c in ("within 3σ", "mean z²", "ident. far")]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for model in jm.MODELS:
        group = [
            o for o in outcomes if o.job.aircraft == model and o.job.condition.endswith("turns")
        ]
        if not group:
            continue
        row = [model, str(len(group))]
        for k in present:
            s = scores(group, k)
            row += [f"{s.within:.0f} %", f"{s.msz:.3g}", f"{s.identified_far}/{s.identified}"]
        print("| " + " | ".join(row) + " |")


def pairs(outcomes: list[Outcome]) -> list[tuple[Outcome, Outcome]]:
    """(turns, level) outcomes of one flight."""
    by = {o.job.name: o for o in outcomes}
    out = []
    for name, o in by.items():
        if name.endswith("_turns") and name[: -len("turns")] + "level" in by:
            out.append((o, by[name[: -len("turns")] + "level"]))
    return out


def print_turns_against_level(outcomes: list[Outcome]) -> None:
    """Per estimator and coefficient: median over flights of sigma (turns / level) and of
    |error| (turns / level), and the mean z² of each case."""
    both = pairs(outcomes)
    if not both:
        return
    names = both[0][0].names
    print(
        "\n## Turns included against the level legs only\n\nper coefficient, the median over "
        f"{len(both)} flights of the sigma shown with the turns over that of the level legs "
        "only, then of the absolute error against the best fit (turns / level; below 1: the "
        "turns helped); the last columns: mean z² of each case. Then the filter's covariance "
        "sigma (turns / level), the sigma shown over the flights where neither case's carries "
        "the prior an uninformed alpha adds (decision 0060; in brackets how many), and in how "
        "many flights each case's does\n"
    )
    print("| estimator | ratio | " + " | ".join(names) + " | all | z² turns | z² level |")
    print("|---|---|" + "---|" * (len(names) + 3))
    for k in ESTIMATORS:
        got = [(t, lv) for t, lv in both if k in t.z and k in lv.z]
        if not got:
            continue
        sig = np.array([np.array(t.parts[k]["shown"]) / lv.parts[k]["shown"] for t, lv in got])
        err = np.array([np.abs(np.array(t.z[k]) * t.parts[k]["shown"]) for t, _ in got]) / np.array(
            [np.abs(np.array(lv.z[k]) * lv.parts[k]["shown"]) for _, lv in got]
        )
        zt = float(np.mean([np.square(t.z[k]) for t, _ in got]))
        zl = float(np.mean([np.square(lv.z[k]) for _, lv in got]))
        for label, r in (("σ", sig), ("abs. error", err)):
            cells = " | ".join(f"{x:.2f}" for x in np.median(r, axis=0))
            print(f"| {k} | {label} | {cells} | {np.median(r):.2f} | {zt:.3g} | {zl:.3g} |")
        cov = np.array(
            [np.array(t.parts[k]["covariance"]) / lv.parts[k]["covariance"] for t, lv in got]
        )
        cells = " | ".join(f"{x:.2f}" for x in np.median(cov, axis=0))
        print(f"| {k} | covariance σ | {cells} | {np.median(cov):.2f} | | |")
        prior_t = np.array([alpha_prior_in_sigma(t, k) for t, _ in got])
        prior_l = np.array([alpha_prior_in_sigma(lv, k) for _, lv in got])
        free = ~(prior_t | prior_l)
        cells = " | ".join(
            f"{np.median(sig[free[:, i], i]):.2f} ({free[:, i].sum()})" if free[:, i].any() else "-"
            for i in range(len(names))
        )
        print(f"| {k} | σ, neither with alpha's prior (flights) | {cells} | | | |")
        cells = " | ".join(
            f"{prior_t[:, i].sum()} / {prior_l[:, i].sum()}" for i in range(len(names))
        )
        print(f"| {k} | alpha's prior in σ (flights: turns / level) | {cells} | | | |")


def alpha_prior_in_sigma(o: Outcome, k: str) -> np.ndarray:
    """Per coefficient, whether the sigma estimator k's run showed carries the prior an
    uninformed alpha adds (decision 0060: no vane, and a climb rate in air that moved, or
    that the model's misses made look so): its structure part at least the coefficient's
    prior sigma. Such a sigma is the prior's whatever the flight held."""
    airframe = Path(o.job.csv).with_name(Path(o.job.csv).stem + ".toml")
    config = load_config(airframe, list(o.job.overrides))
    prior = dict(
        zip(config.coefficient_names, config.filter.initial_sigma.coefficients, strict=True)
    )
    return np.array(o.parts[k]["structure"]) >= np.array([prior[n] for n in o.names])


def print_parts(outcomes: list[Outcome], k: str = "EKF") -> None:
    """What filter k's shown sigma is made of, per case: each part over the shown sigma
    (median over the records; the movement part as its factor)."""
    if not outcomes:
        return
    names = outcomes[0].names
    print(
        f"\n## What the {k}'s sigma is made of\n\neach part of the shown sigma in its units "
        "(median over the records; movement: the factor on the covariance's)\n"
    )
    print("| case | part | " + " | ".join(names) + " |")
    print("|---|---|" + "---|" * len(names))
    for case in CASES:
        group = [o for o in outcomes if o.job.condition.endswith(case) and k in o.parts]
        labels = dict.fromkeys(label for o in group for label in o.parts[k])
        for label in labels:
            if label in ("shown", "estimate"):
                continue
            rows = [
                np.array(o.parts[k][label])
                / (1.0 if label == "movement" else np.array(o.parts[k]["shown"]))
                for o in group
                if label in o.parts[k]
            ]
            cells = " | ".join(f"{x:.2g}" for x in np.median(rows, axis=0))
            print(f"| {case} | {label} | {cells} |")


def print_misses(outcomes: list[Outcome]) -> None:
    """Every coefficient marked identified that lies beyond the 10 % or beyond 3σ."""
    print(
        f"\n## Identified beyond {TARGET_CLOSE_PCT:g} % or beyond 3σ: estimate, target, z, "
        "the sigma's parts\n"
    )
    print(
        "| record | estimator | coefficient | estimate | target | error % | z | σ shown "
        "| parts (σ units) |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for o in outcomes:
        goal = o.job.goal
        assert goal is not None
        for k, marks in o.marks.items():
            for i, mark in enumerate(marks):
                z = o.z[k][i]
                if mark != IDENTIFIED or not (_far(o, k, i) or abs(z) > 3.0):
                    continue
                g = goal[o.names[i]]
                est = o.parts[k]["estimate"][i]
                pct = 100.0 * (est - g) / abs(g) if abs(g) > NEAR_ZERO else math.nan
                parts = ", ".join(
                    f"{label} {v[i]:.2g}"
                    if label == "movement"
                    else f"{label} {v[i] / o.parts[k]['shown'][i]:.2g}"
                    for label, v in o.parts[k].items()
                    if label not in ("shown", "estimate")
                )
                print(
                    f"| {o.job.name} | {k} | {o.names[i]} | {est:.4g} | {g:.4g} | {pct:+.1f} | "
                    f"{z:+.1f} | {o.parts[k]['shown'][i]:.2g} | {parts} |"
                )


def print_advice(outcomes: list[Outcome]) -> None:
    """--advised: what each record's first run advised (its `--set` arguments)."""
    if not any(k in o.z for o in outcomes for k in ADVISED):
        return
    print(
        "\n## What each flight's first run advised, and the process noise its filter-error "
        "fit found\n\nadvised: the settings applied in the advised run; FE noise: the "
        "densities the fit found (applied with the advice in the FE noise run), advised "
        "only where the fit's residuals are white, their colour at most "
        f"{COLOUR_LIMIT:g} on every channel (decision 0087)\n"
    )
    print("| record | advised | FE noise | residual colour (largest) |")
    print("|---|---|---|---|")
    for o in outcomes:
        noise = {k: v for k, v in o.advice_noise.items() if k not in o.advice}
        print(
            f"| {o.job.name} | {set_arguments(o.advice) or 'nothing'} | "
            f"{set_arguments(noise) or '-'} | {o.advice_colour:.3g} |"
        )


def print_best_fits(fits: dict[str, dict[str, Any]]) -> None:
    """Each calm flight's best fit against the sample-by-sample reference, and how well
    the structure reproduces the flight (the fit's residual in sensor sigmas)."""
    print(
        "\n## The targets: each calm flight's best fit (reference: JSBSim's coefficients "
        "fitted sample by sample; residual: RMS per channel in sensor sigmas)\n"
    )
    for name, fit in fits.items():
        pairs_ = ", ".join(
            f"{n} {b:.4g} ({fit['reference'][n]:.4g})" for n, b in fit["best_fit"].items()
        )
        res = ", ".join(f"{r:.2g}" for r in fit["residual_sigmas"])
        print(f"- {name}: {pairs_}; residual {res}; fitted in {fit['seconds']:.0f} s")


# ------------------------------------------------------------------------------- driving


def flights_of(
    args: argparse.Namespace, pool: ProcessPoolExecutor
) -> tuple[list[Flight], dict[str, dict[str, Any]]]:
    """The mission set flown (where --out lacks it) and each calm flight's best fit."""
    out = Path(args.out)
    seeds = tuple(range(1, args.seeds + 1))
    jm.generate(seeds, args.jobs, out, args.models)
    calm = [jm.record_name(m, "calm", s) for m in args.models for s in seeds]
    fits = dict(zip(calm, pool.map(fit_flight, [out] * len(calm), calm), strict=True))
    flights = []
    for m in args.models:
        for s in seeds:
            goal = fits[jm.record_name(m, "calm", s)]["best_fit"]
            for air in args.air:
                name = jm.record_name(m, air, s)
                log = out / f"{name}.{args.log}"
                flights.append(Flight(name, m, air, s, str(log), goal))
    return flights, fits


def kept_fits(out: Path, args: argparse.Namespace) -> dict[str, dict[str, Any]]:
    """The calm flights' best fits as --out keeps them (--again: none is fitted anew)."""
    calm = [jm.record_name(m, "calm", s) for m in args.models for s in range(1, args.seeds + 1)]
    paths = [out / f"{name}.best_fit.json" for name in calm]
    return {
        name: json.loads(p.read_text(encoding="utf-8"))
        for name, p in zip(calm, paths, strict=True)
        if p.exists()
    }


PRIORITY = ("c182", "T37", "t6texan2", "737", "DHC6", "A4")
"""The order the flights are run in, propeller and jet in turn: a run stopped early (its
outcomes are kept one by one) has covered both kinds of propulsion."""


def _priority(job: Job) -> tuple[int, bool, int, bool]:
    """Seed by seed, calm before windy, each flight's two cases one after the other (a
    run stopped early has whole pairs to compare)."""
    air = job.condition.split("_")[0]
    return job.seed, air != "calm", PRIORITY.index(job.aircraft), job.condition.endswith("level")


def estimate(
    todo: list[Job],
    pool: ProcessPoolExecutor,
    kept: Path,
    resume: bool = False,
    job_runner: Callable[[Job], Outcome] = run_job,
) -> list[Outcome]:
    """Run the jobs with job_runner, each outcome kept in `kept` as it comes (the folder
    emptied first; resume: the outcomes kept there stay, and their jobs are not run
    again)."""
    kept.mkdir(parents=True, exist_ok=True)
    outcomes = []
    for old in kept.glob("*.pickle"):
        if resume:
            outcomes.append(pickle.loads(old.read_bytes()))
        else:
            old.unlink()
    done_names = {o.job.name for o in outcomes}
    todo = [j for j in todo if j.name not in done_names]
    for done in as_completed([pool.submit(job_runner, job) for job in todo]):
        o = done.result()
        (kept / f"{o.job.name}.pickle").write_bytes(pickle.dumps(o))
        outcomes.append(o)
        print(f"  {o.job.name}: {o.seconds:.0f} s {o.failed}", file=sys.stderr, flush=True)
    return outcomes


def run(args: argparse.Namespace) -> int:
    start = time.perf_counter()
    kept = Path(args.out) / f"accuracy_{args.thrust}{'_advised' if args.advised else ''}"
    fits: dict[str, dict[str, Any]] = {}
    if args.again:
        outcomes = [pickle.loads(p.read_bytes()) for p in kept.glob("*.pickle")]
        fits = kept_fits(Path(args.out), args)
    else:
        with ProcessPoolExecutor(args.jobs) as pool:
            flights, fits = flights_of(args, pool)
            prepared = time.perf_counter() - start
            print(f"({prepared:.0f} s flying or fitting the targets)", file=sys.stderr)
            todo = sorted(jobs_of(flights, args), key=_priority)
            runner = run_advised if args.advised else run_job
            outcomes = estimate(todo, pool, kept, args.resume, runner)
    outcomes.sort(key=lambda o: o.job.name)
    tables = kept / "tables"
    tables.mkdir(parents=True, exist_ok=True)
    for o in outcomes:
        (tables / f"{o.job.name}.md").write_text(o.table + "\n", encoding="utf-8")
    print(
        f"{len(outcomes)} records ({args.log} logs, no alpha, thrust: {args.thrust}); overrides: "
        f"{' '.join(args.set) or 'none (the defaults)'}; level case: bank limit "
        f"{args.level_bank_deg:g} deg"
    )
    if args.again:
        print(
            "\n(--again: the outcomes an earlier run kept under --out, reported by this "
            "revision's code; the run's revision is the record's before it)"
        )
    print_advice(outcomes)
    print_targets(outcomes)
    print_targets(against_reference(outcomes, Path(args.out)), "the reference")
    print_stricter_marks(outcomes)
    print_by_aircraft(outcomes)
    print_turns_against_level(outcomes)
    print_parts(outcomes)
    print_misses(outcomes)
    if fits:
        print_best_fits(fits)
    failed = [f"{o.job.name}: {o.failed}" for o in outcomes if o.failed]
    if failed:
        print("\n" + "\n".join(failed))
    print(
        f"\n({time.perf_counter() - start:.0f} s wall; {sum(o.seconds for o in outcomes):.0f} s "
        f"of estimation over {args.jobs} processes, {sum(o.cpu_seconds for o in outcomes):.0f} "
        f"s of CPU; each record's table in {kept.name}/tables/ under --out)"
    )
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seeds", type=int, default=1, help="wind, turbulence and noise seeds 1..N")
    ap.add_argument("--jobs", type=int, default=2, help="processes (flying and estimating)")
    ap.add_argument("--out", default=str(jm.OUT), help="where the flights are kept")
    ap.add_argument("--models", nargs="+", default=list(jm.MODELS), choices=jm.MODELS)
    ap.add_argument("--air", nargs="+", default=list(jm.AIRS), choices=jm.AIRS)
    ap.add_argument("--log", choices=("bin", "ulg"), default="bin", help="which log to read")
    ap.add_argument(
        "--thrust",
        choices=("spec", "logged"),
        default="spec",
        help="spec: the airframe file's spec-sheet propeller, the throttle as logged (the "
        "target's case); logged: JSBSim's thrust given as measured (a diagnosis)",
    )
    ap.add_argument(
        "--level-bank-deg",
        type=float,
        default=LEVEL_BANK_DEG,
        help="the level case's bank limit (default %(default)s)",
    )
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a config override for every record",
    )
    ap.add_argument("--refine", choices=(*REFINE_METHODS, "none"), default="auto")
    ap.add_argument(
        "--cases", nargs="+", default=list(CASES), choices=CASES, help="which cases to run"
    )
    ap.add_argument(
        "--advised",
        action="store_true",
        help="run each flight with the filter-error fit, then the filters again with what "
        'its warnings advise ("EKF advised", "IEKF advised"; kept in accuracy_*_advised/)',
    )
    ap.add_argument("--again", action="store_true", help="report the outcomes kept under --out")
    ap.add_argument(
        "--resume",
        action="store_true",
        help="keep the outcomes an earlier run kept under --out and run only the rest",
    )
    record.add_argument(ap, "mission_accuracy")
    args = ap.parse_args(argv)
    with record.recorded("mission_accuracy", args.record, "The JSBSim mission set: accuracy"):
        return run(args)


if __name__ == "__main__":
    sys.exit(main())
