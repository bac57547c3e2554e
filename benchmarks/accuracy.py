"""Monte Carlo accuracy, consistency and convergence of EKF and IEKF on the NOC simulation.

Every coefficient starts at zero (the paper's start). Prints one table per scenario:
median and worst absolute error, share within 3 sigma, mean NEES and NIS against their
95 % chi-square bands, and convergence times, EKF and IEKF side by side.

    python benchmarks/accuracy.py --seeds 20
    python benchmarks/accuracy.py --seeds 20 --turbulence light
    python benchmarks/accuracy.py --seeds 20 --perturb 0.3     # truth off the paper by 30 %
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
import record  # benchmarks/record.py: the script's directory is on sys.path
from bands import mean_chi2_band

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.estimation.estimator import FILTER_KINDS, FilterKind
from gcs_estimator.runtime.session import run_recording
from gcs_estimator.uncertainty.metrics import CoefficientSummary, FilterSummary, percent_error
from sim.reference import output_error
from sim.scenario import scenario_of
from sim.truth import Flight, perturbed, simulate

KINDS = FILTER_KINDS
WELL_EXCITED = ("CL0", "CLa", "CLde", "Cm0", "Cma", "Cmq", "Cmde")
"""The coefficients the issue's accuracy targets apply to."""
DEADLINE_S = 10.0
"""The issue's convergence target: the seven within 5 % of truth by this time."""
TURBULENT_DEADLINE_S = 20.0
"""The same target in turbulence (issue "Honest uncertainty on any aircraft": light
turbulence, the seven within 5 % by 20 s on at least 90 % of seeds)."""


@dataclass(frozen=True)
class RunResult:
    seed: int
    summaries: dict[FilterKind, FilterSummary]
    truth: tuple[float, ...]
    restarts: tuple[float, ...]
    duration: float
    gust_sigma: dict[FilterKind, float]
    """The turbulence level each filter ended with [m/s]."""
    health: dict[FilterKind, tuple[int, int, int]]
    """Covariance repairs, skipped updates and divergences of each filter (all passes)."""
    reference: tuple[tuple[float, ...], tuple[float, ...]] | None = None
    """Output-error maximum-likelihood coefficients and their sigmas (calm air only)."""
    reference_early: tuple[float, ...] | None = None
    """The same fit on the data up to the convergence deadline only."""
    limit: Limit | None = None
    """In turbulence: the filter that knows the simulator's turbulence (limit_config)."""


class Limit(NamedTuple):
    """The filter that knows the simulator's turbulence on one flight (limit_config), at
    TURBULENT_DEADLINE_S and at the end: estimates and covariance sigmas, and its NEES."""

    early: tuple[float, ...]
    early_sigma: tuple[float, ...]
    final: tuple[float, ...]
    final_sigma: tuple[float, ...]
    nees: float


def _num(v: float | None) -> float:
    return math.nan if v is None else v


def _z_covariance(c: CoefficientSummary) -> float:
    """The error in the filter covariance's sigma (the summary's z is in the sigma to
    trust)."""
    return math.nan if c.truth is None else (c.estimate - c.truth) / c.sigma_parts.covariance


def run_one(args: tuple[str, list[str], int, float, bool]) -> RunResult:
    path, overrides, seed, perturb, with_reference = args
    config = perturbed(load_config(path, overrides), seed, perturb)
    assert config.truth is not None
    truth = config.truth
    flight = simulate(config, seed=seed)
    run = run_recording(config, flight.t_s, flight.inputs, flight.measurements)
    filters = run.result.filters
    reference = None
    early = None
    turbulent = scenario_of(config).turbulence.sigma_w > 0.0
    if with_reference and not turbulent:
        fit = output_error(config, flight)
        reference = (tuple(fit.coefficients.tolist()), tuple(fit.sigma.tolist()))
        early = tuple(output_error(config, flight, until_s=DEADLINE_S).coefficients.tolist())
    limit = None
    if with_reference and turbulent:
        limit = turbulent_limit(config, flight)
    return RunResult(
        seed,
        dict(run.summaries),
        truth,
        config.filter.restart_times_s,
        float(flight.t_s[-1] - flight.t_s[0]),
        {kind: f.gust_sigma for kind, f in filters.items()},
        {
            kind: (f.health.covariance_repairs, f.health.failed_updates, f.health.divergences)
            for kind, f in filters.items()
        },
        reference,
        early,
        limit,
    )


