"""What the validation set's aerodynamics hold beyond the structure, and what that does to
the references.

    ./run bench structure_gap [--record NAME|none]

The validation set's references (benchmarks/jsbsim_flights.py) are JSBSim's aerodynamic
coefficients over the flown samples, fitted sample by sample by least squares on the
structure's regressors (1, alpha, q c / (2 V), elevator). A filter, like any estimator
that fits the flight's motion, converges instead to the structure's best fit to the
trajectories (benchmarks/best_fit.py). Where the structure holds the two agree; this
benchmark measures, per aircraft, how far it does not, and where the difference lies.
For each aircraft, calm and in light turbulence (seed 1), it prints:

- the share of the variance of JSBSim's CL and Cm over the flown samples that the
  regressors leave unexplained, with the structure's regressors; with JSBSim's alpha-dot
  regressor (alpha-dot c / (2 V)) added; and with the elevator's slipstream as well
  (elevator x (qbar_induced / qbar - 1), for an aircraft whose elevator JSBSim scales by
  the propeller's induced dynamic pressure);
- the structure's pitch equation at JSBSim's own states (calm), with the references: the
  slope of JSBSim's pitch acceleration on the model's (1: the mass, inertia and moment
  bookkeeping agree), the residual's share of the signal's variance, and how much of the
  residual alpha-dot c / (2 V) and the structure's regressors explain;
- the references against the structure's best fit to the calm trajectories, in %.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from best_fit import best_fit  # benchmarks/: the script's dir is on sys.path
from jsbsim_flights import AIRCRAFT, CLEAN, fly, reference, write_record
from realdata import NEAR_ZERO
from record import add_argument, recorded

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import load_config
from gcs_estimator.model import compiled  # noqa: F401  (registers the equations with numba)
from gcs_estimator.model import equations as eq
from gcs_estimator.model.aircraft import build_model

QDOT = CLEAN.index("qdot")


def _unexplained(y: FloatArray, columns: list[FloatArray]) -> float:
    """Share of y's variance a least-squares fit on `columns` leaves, in %."""
    X = np.column_stack(columns)
    beta, *_ = np.linalg.lstsq(X, y, rcond=None)
    return float(100.0 * np.var(y - X @ beta) / np.var(y))


def _regressors(f: dict[str, FloatArray]) -> dict[str, list[FloatArray]]:
    q_hat = f["q"] * f["chord"] / (2.0 * f["V"])
    paper = [np.ones_like(q_hat), f["alpha"], q_hat, f["de"]]
    induced = np.where(f["qbar_induced"] > 0.0, f["qbar_induced"], f["qbar"])
    slip = f["de"] * (induced / f["qbar"] - 1.0)
    return {
        "structure": paper,
        "+ alpha-dot": [*paper, f["adhat"]],
        "+ alpha-dot + slipstream": [*paper, f["adhat"], slip],
    }


def _pitch_equation(config_path: Path, f: dict[str, FloatArray]) -> tuple[float, float, float]:
    """(slope of JSBSim's qdot on the model's, residual share of qdot's variance in %,
    share of the residual that alpha-dot c / (2 V) and the regressors explain in %) at
    JSBSim's states with the airframe file's references."""
    config = load_config(config_path, ["sensors.vane_x_m=0", "sensors.bias_states=[]"])
    model = build_model(config, gust_states=False)
    beta = np.array(config.truth, float)
    inputs = np.column_stack([f["de"], f["thrust"], f["rho"]])
    predicted = np.empty(f["t"].shape[0])
    for i in range(predicted.shape[0]):
        state = np.array([f["V"][i], f["alpha"][i], f["theta"][i], f["q"][i]])
        x = model.augment(state, beta)
        y, _ = eq.observe(x, model.inputs(inputs[i]), model.arrays)
        predicted[i] = y[QDOT]
    slope = float(np.polyfit(predicted, f["qdot"], 1)[0])
    residual = f["qdot"] - predicted
    share = float(100.0 * np.var(residual) / np.var(f["qdot"]))
    explained = 100.0 - _unexplained(residual, _regressors(f)["+ alpha-dot"])
    return slope, share, explained


def run() -> None:
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for ac in AIRCRAFT:
            print(f"\n## {ac.label}\n")
            flights = {"calm": fly(ac, False, 1), "light": fly(ac, True, 1)}
            print(
                "Share of JSBSim's coefficient variance over the flown samples left "
                "unexplained, %:\n"
            )
            print("| flight | regressors | CL | Cm |")
            print("|---|---|---|---|")
            for label, f in flights.items():
                for name, cols in _regressors(f).items():
                    cl, cm = (_unexplained(f[axis], cols) for axis in ("CL", "Cm"))
                    print(f"| {label} | {name} | {cl:.2f} | {cm:.2f} |")
            calm = flights["calm"]
            config_path, _ = write_record(Path(tmp) / ac.model, ac, calm, 1)
            slope, share, explained = _pitch_equation(config_path, calm)
            print(
                f"\nPitch equation at JSBSim's states, with the references (calm): JSBSim's "
                f"pitch acceleration = {slope:.3f} x the model's; the residual is {share:.2f} % "
                f"of its variance, {explained:.1f} % of it explained by alpha-dot c / (2 V) "
                "with the structure's regressors.\n"
            )
            config = load_config(config_path, ["sensors.vane_x_m=0", "sensors.bias_states=[]"])
            inputs = np.column_stack([calm["de"], calm["thrust"], calm["rho"]])
            clean = np.column_stack([calm[k] for k in CLEAN])
            best, _ = best_fit(config, calm["t"], inputs, clean, np.array(config.truth))
            ref = reference(calm, float(calm["chord"][0]))
            print(
                "| coefficient | reference (sample by sample) | best fit (trajectories) "
                "| difference % |"
            )
            print("|---|---|---|---|")
            for name, b in zip(config.coefficient_names, best, strict=True):
                r = ref[name][0]
                diff = f"{100.0 * (b - r) / abs(r):+.1f}" if abs(r) > NEAR_ZERO else "ref ≈ 0"
                print(f"| {name} | {r:.4g} | {b:.4g} | {diff} |")
    print(f"\n({time.perf_counter() - start:.1f} s wall)")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    add_argument(ap, "structure_gap")
    args = ap.parse_args(argv)
    with recorded(
        "structure_gap", args.record, "The validation set's aerodynamics against the structure"
    ):
        run()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
