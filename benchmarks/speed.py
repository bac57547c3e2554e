"""Filter steps per second on one core for the NOC model (predict + update per step).

    python benchmarks/speed.py

Compiled kernel (filters.fast.step) for the EKF and the IEKF with N = 7, through the
estimator's runner and the bare kernel, against the straightforward baseline on the same
model: the plain-numpy reference path (filters.hybrid), as a ratio. Targets: IEKF (N = 7)
>= 20,000 steps/s, EKF >= 50,000 steps/s.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from gcs_estimator.config import load_config_with
from gcs_estimator.estimator import FilterRunner
from gcs_estimator.filters import fast
from gcs_estimator.model.aircraft import build_model
from sim.truth import simulate


def rate(config_path: str, kind: str, backend: str, frames: int, bare: bool) -> float:
    # relinearise_sigma = 0: the IEKF runs all N iterations every step (the configured
    # gate usually stops it after 2 near the solution, which would flatter the figure).
    config = load_config_with(config_path, ["filter.relinearise_sigma=0"])
    fl = simulate(config, seed=1)
    model = build_model(config)
    runner = FilterRunner(kind, model, config, backend)  # type: ignore[arg-type]
    # Start from a converged belief so the timing is of the steady state.
    for i in range(300):
        runner.step(float(fl.t_s[i]), fl.inputs[i], fl.measurements[i])
    n = min(frames, len(fl.t_s) - 300)
    idx = range(300, 300 + n)
    if bare:
        assert runner.belief is not None
        x, P = runner.belief.x, runner.belief.P
        Q, R = runner.process_noise(1e9), runner.R
        tun = config.filter
        t0 = time.perf_counter()
        for i in idx:
            x, P, *_ = fast.step(
                x,
                P,
                fl.inputs[i - 1],
                0.02,
                fl.inputs[i],
                fl.measurements[i],
                Q,
                R,
                runner.iterations,
                0.0,
                tun.relinearise_sigma,
                tun.max_step_s,
                0.0,
                model,
            )
        return n / (time.perf_counter() - t0)
    t0 = time.perf_counter()
    for i in idx:
        runner.step(float(fl.t_s[i]), fl.inputs[i], fl.measurements[i])
    return n / (time.perf_counter() - t0)


def main() -> int:
    cfg = "configs/noc_uav.toml"
    print(
        "| filter | compiled kernel steps/s | compiled via runner steps/s | "
        "numpy reference steps/s | kernel / reference |"
    )
    print("|---|---|---|---|---|")
    for kind in ("EKF", "IEKF"):
        kernel = np.median([rate(cfg, kind, "fast", 2500, True) for _ in range(3)])
        runner = np.median([rate(cfg, kind, "fast", 2500, False) for _ in range(3)])
        ref = rate(cfg, kind, "reference", 300, False)
        label = "IEKF (N = 7)" if kind == "IEKF" else "EKF"
        print(f"| {label} | {kernel:,.0f} | {runner:,.0f} | {ref:,.0f} | {kernel / ref:.0f}x |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