def limit_config(config: AircraftConfig) -> AircraftConfig:
    """The filters given what the simulator knows of its turbulence: gust states with the
    simulator's scale lengths, intensity and sigma_u / sigma_w, the level held instead of
    estimated; otherwise as configured (zero start, restarts). Their covariance is then
    the precision the flight allows an estimator that knows the air (the simulator flies
    second-order Dryden w_g, these states are first order: close, not exact; the NEES
    says how close). Started at the truth without restarts instead, the EKF diverged on
    one seed in 20 and was inconsistent on several: the restarts are part of what makes
    the filter efficient."""
    sim = scenario_of(config).turbulence
    ft = config.filter
    turbulence = replace(
        ft.turbulence,
        model="states",
        adaptive=False,
        sigma_w_mps=sim.sigma_w,
        sigma_u_ratio=sim.sigma_u / sim.sigma_w,
        length_u_m=sim.length_u_m,
        length_w_m=sim.length_w_m,
    )
    return replace(config, filter=replace(ft, turbulence=turbulence))


def turbulent_limit(config: AircraftConfig, flight: Flight) -> Limit:
    """limit_config's EKF on the flight: its belief at TURBULENT_DEADLINE_S and at the end."""
    limit = limit_config(config)
    run = run_recording(limit, flight.t_s, flight.inputs, flight.measurements)
    result = run.result.filters["EKF"]
    track = result.track
    assert track is not None
    at = int(np.searchsorted(track.t - track.t[0], TURBULENT_DEADLINE_S, "right")) - 1
    return Limit(
        tuple(track.coefficients[at].tolist()),
        tuple(track.coefficient_sigma[at].tolist()),
        tuple(result.coefficients.tolist()),
        tuple(result.sigma.tolist()),
        _num(run.summaries["EKF"].nees),
    )


def information_limit(path: str, overrides: list[str], seed: int) -> dict[str, float]:
    """1-sigma precision the data allow, in % of truth: the final sigma of the EKF on
    calm air with its turbulence level held at zero, which is the Cramer-Rao bound of the
    flight (tests/sim/test_reference.py compares the two)."""
    from dataclasses import replace

    config = load_config(path, overrides)
    assert config.truth is not None
    tuning = config.filter
    limit = replace(
        config,
        filter=replace(
            tuning, turbulence=replace(tuning.turbulence, adaptive=False, sigma_w_mps=0.0)
        ),
    )
    flight = simulate(limit, seed=seed)
    res = run_recording(limit, flight.t_s, flight.inputs, flight.measurements, keep_history=False)
    sigma = res.result.filters["EKF"].sigma
    return {
        name: 100.0 * float(s) / abs(t)
        for name, s, t in zip(res.result.names, sigma, config.truth, strict=True)
    }


