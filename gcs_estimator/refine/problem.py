"""One record to fit: the model's output over it from an initial state, and the output's
sensitivities to the parameters.

The sensitivities are forward differences: each column is an independent flight of the
model, and the columns run in threads (the compiled flights release the GIL), so a fit
uses the machine's cores; each column is the same number whatever the threads.
"""

from __future__ import annotations

import math
import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from gcs_estimator.arrays import FloatArray, IntArray
from gcs_estimator.estimation.delay import delayed_inputs
from gcs_estimator.model.aircraft import Model
from gcs_estimator.model.channels import N_FLIGHT, N_OBS
from gcs_estimator.model.equations import ModelArrays
from gcs_estimator.refine.flights import innovations


def available_cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on every platform
        return os.cpu_count() or 1


_POOLS: dict[int, ThreadPoolExecutor] = {}
_POOLS_LOCK = threading.Lock()


def thread_pool(threads: int | None) -> ThreadPoolExecutor | None:
    """The process's pool of `threads` threads (default: available_cores()), made on
    first use and kept for the next fit; None for one thread."""
    count = available_cores() if threads is None else threads
    if count < 2:
        return None
    with _POOLS_LOCK:
        pool = _POOLS.get(count)
        if pool is None:
            pool = ThreadPoolExecutor(max_workers=count, thread_name_prefix="refine")
            _POOLS[count] = pool
    return pool


DELAY_STEP_S = 1e-5
"""The finite-difference step of a delay [s]: well inside one sample interval, over
which the shifted input is linear in the delay."""


