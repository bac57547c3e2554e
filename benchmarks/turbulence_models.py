"""Which turbulence model serves the coefficients, and would the data's likelihood choose it?

    ./run bench turbulence_models [--seeds 5] [--noc-seeds 20] [--refine-noise]
                                  [--record NAME|none]

The filters model turbulence as white process noise on the flight states (the default) or
as Dryden gust states whose scale lengths the airframe file gives (docs/decisions/0009).
The states need a scale length; the default (200 m, 50 m) is MIL-F-8785C's near the
ground, 533 m its length above 2,000 ft, where the JSBSim set and HFB-320 fly. This runs
every record with each model and prints, per record and model:

- the worst well-excited |error| in % against the record's reference (the structure's
  best fit for the JSBSim set, benchmarks/realdata.py; the book for HFB-320; the truth for
  the NOC simulator), over the coefficients whose reference is not near zero;
- the coefficient NEES against that reference (a consistency figure where the reference
  is the truth, the NOC flights; elsewhere it also holds what the structure misses);
- -2 log L: the EKF's innovations over the frames from 12 s on (after the restarts), as
  the sum of NIS + sum over channels of log S_cc (the log-determinant from S's diagonal:
  the frames keep each channel's innovation sigma, not S's correlations).

and, pooled per group, the same figures for a policy that takes, per record, the model of
smallest -2 log L: what choosing the turbulence model by likelihood would give.

With `--refine-noise`, a fourth model: the record's own process noise levels, fitted by
maximum likelihood over the whole record (`refine`'s filter error, from a first run with
the defaults), given to the filters as fixed white process noise on V, alpha, theta and q
(never below the calm-air floor; no online turbulence level, no pitch gust state: the
fitted q noise stands for it) in a second run. It asks whether noise levels the data
choose by likelihood serve the coefficients (docs/decisions/0029).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from bands import mean_chi2_band
from jsbsim_flights import ROOT, generate  # benchmarks/: the script's dir is on sys.path
from realdata import NEAR_ZERO, WELL_EXCITED
from record import add_argument, recorded

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.ingest.flightdata import load_recording
from gcs_estimator.refine import refine_run
from gcs_estimator.runtime.session import run_recording
from sim.truth import simulate

MODELS: dict[str, list[str]] = {
    "white noise": [],
    "states, config's lengths": ['filter.turbulence.model="states"'],
    "states, 533 m": [
        'filter.turbulence.model="states"',
        "filter.turbulence.length_u_m=533",
        "filter.turbulence.length_w_m=533",
    ],
}
"""The models compared, as config overrides on each record's airframe file."""
REFINE_NOISE = "refine's noise"
"""--refine-noise's model: its overrides are the record's own (refine_noise)."""
PICK = "chosen by -2 log L"
LIKELIHOOD_FROM_S = 12.0
"""Frames from this time after the first [s] enter -2 log L: after the restarts (5 s,
10 s), so that each model is judged on its final pass."""


@dataclass(frozen=True)
class Record:
    name: str
    group: str
    config: Callable[[list[str]], AircraftConfig]
    data: tuple[FloatArray, FloatArray, FloatArray]
    reference: dict[str, float] | None
    """None: the config's [truth]."""


@dataclass(frozen=True)
class Outcome:
    worst: float
    nees: float
    minus2ll: float


def _records(seeds: int, noc_seeds: int) -> Iterator[Record]:
    for seed in range(1, noc_seeds + 1):
        for turbulence in ("none", "light"):
            base = [f'simulation.turbulence.preset="{turbulence}"', f"simulation.seed={seed}"]

            def noc(o: list[str], base: list[str] = base) -> AircraftConfig:
                return load_config("noc_uav", base + o)

            flight = simulate(noc([]))
            yield Record(
                f"noc_{turbulence}_s{seed}",
                f"NOC {turbulence}",
                noc,
                (flight.t_s, flight.inputs, flight.measurements),
                None,
            )
    hfb = load_config("hfb320", [])
    rec = load_recording("hfb320", hfb.data)[1]
    yield Record(
        "hfb320",
        "HFB-320",
        lambda o: load_config("hfb320", o),
        (rec.t_s, rec.inputs, rec.measurements),
        None,
    )
    for config_path, csv_path in generate(ROOT / "out" / "realdata", tuple(range(1, seeds + 1))):
        best = json.loads(csv_path.with_suffix(".best_fit.json").read_text(encoding="utf-8"))
        rec = load_recording(csv_path)[1]
        stem = csv_path.stem

        def jsb(o: list[str], path: Path = config_path) -> AircraftConfig:
            return load_config(path, o)

        yield Record(
            stem,
            stem.split("_s")[0],
            jsb,
            (rec.t_s, rec.inputs, rec.measurements),
            best["coefficients"],
        )