def report(results: list[RunResult], title: str) -> None:
    names = [c.name for c in results[0].summaries["EKF"].coefficients]
    runs = len(results)
    print(f"\n## {title}: {runs} seeds\n")
    header = (
        "| coefficient | "
        + " | ".join(
            f"{k} med err % | {k} worst err % | {k} within 3σ | {k} conv. to truth s (med/worst)"
            for k in KINDS
        )
        + " |"
    )
    print(header)
    print("|" + "---|" * (1 + 8))
    for i, name in enumerate(names):
        cells = [name]
        for kind in KINDS:
            errs = np.array(
                [abs(_num(r.summaries[kind].coefficients[i].error_pct)) for r in results]
            )
            zs = np.array([abs(_z_covariance(r.summaries[kind].coefficients[i])) for r in results])
            conv = np.array(
                [_num(r.summaries[kind].coefficients[i].converged_truth_s) for r in results]
            )
            conv_txt = (
                f"{np.median(conv):.1f} / {np.max(conv):.1f}"
                if np.all(np.isfinite(conv))
                else f"{np.nanmedian(conv):.1f} / never"
                if np.any(np.isfinite(conv))
                else "never"
            )
            cells += [
                f"{np.median(errs):.2f}",
                f"{np.max(errs):.2f}",
                f"{np.mean(zs <= 3.0) * 100:.0f} %",
                conv_txt,
            ]
        print("| " + " | ".join(cells) + " |")

    print()
    p = len(names)
    for kind in KINDS:
        zs = np.array(
            [[abs(_z_covariance(c)) for c in r.summaries[kind].coefficients] for r in results]
        )
        share = float(np.mean(zs <= 3.0))
        zc = np.array(
            [
                [
                    abs(_z_covariance(c)) * c.sigma_parts.covariance / c.sigma
                    for c in r.summaries[kind].coefficients
                ]
                for r in results
            ]
        )
        share_c = float(np.mean(zc <= 3.0))
        inflation = np.array(
            [[c.sigma_parts.inflation for c in r.summaries[kind].coefficients] for r in results]
        )
        nees = np.array([_num(r.summaries[kind].nees) for r in results])
        lo, hi = mean_chi2_band(p, runs)
        nis = np.array([r.summaries[kind].mean_nis for r in results])
        nis_all = np.array([r.summaries[kind].mean_nis_all for r in results])
        dof = float(np.mean([r.summaries[kind].mean_channels for r in results]))
        restarts = results[0].restarts
        steps = int(
            np.mean([r.summaries[kind].steps for r in results])
            * (1 - (restarts[-1] if restarts else 0) / results[0].duration)
        )
        nlo, nhi = mean_chi2_band(dof, steps * runs)
        well = [names.index(n) for n in WELL_EXCITED if n in names]
        errs = np.array(
            [
                [abs(_num(r.summaries[kind].coefficients[i].error_pct)) for i in well]
                for r in results
            ]
        )
        conv = np.array(
            [
                [_num(r.summaries[kind].coefficients[i].converged_truth_s) for i in well]
                for r in results
            ]
        )
        conv_worst = np.where(np.isnan(conv), np.inf, conv).max(axis=1)
        gust = np.array([r.gust_sigma[kind] for r in results])
        repairs, skipped, diverged = np.array([r.health[kind] for r in results]).sum(axis=0)
        print(
            f"{kind}: turbulence level estimated sigma_w {np.median(gust):.2f} m/s "
            f"(median; range {gust.min():.2f}-{gust.max():.2f}) | "
            f"within 3σ {share * 100:.1f} % of (coefficient, seed) pairs "
            f"({share_c * 100:.1f} % with the corrected σ, median factor "
            f"{np.nanmedian(inflation):.2f}, largest {np.nanmax(inflation):.2f}) | "
            f"mean NEES {np.mean(nees):.2f} (95 % band {lo:.2f}-{hi:.2f}, dof {p}) | "
            f"mean NIS after the last restart {np.mean(nis):.3f} (95 % band {nlo:.3f}-{nhi:.3f},"
            f" dof {dof:.2f}; over the whole flight {np.mean(nis_all):.2f}) | "
            f"well-excited: median |err| {np.median(errs):.2f} %, worst {np.max(errs):.2f} % | "
            f"all 7 within 5 % of truth by: median {np.median(conv_worst):.1f} s, "
            f"worst {np.max(conv_worst):.1f} s | "
            f"covariance repairs {repairs}, skipped updates {skipped}, divergences {diverged} "
            f"(all seeds and passes)"
        )