class Problem:
    """One record (t [N], model inputs u [N x m], observations y [N x 7] with 0 where
    mask [N x 7] is 0) and how the model flies over it (Runge-Kutta steps of at most
    max_step [s]; inputs linear between samples, or held). The parameters are the
    model's augmented state (model.n entries), then a delay [s] of each input in
    `delayed` (delayed_inputs; decision 0044), then a factor on each airframe constant
    in `factors` (decision 0054), then the flight states of each further
    piece of the record: segments or flights (decision 0050), each flown from its own
    first frame, the coefficients, biases and delays shared."""

    def __init__(
        self,
        model: Model,
        t: FloatArray,
        u: FloatArray,
        y: FloatArray,
        mask: FloatArray,
        max_step: float,
        linear: bool,
        delayed: IntArray | None = None,
        factors: Sequence[tuple[int, float]] = (),
        pieces: IntArray | None = None,
    ) -> None:
        """pieces: the first frame of each piece after the first (increasing; none: the
        record is one piece)."""
        self.model = model
        self.delayed = np.zeros(0, dtype=np.int64) if delayed is None else delayed
        self.factor_k = np.array([i for i, _ in factors], dtype=np.int64)
        """Which airframe constants (model.k) a factor multiplies (decision 0054)."""
        self.factor_sigma = np.array([s for _, s in factors], dtype=float)
        """Each factor's prior 1-sigma about 1."""
        self.factor_start = model.n + self.delayed.size
        """Where the factors sit in the parameters, after the delays."""
        self.pieces_start = self.factor_start + self.factor_k.size
        """Where the further pieces' flight states sit, after the factors."""
        self.bounds = [0, *(int(i) for i in ([] if pieces is None else pieces)), len(t)]
        """Each piece's first frame, then the record's length."""
        self.t, self.u, self.y, self.mask = t, u, y, mask
        self.max_step = max_step
        self.linear = linear
        self.runs = 0
        self._lock = threading.Lock()
        self.pool: ThreadPoolExecutor | None = None
        """Threads for the sensitivities' columns (None: the calling thread)."""

    def arrays(self, x: FloatArray) -> ModelArrays:
        """The model's arrays with the parameters x's factors on their constants."""
        m = self.model.arrays
        if self.factor_k.size == 0:
            return m
        k = m.k.copy()
        k[self.factor_k] *= x[self.factor_start : self.pieces_start]
        return m._replace(k=k)

    def prior(self, x: FloatArray, columns: IntArray) -> tuple[FloatArray, FloatArray]:
        """The factors' priors as residual rows: (x_j - 1) / sigma_j [factors], and their
        sensitivities [factors x len(columns)] to the parameters `columns` (a factor not
        among them has a zero row)."""
        f = self.factor_start + np.arange(self.factor_k.size)
        e = (x[f] - 1.0) / self.factor_sigma
        J = np.zeros((f.size, columns.shape[0]))
        for i, j in enumerate(f):
            J[i, columns == j] = 1.0 / self.factor_sigma[i]
        return e, J

    def prior_cost(self, x: FloatArray) -> float:
        """The factors' priors' share of the cost (sum of their squared residuals)."""
        e, _ = self.prior(x, np.zeros(0, dtype=np.int64))
        return float(e @ e)

    def state(self, x: FloatArray) -> FloatArray:
        """The model's augmented state of the parameters x."""
        return np.ascontiguousarray(x[: self.model.n])

    def inputs(self, x: FloatArray) -> FloatArray:
        """The model's inputs at the parameters x's delays."""
        if self.delayed.size == 0:
            return self.u
        return delayed_inputs(self.t, self.u, self.delayed, x[self.model.n : self.factor_start])

    def step(self, j: int, value: float) -> float:
        """The finite-difference step of parameter j at `value`: a millionth of its size
        (at least of 1e-3) for a state and a factor, DELAY_STEP_S for a delay."""
        if self.model.n <= j < self.factor_start:
            return DELAY_STEP_S
        return 1e-6 * max(abs(value), 1e-3)

    def pieces(self, x: FloatArray) -> list[tuple[slice, FloatArray]]:
        """Each piece's frames and the augmented state it is flown from: the model's state
        of x with that piece's own flight states (the first piece's: x's own)."""
        state = self.state(x)
        extra = self.pieces_start
        out = []
        for p in range(len(self.bounds) - 1):
            x0 = state
            if p > 0:
                x0 = state.copy()
                x0[:N_FLIGHT] = x[extra + (p - 1) * N_FLIGHT : extra + p * N_FLIGHT]
            out.append((slice(self.bounds[p], self.bounds[p + 1]), x0))
        return out

    def count_run(self) -> None:
        with self._lock:
            self.runs += 1

    def columns(self, column: Callable[[int], FloatArray], count: int) -> list[FloatArray]:
        """column(j) for j < count: in the pool's threads where there is one."""
        if self.pool is None or count < 2:
            return [column(j) for j in range(count)]
        return list(self.pool.map(column, range(count)))

    def run(
        self, x0: FloatArray, q: FloatArray, r: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray, bool]:
        """flights.innovations from x0 at process noise density q and noise variances r,
        piece by piece (each from its own flight states)."""
        self.count_run()
        u = self.inputs(x0)
        arrays = self.arrays(x0)
        parts = []
        for part, start in self.pieces(x0):
            parts.append(
                innovations(
                    start,
                    self.t[part],
                    np.ascontiguousarray(u[part]),
                    self.y[part],
                    self.mask[part],
                    arrays,
                    q,
                    r,
                    self.max_step,
                    self.linear,
                )
            )
            if not parts[-1][3]:
                break
        if len(parts) == 1:
            return parts[0]
        ok = all(p[3] for p in parts) and len(parts) == len(self.bounds) - 1
        if not ok:
            n = len(self.t)
            return np.zeros((n, N_OBS)), np.zeros(n), np.zeros((n, N_OBS)), False
        return (
            np.vstack([p[0] for p in parts]),
            np.concatenate([p[1] for p in parts]),
            np.vstack([p[2] for p in parts]),
            True,
        )

    def cost(self, x0: FloatArray, q: FloatArray, r: FloatArray) -> float:
        """Negative log-likelihood (without its constant): sum e^2 + log det S."""
        e, logdet, _, ok = self.run(x0, q, r)
        c = float(np.sum(e * e) + np.sum(logdet)) + self.prior_cost(x0)
        return c if ok and math.isfinite(c) else math.inf

    def jacobian(
        self, x0: FloatArray, free: IntArray, q: FloatArray, r: FloatArray, e0: FloatArray
    ) -> FloatArray:
        """d e / d x0[free] by forward differences [N*7 x len(free)]."""

        def column(col: int) -> FloatArray:
            j = free[col]
            step = self.step(int(j), float(x0[j]))
            xp = x0.copy()
            xp[j] += step
            e, _, _, ok = self.run(xp, q, r)
            if not ok:
                xp[j] = x0[j] - step
                e, _, _, _ = self.run(xp, q, r)
                step = -step
            out: FloatArray = (e - e0).ravel() / step
            return out

        J = np.empty((e0.size, len(free)))
        for col, values in enumerate(self.columns(column, len(free))):
            J[:, col] = values
        return J