def outcome(record: Record, overrides: list[str]) -> Outcome:
    config = record.config(overrides)
    result = run_recording(config, *record.data).result
    fr = result.filters["EKF"]
    track = fr.track
    assert track is not None
    names = result.names
    truth = dict(zip(names, config.truth or (), strict=False))
    ref = record.reference if record.reference is not None else truth
    goal = np.array([ref[n] for n in names])
    judged = [i for i, n in enumerate(names) if n in WELL_EXCITED and abs(goal[i]) > NEAR_ZERO]
    err = 100.0 * np.abs(fr.coefficients[judged] - goal[judged]) / np.abs(goal[judged])
    d = fr.coefficients - goal
    nees = float(d @ np.linalg.solve(fr.covariance, d))
    late = (track.t - track.t[0]) >= LIKELIHOOD_FROM_S
    s2 = track.innovation_sigma[late] ** 2
    seen = np.isfinite(track.innovation[late]) & np.isfinite(s2) & (s2 > 0.0)
    minus2ll = float(np.sum(track.nis[late]) + np.sum(np.log(s2[seen])))
    return Outcome(float(err.max()), nees, minus2ll)


def refine_noise(record: Record) -> list[str]:
    """Overrides that give the filters the record's process noise as `refine`'s filter
    error fits it (from a run with the defaults), fixed and white, never below the
    airframe file's calm-air floor."""
    config = record.config([])
    result = run_recording(config, *record.data).result
    fitted = refine_run(result, "filter-error").process_noise
    floor = config.filter.process_noise.states
    return [
        "filter.turbulence.adaptive=false",
        "filter.turbulence.sigma_w_mps=0",
        "airframe.wing_span_m=0",  # no pitch gust: the fit's white noise alone
        *(
            f"filter.process_noise.{k}={max(float(q), f)!r}"
            for k, q, f in zip(("V", "alpha", "theta", "q"), fitted, floor, strict=True)
        ),
    ]


def run(seeds: int, noc_seeds: int, with_refine_noise: bool = False) -> None:
    start = time.perf_counter()
    models: dict[str, list[str] | None] = {**MODELS}
    if with_refine_noise:
        models[REFINE_NOISE] = None
    groups: dict[str, list[dict[str, Outcome]]] = {}
    head = " | ".join(f"{m}: worst % / NEES / -2 log L" for m in models)
    print("| record | " + head + " | chosen by -2 log L |")
    print("|---|" + "---|" * (len(models) + 1))
    for record in _records(seeds, noc_seeds):
        by_model = {
            m: outcome(record, refine_noise(record) if o is None else o) for m, o in models.items()
        }
        chosen = min(by_model, key=lambda m: by_model[m].minus2ll)
        by_model[PICK] = by_model[chosen]
        groups.setdefault(record.group, []).append(by_model)
        low = min(o.minus2ll for m, o in by_model.items() if m != PICK)
        cells = [
            f"{o.worst:.2f} / {o.nees:.1f} / {o.minus2ll - low:+.0f}"
            for m, o in by_model.items()
            if m != PICK
        ]
        print(f"| {record.name} | " + " | ".join(cells) + f" | {chosen} |", flush=True)
    print(
        "\n(-2 log L as the difference from the smallest of the record's models.)\n\n"
        "## Pooled per group: worst well-excited |error| % (largest; median of each "
        "record's), mean NEES, and how often the likelihood chose each model\n"
    )
    print("| group | records | " + " | ".join([*models, PICK]) + " | chosen |")
    print("|---|---|" + "---|" * (len(models) + 2))
    for group, rows in groups.items():
        cells = []
        for m in [*models, PICK]:
            worst = [r[m].worst for r in rows]
            nees = [r[m].nees for r in rows]
            cells.append(f"{max(worst):.2f} / {np.median(worst):.2f} / NEES {np.mean(nees):.1f}")
        counts = {m: sum(1 for r in rows if r[PICK] == r[m]) for m in models}
        chosen = ", ".join(f"{m} {c}" for m, c in counts.items() if c)
        print(f"| {group} | {len(rows)} | " + " | ".join(cells) + f" | {chosen} |")
    p = len(load_config("noc_uav").coefficient_names)
    lo, hi = mean_chi2_band(p, noc_seeds)
    print(
        f"\nNOC NEES 95 % band over {noc_seeds} seeds, dof {p}: {lo:.2f}-{hi:.2f}. "
        f"({time.perf_counter() - start:.1f} s wall)"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seeds", type=int, default=5, help="JSBSim seeds (default %(default)s)")
    ap.add_argument(
        "--noc-seeds", type=int, default=20, help="NOC simulator seeds (default %(default)s)"
    )
    ap.add_argument(
        "--refine-noise",
        action="store_true",
        help="also the record's own process noise as refine's filter error fits it",
    )
    add_argument(ap, "turbulence_models")
    args = ap.parse_args(argv)
    if args.seeds < 1 or args.noc_seeds < 1:
        raise SystemExit("turbulence_models: --seeds and --noc-seeds must be 1 or more")
    with recorded(
        "turbulence_models",
        args.record,
        "Turbulence models: which serves the coefficients, and what likelihood would choose",
    ):
        run(args.seeds, args.noc_seeds, args.refine_noise)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
