"""Filter steps per second on one core for the NOC model (predict + update per step).

    python benchmarks/speed.py

Per filter (the EKF, and the IEKF with all N = 7 iterations every step), CPU time,
median of 3:
- kernel: the compiled backend's one call per step (filters.fast.kernel_step: process
  noise, prediction, update, health check, gust matching);
- step contract: the same through filters.core's guarded step, as the estimator calls it;
- numpy reference: the reference backend through the same contract, and the ratio.
Then a whole 60 s flight through the estimator (both filters, restarts, history):
frames per second.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable

import numpy as np
import record  # benchmarks/record.py: the script's directory is on sys.path

from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.estimator import FILTER_KINDS, FilterKind, run_recording
from gcs_estimator.filters import core, fast
from gcs_estimator.filters.core import FilterState, Tuning
from gcs_estimator.model.aircraft import Model, build_model
from sim.truth import Flight, simulate

WARM = 300
"""Frames stepped before timing, so that the timing is of the steady state."""


def _converged(config: AircraftConfig, model: Model, tuning: Tuning, flight: Flight) -> FilterState:
    step = core.stepper("fast")
    s = core.initial_state(model, tuning, flight.t_s[0], flight.inputs[0], flight.measurements[0])
    for i in range(WARM):
        s, _ = step(
            s, float(flight.t_s[i]), flight.inputs[i], flight.measurements[i], tuning, model
        )
    return s


def rate(
    step: Callable[..., tuple[FilterState, object]]
    | Callable[..., tuple[FilterState, object, bool]],
    kind: FilterKind,
    frames: int,
) -> float:
    # relinearise_sigma = 0: the IEKF runs all N iterations every step (the configured
    # gate usually stops it after 2 near the solution, which would flatter the figure).
    config = load_config("noc_uav", ["filter.relinearise_sigma=0"])
    flight = simulate(config, seed=1)
    model = build_model(config)
    tuning = core.tuning_of(config, model, kind)
    s = _converged(config, model, tuning, flight)
    n = min(frames, len(flight.t_s) - WARM)
    t, u, y = flight.t_s, flight.inputs, flight.measurements
    t0 = time.process_time()
    for i in range(WARM, WARM + n):
        s = step(s, float(t[i]), u[i], y[i], tuning, model)[0]
    return n / (time.process_time() - t0)


def whole_flight() -> tuple[float, int]:
    """Frames per second of a 60 s flight through the estimator, both filters."""
    config = load_config("noc_uav", [])
    flight = simulate(config, seed=1)
    best = 0.0
    for _ in range(3):
        t0 = time.process_time()
        run_recording(config, flight.t_s, flight.inputs, flight.measurements)
        best = max(best, len(flight.t_s) / (time.process_time() - t0))
    return best, len(flight.t_s)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    record.add_argument(ap, "speed")
    args = ap.parse_args()
    with record.recorded("speed", args.record, "Speed: filter steps per second"):
        return run()


def run() -> int:
    fast_step, ref_step = core.stepper("fast"), core.stepper("reference")
    print(
        "| filter | kernel steps/s | step contract steps/s | contract / kernel | "
        "numpy reference steps/s | contract / reference |"
    )
    print("|---|---|---|---|---|---|")
    for kind in FILTER_KINDS:
        kernel = np.median([rate(fast.kernel_step, kind, 2500) for _ in range(3)])
        contract = np.median([rate(fast_step, kind, 2500) for _ in range(3)])
        ref = rate(ref_step, kind, 300)
        label = "IEKF (N = 7)" if kind == "IEKF" else "EKF"
        print(
            f"| {label} | {kernel:,.0f} | {contract:,.0f} | {contract / kernel:.2f} | "
            f"{ref:,.0f} | {contract / ref:.0f}x |"
        )
    fps, n = whole_flight()
    print(
        f"\nwhole estimator: {n} frames of a 60 s flight, both filters, restarts and history: "
        f"{fps:,.0f} frames/s (best of 3)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