def report_reference(results: list[RunResult]) -> None:
    """The output-error fit next to the IEKF, seed by seed."""
    fits = [r for r in results if r.reference is not None]
    refs = [r.reference for r in results if r.reference is not None]
    if not fits:
        return
    names = [c.name for c in fits[0].summaries["IEKF"].coefficients]
    print(
        "\n### Output-error maximum likelihood on the same flights: what the data allow\n\n"
        "A batch fit of the whole record, started at the truth (the most favourable start)."
        " Its sigma is the Cramer-Rao bound at the fit.\n"
    )
    print(
        "| coefficient | ML med err % | ML worst err % | ML within 3σ "
        "| IEKF − ML, median / worst in ML sigmas |"
    )
    print("|---|---|---|---|---|")
    worst: list[tuple[float, str]] = []
    all_within = np.ones(len(fits), dtype=bool)
    for i, name in enumerate(names):
        truth = np.array([r.truth[i] for r in fits])
        ml = np.array([ref[0][i] for ref in refs])
        sig = np.array([ref[1][i] for ref in refs])
        iekf = np.array([_num(r.summaries["IEKF"].coefficients[i].estimate) for r in fits])
        errs = np.array([abs(_num(percent_error(m, t))) for m, t in zip(ml, truth, strict=True)])
        gap = np.abs(iekf - ml) / sig
        if name in WELL_EXCITED:
            worst.append((float(np.max(errs)), name))
            all_within &= errs <= 5.0
        print(
            f"| {name} | {np.median(errs):.2f} | {np.max(errs):.2f} | "
            f"{np.mean(np.abs(ml - truth) <= 3.0 * sig) * 100:.0f} % | "
            f"{np.median(gap):.2f} / {np.max(gap):.2f} |"
        )
    value, name = max(worst)
    print(
        f"\nML well-excited worst seed: {value:.2f} % ({name}); all seven within 5 % of truth "
        f"in {int(all_within.sum())} of {len(fits)} seeds"
    )
    early = [(r.reference_early, r.truth) for r in fits if r.reference_early is not None]
    if early:
        cells = []
        for i, name in enumerate(names):
            if name not in WELL_EXCITED:
                continue
            errs = np.array([abs(_num(percent_error(fit[i], truth[i]))) for fit, truth in early])
            cells.append(
                f"{name} {np.median(errs):.2f} / {np.max(errs):.2f} "
                f"({np.sum(errs <= 5.0)} of {len(errs)} within 5 %)"
            )
        print(f"ML on the first {DEADLINE_S:g} s only (median / worst err %): " + " | ".join(cells))


def _within(sigma_pct: FloatArray, band_pct: float) -> FloatArray:
    """Probability that an unbiased estimate with this sigma [% of truth] lands within
    band_pct of the truth: erf(band / (sigma sqrt 2))."""
    return np.array([math.erf(band_pct / (s * math.sqrt(2.0))) for s in sigma_pct])


