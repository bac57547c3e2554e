"""Filter steps per second on one core for the NOC model (predict + update per step).

    python benchmarks/speed.py

Per filter (the EKF; the IEKF with the configured relinearisation gate, which stops it
after the first iteration near the solution; and the IEKF with all N = 7 iterations every
step), CPU time, best of 9, from a converged state over 2500 frames of a flight:
- kernel: the compiled backend's one call per step on a belief kept in one buffer
  (filters.fast.lane_kernel: process noise, prediction, update, health check, gust
  matching), with nothing around it;
- runner: one filter's step as the estimator's runner takes it for each frame
  (Runner.one: the lane's step, Lane.step, the health count and the
  frame's output; the target figure);
- FilterState contract: the same step through filters.core's guarded step on a
  FilterState, as the numpy reference is called below;
- blocks: a lane's block step (Lane.block, one compiled call for many frames), 10
  frames a call as a restart's re-run steps its buffered frames beside the live pass, and
  100 a call;
- flops per step: counted from the loop bounds of the step's linear algebra (the model's
  own equations not counted), and the rate the runner's step runs them at as a share of
  the machine's small-matrix rate (a 15 x 15 product through BLAS in a compiled loop,
  measured here);
- numpy reference: the reference backend through the same contract;
- filterpy: filterpy's ExtendedKalmanFilter on the same model functions (the numpy
  equations, Runge-Kutta state and transition matrix), all channels every frame.
Then a whole 60 s flight through the estimator (both filters, restarts, history):
frames per second.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import record  # benchmarks/record.py: the script's directory is on sys.path
from numba import njit

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.estimation.estimator import Estimator
from gcs_estimator.estimation.filters import core, fast
from gcs_estimator.estimation.filters.core import FilterKind, FilterState, Tuning
from gcs_estimator.estimation.filters.lane import Lane, stepper
from gcs_estimator.model import equations as eq
from gcs_estimator.model.aircraft import Model, build_model
from gcs_estimator.model.channels import N_OBS
from gcs_estimator.runtime.session import run_recording
from sim.truth import Flight, simulate

REPEATS = 9
"""Timed runs per figure, the best kept (as timeit does): on a shared machine the others
measure its neighbours."""

WARM = 300
"""Frames stepped before timing, so that the timing is of the steady state."""

BLOCKS = (10, 100)
"""Frames per block call: a re-run's frames per new frame (filter.restart_frames_per_step),
and more."""

FILTERS: tuple[tuple[str, str, list[str]], ...] = (
    ("EKF", "EKF", []),
    ("IEKF (default gate)", "IEKF", []),
    ("IEKF (N = 7)", "IEKF", ["filter.relinearise_sigma=0"]),
)
"""(label, filter kind, config overrides)."""

Step = Callable[..., Any]


class Setup:
    """One filter on the NOC flight, stepped to WARM frames."""

    def __init__(self, kind: str, overrides: list[str]) -> None:
        self.kind = kind
        self.config: AircraftConfig = load_config("noc_uav", overrides)
        self.flight: Flight = simulate(self.config, seed=1)
        self.model: Model = build_model(self.config)
        self.tuning: Tuning = core.tuning_of(self.config, self.model, kind)  # type: ignore[arg-type]
        step = stepper("fast")
        f, inputs = self.flight, self.model.inputs  # u as the equations take it (3 values)
        s = core.initial_state(
            self.model, self.tuning, f.t_s[0], inputs(f.inputs[0]), f.measurements[0]
        )
        for i in range(WARM):
            u = inputs(f.inputs[i])
            s, _ = step(s, float(f.t_s[i]), u, f.measurements[i], self.tuning, self.model)
        self.state: FilterState = s

    def rate(self, step: Step, frames: int) -> tuple[float, float]:
        """(steps per second, mean update iterations per step)."""
        f, s = self.flight, self.state
        n = min(frames, len(f.t_s) - WARM)
        us = [self.model.inputs(v) for v in f.inputs[WARM : WARM + n]]
        iterations = 0
        t0 = time.process_time()
        for i in range(WARM, WARM + n):
            u = us[i - WARM]
            s, info = step(s, float(f.t_s[i]), u, f.measurements[i], self.tuning, self.model)[:2]
            iterations += info.iterations
        return n / (time.process_time() - t0), iterations / n

    def frames(self, count: int) -> tuple[int, list[float], FloatArray, FloatArray]:
        """(n, times, inputs as the equations take them, observations) of the n <= count
        frames after WARM."""
        f = self.flight
        n = min(count, len(f.t_s) - WARM)
        u = np.array([self.model.inputs(v) for v in f.inputs[WARM : WARM + n]])
        return n, [float(v) for v in f.t_s[WARM : WARM + n]], u, f.measurements[WARM : WARM + n]

    def kernel_rate(self, count: int) -> float:
        """Steps per second of the compiled call alone (fast.lane_kernel)."""
        n, t, u, y = self.frames(count)
        buf = fast.belief_buffer(self.state)
        tf, ti = fast.pack(self.tuning, self.model.arrays)
        width = fast.output_width(self.model.n)
        kernel = fast.lane_kernel
        t0 = time.process_time()
        for i in range(n):
            kernel(buf, t[i], u[i], y[i], tf, ti, np.empty(width))
        return n / (time.process_time() - t0)

    def runner_rate(self, count: int) -> float:
        """Steps per second of one filter as the estimator's runner steps it for each
        frame (Runner.one on the lane of the converged state)."""
        n, t, u, y = self.frames(count)
        est = Estimator(self.config)
        kind: FilterKind = self.kind  # type: ignore[assignment]
        states: dict[FilterKind, Lane | None] = {kind: Lane(self.state, "fast")}
        advance, tuning = est.runner.one, self.tuning
        t0 = time.process_time()
        for i in range(n):
            advance(kind, states, t[i], u[i], y[i], True, tuning)
        return n / (time.process_time() - t0)

    def block_rate(self, count: int, size: int) -> float:
        """Steps per second through a lane's block step, `size` frames a call."""
        n, times, u, y = self.frames(count)
        t = np.array(times)
        lane = Lane(self.state, "fast")
        t0 = time.process_time()
        for i in range(0, n, size):
            j = i + size
            _, counts = lane.block(t[i:j], u[i:j], y[i:j], self.tuning, self.model)
            assert counts == (0, 0, 0), "a healthy flight fails no update"
        return n / (time.process_time() - t0)

    def pattern(self) -> tuple[int, int, int, int]:
        """(n, n_dynamic, channels, non-zeros of H) at the converged state."""
        _, H = eq.observe(self.state.x, self.flight.inputs[WARM], self.model.arrays)
        return self.model.n, self.model.arrays.n_dynamic, N_OBS, int(np.count_nonzero(H))


