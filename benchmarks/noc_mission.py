"""The NOC simulator flying a mission, with and without a vane (issue 53's NOC targets).

    ./run bench noc_mission [--seeds 20] [--minutes 8] [--record NAME|none]

Each seed flies `gcs-sim --scenario mission` (sim.scenario.mission: legs joined by
coordinated turns of 20-35 degrees of bank, 3-2-1-1s on every other leg, a climb and a
descent on throttle) in calm air and in light turbulence, and each flight runs through
both filters twice: with the vane's alpha, and without it (alpha from the climb rate,
decision 0049). Per case and filter it prints

- the share of coefficients within 3 sigma of the truth (sigma: the one the table shows),
  and the share of those marked identified that lie within 5 % of it;
- the coefficient NEES (mean over seeds; 11 is its expectation, the header gives its
  95 % band; `calm_nees` says why seeds 1-20 fall below it in calm air, decision 0082)
  and the mean NIS against the channels used (its expectation);
- the no-vane sigma over the vane sigma per coefficient (median over seeds): what losing
  the vane costs, for the table's sigma and for the filters' own (covariance sigma
  times the movement factor, without the structure check and without the prior an
  uninformed alpha adds: decision 0060).

The third case flies the light turbulence's along-path gusts without its vertical wind
(sigma_w = 0, sigma_u the light preset's): the vertical wind is what a vane sees and
the climb rate does not, so the ratio there against light turbulence's says how much of
the turbulent ratio is the vertical wind (all of it, decision 0060). That air is not the
filters' turbulence model (sigma_u = 1.5 sigma_w): with the vane they read it badly.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
from bands import mean_chi2_band
from record import add_argument, recorded

from gcs_estimator.config import load_config
from gcs_estimator.model.channels import Channel
from gcs_estimator.model.turbulence import SIGMA_U_RATIO, SIGMA_W_PRESETS
from gcs_estimator.runtime.session import run_recording
from gcs_estimator.uncertainty.metrics import IDENTIFIED
from gcs_estimator.uncertainty.result import VehicleResult
from sim.scenario import mission
from sim.truth import simulate

SIGMA_U_LIGHT = SIGMA_U_RATIO * SIGMA_W_PRESETS["light"]
CASES: tuple[tuple[str, str, str, tuple[str, ...]], ...] = (
    ("calm", "calm", "none", ()),
    ("light", "light", "light", ()),
    (
        "light-horizontal",
        "light, no vertical wind",
        "custom",
        (
            "simulation.turbulence.sigma_w_mps=0.0",
            f"simulation.turbulence.sigma_u_mps={SIGMA_U_LIGHT}",
        ),
    ),
)
"""(key for --cases, heading, [simulation.turbulence] preset, further overrides)"""
Figures = tuple[float, float, float, float, np.ndarray, np.ndarray]


def _figures(run: VehicleResult, kind: str) -> Figures:
    """(share within 3 sigma, share of the identified within 5 %, NEES, mean NIS, sigmas,
    the filter's own sigmas: covariance times movement factor)."""
    s = run.summaries[kind]  # type: ignore[index]
    z = np.array([c.z for c in s.coefficients], float)
    sig = np.array([c.sigma for c in s.coefficients], float)
    marked = [c for c in s.coefficients if c.identifiability == IDENTIFIED]
    close = [abs(c.error_pct or 0.0) <= 5.0 for c in marked]
    within5 = float(np.mean(close)) if close else float("nan")
    nees = float(s.nees) if s.nees is not None else float("nan")
    own = np.array(
        [
            c.sigma_parts.covariance * np.nan_to_num(c.sigma_parts.movement_factor, nan=1.0)
            for c in s.coefficients
        ]
    )
    return float(np.mean(np.abs(z) < 3.0)), within5, nees, float(s.mean_nis), sig, own


def run(
    seeds: int, minutes: float, cases: tuple[str, ...] = (), overrides: tuple[str, ...] = ()
) -> None:
    """The cases' tables; overrides: config `--set` values on every flight (after the
    mission's and the case's)."""
    shown = f"; overrides: {' '.join(overrides)}" if overrides else ""
    print(
        f"NOC mission of {minutes:g} min, {seeds} seed(s), both filters; vane vs no vane{shown}\n"
    )
    for key, label, turbulence, extra in CASES:
        if cases and key not in cases:
            continue
        config = load_config("noc_uav", [*mission(turbulence, 60.0 * minutes), *extra, *overrides])
        rows: dict[tuple[str, str], list[Figures]] = {}
        names: tuple[str, ...] = ()
        start = time.perf_counter()
        for seed in range(1, seeds + 1):
            flight = simulate(config, seed=seed)
            no_vane = flight.measurements.copy()
            no_vane[:, Channel.ALPHA] = np.nan
            for vane, y in (("vane", flight.measurements), ("no vane", no_vane)):
                result = run_recording(config, flight.t_s, flight.inputs, y)
                names = result.result.names
                for kind in ("EKF", "IEKF"):
                    rows.setdefault((vane, kind), []).append(_figures(result, kind))
        took = time.perf_counter() - start
        print(f"## {label} ({took:.0f} s)\n")
        lo, hi = mean_chi2_band(len(names), seeds)
        print(
            f"| case | filter | within 3σ | identified within 5 % | NEES (95 % band "
            f"{lo:.1f}-{hi:.1f}) | mean NIS |"
        )
        print("|---|---|---:|---:|---:|---:|")
        for (vane, kind), figs in rows.items():
            w3 = np.mean([f[0] for f in figs])
            marked = [f[1] for f in figs if np.isfinite(f[1])]
            w5 = np.mean(marked) if marked else float("nan")  # nan: none marked identified
            print(
                f"| {vane} | {kind} | {100 * w3:.0f} % | {100 * w5:.0f} % | "
                f"{np.mean([f[2] for f in figs]):.1f} | {np.mean([f[3] for f in figs]):.2f} |"
            )
        for kind in ("EKF", "IEKF"):
            for which, col in (("table's", 4), ("filter's own", 5)):
                ratio = np.median(
                    [
                        b[col] / a[col]
                        for a, b in zip(rows[("vane", kind)], rows[("no vane", kind)], strict=True)
                    ],
                    axis=0,
                )
                pairs = ", ".join(f"{n} {r:.2f}" for n, r in zip(names, ratio, strict=True))
                print(f"\n{kind} {which} sigma no vane / vane (median): {pairs}")
        print()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seeds", type=int, default=20, help="seeds (default %(default)s)")
    ap.add_argument(
        "--minutes", type=float, default=8.0, help="mission length (default %(default)s)"
    )
    ap.add_argument(
        "--cases",
        default="calm,light,light-horizontal",
        help="which air (default %(default)s; light-horizontal: without the vertical wind)",
    )
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a config override on every flight (repeatable), e.g. the mission without its "
        "turns: --set simulation.turns.starts_s=[] (and its durations_s and banks_deg)",
    )
    add_argument(ap, "noc_mission")
    args = ap.parse_args(argv)
    if args.seeds < 1 or args.minutes <= 0:
        raise SystemExit("noc_mission: --seeds must be 1 or more, --minutes positive")
    with recorded("noc_mission", args.record, "NOC mission: turns, wind, vane and no vane"):
        run(args.seeds, args.minutes, tuple(args.cases.split(",")), tuple(args.set))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