def report_limit(results: list[RunResult]) -> None:
    """In turbulence: the filter that knows the air (limit_config) beside the filters."""
    fits = [r for r in results if r.limit is not None]
    if not fits:
        return
    names = [c.name for c in fits[0].summaries["EKF"].coefficients]
    runs = len(fits)
    lo, hi = mean_chi2_band(len(names), runs)
    nees = float(np.mean([r.limit.nees for r in fits if r.limit is not None]))
    d = TURBULENT_DEADLINE_S
    print(
        "\n### What the data allow in this turbulence\n\n"
        "The EKF given what the simulator knows of its air (gust states at its scale lengths "
        "and intensity, held; the final pass after the restarts): its covariance is the "
        "precision an estimator that knows the air has on these flights. Its mean "
        f"NEES {nees:.2f} (95 % band {lo:.2f}-{hi:.2f}) says how far to trust that. "
        f"'P within 5 %' is the chance that an unbiased estimate with the sigma at {d:g} s "
        "lands within 5 % of the truth, averaged over the seeds.\n"
    )
    print(
        f"| coefficient | σ at {d:g} s, % of truth (median) | σ at the end, % (median) "
        f"| P within 5 % at {d:g} s | within 5 % at {d:g} s (seeds) | err % at the end "
        "(median / worst) |"
    )
    print("|---|---|---|---|---|---|")
    every = np.ones(runs, dtype=bool)
    expected = np.ones(runs)
    for i, name in enumerate(names):
        truth = np.array([r.truth[i] for r in fits])
        scale = 100.0 / np.abs(truth)
        lim = [r.limit for r in fits if r.limit is not None]
        s_early = scale * np.array([m.early_sigma[i] for m in lim])
        s_final = scale * np.array([m.final_sigma[i] for m in lim])
        e_early = scale * np.abs(np.array([m.early[i] for m in lim]) - truth)
        e_final = scale * np.abs(np.array([m.final[i] for m in lim]) - truth)
        p = _within(s_early, 5.0)
        if name in WELL_EXCITED:
            every &= e_early <= 5.0
            expected *= p
        print(
            f"| {name} | {np.median(s_early):.2f} | {np.median(s_final):.2f} | "
            f"{np.mean(p) * 100:.0f} % | {int(np.sum(e_early <= 5.0))} of {runs} | "
            f"{np.median(e_final):.2f} / {np.max(e_final):.2f} |"
        )
    print(
        f"\nAll seven well-excited within 5 % at {d:g} s: {int(every.sum())} of {runs} seeds; "
        "an efficient unbiased estimator with these sigmas, the seven taken as independent: "
        f"{np.mean(expected) * 100:.0f} % of seeds"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--config", default="noc_uav")
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--turbulence", choices=("none", "light", "moderate"), default="none")
    ap.add_argument(
        "--perturb",
        type=float,
        default=0.0,
        help="scale each true coefficient by 1 +- U(0.5, 1)*PERTURB (seeded)",
    )
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="config override, e.g. filter.iterations=3",
    )
    ap.add_argument(
        "--no-reference",
        action="store_true",
        help="skip what the data allow: the output-error maximum-likelihood fit run next to "
        "the filters in calm air, the filter that knows the turbulence in turbulence",
    )
    ap.add_argument("--jobs", type=int, default=2)
    record.add_argument(ap, "derived from the arguments: accuracy_TURBULENCE[_perturbed]")
    args = ap.parse_args(argv)
    name = args.record
    if name.startswith("derived"):
        name = f"accuracy_{args.turbulence}" + ("_perturbed" if args.perturb > 0 else "")
    with record.recorded("accuracy", name, "Accuracy: Monte Carlo over seeded flights"):
        return run(args)


def run(args: argparse.Namespace) -> int:

    overrides = [*args.set, f'simulation.turbulence.preset="{args.turbulence}"']
    with_reference = not args.no_reference
    jobs = [
        (args.config, overrides, s, args.perturb, with_reference)
        for s in range(args.first_seed, args.first_seed + args.seeds)
    ]
    start = time.perf_counter()
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        results = list(pool.map(run_one, jobs))
    title = f"NOC, turbulence {args.turbulence}, truth perturbation {args.perturb:g}"
    report(results, title)
    report_reference(results)
    report_limit(results)
    if args.turbulence == "none" and args.perturb <= 0:
        limit = information_limit(args.config, overrides, args.first_seed)
        print(
            "\nInformation limit (seed "
            f"{args.first_seed}; 1 sigma in % of truth, the best any unbiased estimator can "
            "do on this flight; the worst of 20 seeds is typically 2-2.5 times it):\n"
            + " | ".join(f"{n} {v:.2f}" for n, v in limit.items())
        )
    print(f"\n({time.perf_counter() - start:.1f} s wall, {args.jobs} processes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
