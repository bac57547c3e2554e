"""The calm NOC mission's coefficient NEES against the efficient estimator on the same
flights, and over further seeds (issue 53's calm NEES target; decision 0082).

    ./run bench calm_nees [--seeds 20] [--more 100] [--minutes 8] [--jobs 2]

noc_mission scores the filters' coefficient NEES over seeds 1..seeds. A mean NEES below
its band says either that the filters' covariance is wider than their errors, or that
those flights' noise fell on the small side. Two measurements tell the two apart:

- the yardstick, on each of those flights (with the vane and without): the output-error
  maximum-likelihood fit of the whole record (sim.reference: the simulator's own
  integrator, white noise of known sigma, so asymptotically efficient) with its
  Cramer-Rao covariance. Printed: its NEES and mean z² (each coefficient's error in its
  own sigma, averaged) beside the filters', the filters' covariance sigma over the
  Cramer-Rao sigma, the correlation across seeds of the filters' errors with the fit's,
  and the filters' variance along the combination of coefficients the bound holds best.
  A filter at the information limit has the ratio 1 and the correlation near 1: a NEES
  both have below the band is those flights' noise, not the filter's covariance;
- further seeds (seeds + 1 .. seeds + more): the filters' NEES with the band for that
  many seeds.

The structure check is off in every run: it widens the sigma the table shows, never the
filters' covariance the NEES is of, and it is most of a run's time.
"""

from __future__ import annotations

import argparse
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from typing import NamedTuple

import numpy as np
from bands import mean_chi2_band
from record import add_argument, recorded

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.estimation.filters.core import FILTER_KINDS
from gcs_estimator.model.channels import Channel
from gcs_estimator.runtime.session import run_recording
from sim.reference import output_error
from sim.scenario import mission
from sim.truth import simulate

CASES = ("vane", "no vane")
ML = "ML"
"""The yardstick's row: output-error maximum likelihood with its Cramer-Rao covariance."""


MIN_CORRELATED = 3
"""Flights a correlation across them needs (fewer: NaN)."""


class Estimate(NamedTuple):
    """One estimator's end on one flight: error against the truth, covariance."""

    error: FloatArray
    covariance: FloatArray

    @property
    def nees(self) -> float:
        return float(self.error @ np.linalg.solve(self.covariance, self.error))

    @property
    def sigma(self) -> FloatArray:
        return np.sqrt(np.diag(self.covariance))

    @property
    def z2(self) -> float:
        """Each coefficient's squared error in its own sigma, averaged over them."""
        return float(np.mean((self.error / self.sigma) ** 2))


Flight = dict[tuple[str, str], Estimate]
"""(case, estimator) -> its estimate on one flight."""


def config_of(minutes: float) -> AircraftConfig:
    return load_config("noc_uav", [*mission("none", 60.0 * minutes), "filter.structure_check=off"])


def fly(job: tuple[float, int, bool]) -> Flight:
    """One seed's flight through both filters, with the vane and without, and (yardstick)
    the output-error fit of each."""
    minutes, seed, yardstick = job
    config = config_of(minutes)
    truth = np.array(config.truth)
    flight = simulate(config, seed=seed)
    out: Flight = {}
    for case in CASES:
        y = flight.measurements.copy()
        if case == "no vane":
            y[:, Channel.ALPHA] = np.nan
        run = run_recording(config, flight.t_s, flight.inputs, y, keep_history=False)
        for kind, f in run.result.filters.items():
            out[(case, kind)] = Estimate(f.coefficients - truth, f.covariance)
        if yardstick:
            fit = output_error(config, replace(flight, measurements=y))
            out[(case, ML)] = Estimate(fit.coefficients - truth, fit.covariance)
    return out


def table(flights: list[Flight], estimators: tuple[str, ...], dof: int) -> None:
    """Per case and estimator: the mean NEES and the mean z² over the coefficients and
    the flights, with their 95 % bands."""
    lo, hi = mean_chi2_band(dof, len(flights))
    zlo, zhi = mean_chi2_band(1, len(flights) * dof)  # as if the coefficients were independent
    print(
        f"| case | estimator | mean NEES (95 % band {lo:.2f}-{hi:.2f}) | mean z² "
        f"(1 expected; {zlo:.2f}-{zhi:.2f} were the errors independent) |"
    )
    print("|---|---|---:|---:|")
    for case in CASES:
        for k in estimators:
            nees = np.mean([f[(case, k)].nees for f in flights])
            z2 = np.mean([f[(case, k)].z2 for f in flights])
            print(f"| {case} | {k} | {nees:.2f} | {z2:.2f} |")