def step_flops(n: int, d: int, k: int, nnz: int, linearisations: float, rk_steps: int = 1) -> float:
    """Floating-point operations of one step's linear algebra, from the loop bounds of
    filters.fast and filters.small (a multiply-add counts 2); `linearisations` of the
    observation (the update's iterations, and the gate's look at a second one)."""
    predict = rk_steps * (
        3 * 2 * d * d * n  # Runge-Kutta stages of the transition matrix
        + 8 * d * n  # its weighted sums
        + 2 * d * n * n
        + 2 * d * d * n
        + 4 * d * n  # congruence
        + n
        + 5 * d * n
        + 5 * d * d * n  # process noise (Simpson)
    )
    linearise = 2 * nnz * n + k * (k + 1) * n + k**3 / 3  # H P, S, Cholesky
    update = (
        2 * N_OBS * n  # gate
        + 2 * k * k  # NIS
        + linearisations * (linearise + 2 * k * k * n + 4 * k * n)  # gain, iterate
    )
    joseph = 2 * n * n * k + 2 * nnz * n + 2 * n * k + n * (n + 1) * k  # R diagonal
    return predict + update + joseph


@njit(cache=True)
def _products(A: np.ndarray, times: int) -> float:  # pragma: no cover
    acc = 0.0
    for _ in range(times):
        acc += (A @ A)[0, 0]
    return acc


def small_matrix_gflops() -> float:
    """The machine's rate on 15 x 15 products through BLAS, from compiled code: best of 5."""
    A = np.random.default_rng(0).standard_normal((15, 15))
    _products(A, 10)
    best = 0.0
    for _ in range(5):
        t0 = time.perf_counter()
        _products(A, 20000)
        best = max(best, 20000 * 2 * 15**3 / (time.perf_counter() - t0) / 1e9)
    return best