def against_yardstick(flights: list[Flight], names: tuple[str, ...]) -> None:
    """Per case and filter: the covariance sigma over the Cramer-Rao sigma (median over
    the flights) and the correlation of the errors with the fit's across them."""
    print(
        "\nper coefficient: the filter's covariance sigma over the Cramer-Rao sigma (median "
        "over the flights), then the correlation across the flights of the filter's error "
        "with the fit's; last column: the filter's variance along the combination of "
        "coefficients the Cramer-Rao covariance holds best (its smallest eigenvalue's "
        "direction) over that eigenvalue (median)\n"
    )
    print("| case | filter | figure | " + " | ".join(names) + " | best-held combination |")
    print("|---|---|---|" + "---|" * (len(names) + 1))
    for case in CASES:
        for kind in FILTER_KINDS:
            ratio = np.median(
                [f[(case, kind)].sigma / f[(case, ML)].sigma for f in flights], axis=0
            )
            a = np.array([f[(case, kind)].error for f in flights])
            b = np.array([f[(case, ML)].error for f in flights])
            corr = [float(np.corrcoef(a[:, i], b[:, i])[0, 1]) for i in range(len(names))]
            if len(flights) < MIN_CORRELATED:
                corr = [float("nan")] * len(names)
            best = np.median([best_held(f[(case, kind)], f[(case, ML)]) for f in flights])
            print(
                f"| {case} | {kind} | σ / Cramer-Rao | "
                + " | ".join(f"{r:.2f}" for r in ratio)
                + f" | {best:.2f} |"
            )
            print(
                f"| {case} | {kind} | error correlation | "
                + " | ".join(f"{c:.2f}" for c in corr)
                + " | |"
            )


def best_held(filt: Estimate, fit: Estimate) -> float:
    """The filter's variance along the fit's best-held combination of coefficients (the
    Cramer-Rao covariance's eigenvector of the smallest eigenvalue) over that eigenvalue."""
    w, v = np.linalg.eigh(fit.covariance)
    return float(v[:, 0] @ filt.covariance @ v[:, 0] / w[0])


def run(seeds: int, more: int, minutes: float, jobs: int) -> None:
    names = config_of(minutes).coefficient_names
    dof = len(names)
    print(
        f"NOC mission of {minutes:g} min in calm air; coefficient NEES (dof {dof}) of both "
        "filters with the vane and without; structure check off (it does not touch the "
        "covariance)\n"
    )
    start = time.perf_counter()
    work = [(minutes, s, True) for s in range(1, seeds + 1)]
    work += [(minutes, s, False) for s in range(seeds + 1, seeds + more + 1)]
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        flights = list(pool.map(fly, work))
    first, further = flights[:seeds], flights[seeds:]
    if first:
        print(f"## Seeds 1-{seeds}, the output-error fit beside the filters\n")
        table(first, (*FILTER_KINDS, ML), dof)
        against_yardstick(first, names)
    if further:
        print(f"\n## Seeds {seeds + 1}-{seeds + more}, the filters\n")
        table(further, FILTER_KINDS, dof)
    if first and further:
        print(f"\n## All {seeds + more} seeds, the filters\n")
        table(flights, FILTER_KINDS, dof)
    print(f"\n({time.perf_counter() - start:.0f} s wall, {jobs} processes)")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument(
        "--seeds", type=int, default=20, help="seeds with the yardstick (default %(default)s)"
    )
    ap.add_argument(
        "--more", type=int, default=100, help="further seeds, filters only (default %(default)s)"
    )
    ap.add_argument(
        "--minutes", type=float, default=8.0, help="mission length (default %(default)s)"
    )
    ap.add_argument("--jobs", type=int, default=2, help="processes (default %(default)s)")
    add_argument(ap, "calm_nees")
    args = ap.parse_args(argv)
    if args.seeds < 0 or args.more < 0 or args.seeds + args.more < 1 or args.minutes <= 0:
        raise SystemExit("calm_nees: --seeds and --more 0 or more, not both 0; --minutes positive")
    if args.jobs < 1:
        raise SystemExit("calm_nees: --jobs must be 1 or more")
    with recorded(
        "calm_nees", args.record, "Calm NOC mission: NEES against the efficient estimator"
    ):
        run(args.seeds, args.more, args.minutes, args.jobs)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