def filterpy_rate(setup: Setup, frames: int) -> float | None:
    """filterpy's EKF over the same frames, the model's numpy functions, steps/s."""
    try:
        from filterpy.kalman import ExtendedKalmanFilter
    except ImportError:
        return None
    model, tuning, f = setup.model, setup.tuning, setup.flight
    n = model.n
    eye = np.eye(n)
    ekf = ExtendedKalmanFilter(dim_x=n, dim_z=N_OBS)
    ekf.x = setup.state.x.copy()
    ekf.P = setup.state.P.copy()
    ekf.R = tuning.R.copy()
    count = min(frames, len(f.t_s) - WARM)
    t0 = time.process_time()
    for i in range(WARM, WARM + count):
        dt = float(f.t_s[i] - f.t_s[i - 1])
        u0, u1 = model.inputs(f.inputs[i - 1]), model.inputs(f.inputs[i])
        x1, *rows = eq.rk4_step(ekf.x, u0, u1, dt, model.arrays)
        F1, F2, F3, F4 = (np.vstack([r, np.zeros((n - r.shape[0], n))]) for r in rows)
        K2 = F2 @ (eye + 0.5 * dt * F1)
        K3 = F3 @ (eye + 0.5 * dt * K2)
        K4 = F4 @ (eye + dt * K3)
        ekf.F = eye + dt / 6.0 * (F1 + 2.0 * K2 + 2.0 * K3 + K4)
        ekf.Q = np.diag(tuning.q) * dt
        ekf.predict()
        ekf.x = x1
        ekf.update(
            f.measurements[i],
            lambda x, u=u1: eq.observe(x, u, model.arrays)[1],
            lambda x, u=u1: eq.observe(x, u, model.arrays)[0],
        )
    return count / (time.process_time() - t0)


def whole_flight() -> tuple[float, float, int]:
    """Frames per second of a 60 s flight through the estimator, both filters, its
    results included but for the structure check; and the check's CPU time [s] (it
    replays the final pass at the end: weighting.py). Best of three each."""
    config = load_config("noc_uav", [])
    unchecked = load_config("noc_uav", ["filter.structure_check=off"])
    flight = simulate(config, seed=1)

    def cpu(c: AircraftConfig) -> float:
        t0 = time.process_time()
        run_recording(c, flight.t_s, flight.inputs, flight.measurements)
        return time.process_time() - t0

    plain = min(cpu(unchecked) for _ in range(3))
    checked = min(cpu(config) for _ in range(3))
    return len(flight.t_s) / plain, checked - plain, len(flight.t_s)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    record.add_argument(ap, "speed")
    args = ap.parse_args()
    with record.recorded("speed", args.record, "Speed: filter steps per second"):
        return run()


def run() -> int:
    fast_step, ref_step = stepper("fast"), stepper("reference")
    peak = small_matrix_gflops()
    print(f"small-matrix rate of this machine: {peak:.2f} GFLOP/s (15 x 15 products, BLAS)\n")
    print(
        "| filter | kernel steps/s | runner steps/s | FilterState contract steps/s | "
        + "".join(f"blocks of {b} steps/s | " for b in BLOCKS)
        + "iterations/step | kflop/step | "
        "GFLOP/s (runner) | share of small-matrix rate | numpy reference steps/s | "
        "filterpy EKF steps/s |"
    )
    print("|---" * (10 + len(BLOCKS)) + "|")
    for label, kind, overrides in FILTERS:
        setup = Setup(kind, overrides)
        kernel = max(setup.kernel_rate(2500) for _ in range(REPEATS))
        runner = max(setup.runner_rate(2500) for _ in range(REPEATS))
        runs = [setup.rate(fast_step, 2500) for _ in range(REPEATS)]
        contract = max(r[0] for r in runs)
        blocks = "".join(
            f"{max(setup.block_rate(2500, b) for _ in range(REPEATS)):,.0f} | " for b in BLOCKS
        )
        iterations = runs[0][1]
        # The relinearisation gate linearises a second time to decide, kept or not.
        gated = kind == "IEKF" and setup.tuning.relinearise > 0.0 and setup.tuning.iterations > 1
        flops = step_flops(*setup.pattern(), max(iterations, 2.0) if gated else iterations)
        gflops = flops * runner / 1e9
        ref = setup.rate(ref_step, 300)[0]
        fp = filterpy_rate(setup, 300) if kind == "EKF" else None
        fp_text = "-" if fp is None else f"{fp:,.0f}"
        print(
            f"| {label} | {kernel:,.0f} | {runner:,.0f} | {contract:,.0f} | {blocks}"
            f"{iterations:.2f} | {flops / 1e3:.1f} | {gflops:.2f} | {gflops / peak:.1%} | "
            f"{ref:,.0f} | {fp_text} |"
        )
    fps, check_s, n = whole_flight()
    print(
        f"\nwhole estimator: {n} frames of a 60 s flight, both filters, restarts and history: "
        f"{fps:,.0f} frames/s (best of 3); the structure check at its end "
        f"(filter.structure_check): {check_s:.2f} s of CPU more"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
