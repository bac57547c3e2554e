"""Maximum likelihood over a whole record: `gcs-estimator refine`.

The filters give an estimate and a covariance online. Once the flight is over, the
record can be fitted as a whole: the initial state, the coefficients and the sensor
biases that make the model, flown through the record's inputs from its first frame,
reproduce the observations best. All fits integrate the model as the filters
predict (Runge-Kutta steps of at most max_step_s, the configured input hold, air density
per sample, sensor placement); the sensitivities are forward differences.

- Output error (calm air): the model flies open loop (`innovations` with no process
  noise: its innovations are the output errors). With the noise unknown, each
  Gauss-Newton iteration first sets each channel's variance to its mean squared output
  error (the relaxation method; Jategaonkar 2015, ch. 4).
- Filter error (turbulence, or anything the model misses): the classical formulation
  (Maine and Iliff 1981; Jategaonkar 2015, ch. 5). A Kalman filter with a steady-state
  gain corrects the flight states inside the fit. The gain comes from the continuous
  Riccati equation A P + P A' - P C' R^-1 C P / dt + F F' = 0, linearised at the first
  frame, where F is the process noise's distribution (diagonal, estimated with the other
  parameters) and R the innovations' covariance (diagonal), which each iteration sets to
  the innovations' mean square (relaxation again). Gauss-Newton steps are kept where the
  gain corrects no state by more than its own innovation says (diag(K C) <= 1): at that
  edge the record's measurement noise of a channel is spent, and the book's fit of
  HFB-320 lies on it. Estimating the innovations' covariance directly, rather than the
  sensors' and the air's noise apart, is what makes the noise identifiable from one
  record: the split between the two is what a record tells least. Unlike the book, the
  initial state is fitted too: held at the first frame's measurement, its error stays in
  the slow modes as a transient the coefficients take up (decision 0021).
- With the noise held (`hold_noise`: the sensors' and the air's levels known), filter
  error runs the time-varying extended Kalman filter on the flight states at those levels
  (`innovations`), the exact likelihood for them.

Uncertainty, four ways:
- the Cramer-Rao bound, M^-1 with M = sum S^T R^-1 S: right when the residuals are
  white, which they are only when the model holds everything the aircraft does;
- the Morelli-Klein correction (J. Aircraft 34(5), 1997), which uses the residuals'
  own autocorrelation: M^-1 (sum_i sum_j S_i^T R^-1 Rvv(i - j) R^-1 S_j) M^-1. Coloured
  residuals (turbulence, what the structure misses) carry less information than white
  ones, and this bound says how much less;
- the structure sigma: how far the fit moves when one channel at a time is trusted half
  as much, beyond what the information given up explains (decision 0022), and never less
  than the session's same check of the filter it started from found for the record
  (refine_run given the session's vehicle, decision 0031);
- the difference sigma (refine_run): how far the fit lands from the filter it started
  from, beyond what the two covariances allow (decision 0030). The filter and the fit
  weigh the record differently; where the model holds they agree, where it does not each
  settles on its own compromise.
The last two added in quadrature to Morelli-Klein's give the sigma to trust on real data.

The sensitivities' columns are independent flights of the model, run in threads (the
kernels release the GIL), so a fit uses the machine's cores; each column is the same
number whatever the threads.

Output error assumes calm air: in turbulence the filters' and filter error's estimates
are the better ones, and the residual colour shows it (the corrected sigma grows). The
method "auto" (the default) chooses from what the filters found: filter error where their
turbulence level over the final pass stands clear of zero, output error otherwise
(choose_method; decision 0025).
"""

from __future__ import annotations

import math
import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from numba import njit
from scipy.linalg import solve_continuous_are
from scipy.optimize import minimize

from gcs_estimator import blas
from gcs_estimator.arrays import BoolArray, FloatArray, IntArray
from gcs_estimator.config import REFINE_METHODS
from gcs_estimator.estimation.estimator import EstimatorResult, FilterKind
from gcs_estimator.estimation.filters.core import MAX_STEP_S
from gcs_estimator.model import compiled  # noqa: F401  (registers the equations with numba)
from gcs_estimator.model import equations as eq
from gcs_estimator.model.aircraft import Model, build_model
from gcs_estimator.model.channels import N_FLIGHT, N_OBS
from gcs_estimator.uncertainty.metrics import correlation_of, identifiability
from gcs_estimator.uncertainty.weighting import VARIANCE_FACTOR, WEIGHT_SHARE

if TYPE_CHECKING:
    from gcs_estimator.runtime.session import VehicleResult


@njit(cache=True)
def _predict(
    x: FloatArray,
    P: FloatArray,
    u0: FloatArray,
    u1: FloatArray,
    span: float,
    m: eq.ModelArrays,
    q: FloatArray,
    max_step: float,
) -> tuple[FloatArray, FloatArray]:  # pragma: no cover
    """x and the flight states' covariance P over span [s]: Runge-Kutta steps of at most
    max_step, the inputs going from u0 to u1, process noise density q."""
    nd = P.shape[0]
    steps = max(1, int(math.ceil(span / max_step - 1e-9)))
    h = span / steps
    eye = np.eye(nd)
    for s in range(steps):
        ua = u0 + (u1 - u0) * (s / steps)
        ub = u0 + (u1 - u0) * ((s + 1) / steps)
        x1, F1, F2, F3, F4 = eq.rk4_step(x, ua, ub, h, m)
        # The transition of the Runge-Kutta step: each stage's slope depends on x
        # through the stages before it.
        d1 = np.ascontiguousarray(F1[:nd, :nd])
        f2 = np.ascontiguousarray(F2[:nd, :nd])
        f3 = np.ascontiguousarray(F3[:nd, :nd])
        f4 = np.ascontiguousarray(F4[:nd, :nd])
        d2 = f2 + 0.5 * h * (f2 @ d1)
        d3 = f3 + 0.5 * h * (f3 @ d2)
        d4 = f4 + h * (f4 @ d3)
        phi = eye + h / 6.0 * (d1 + 2.0 * d2 + 2.0 * d3 + d4)
        P = phi @ P @ phi.T
        for j in range(nd):
            P[j, j] += q[j] * h
        x = x1
    return x, P


@njit(cache=True)
def _cholesky(S: FloatArray) -> tuple[FloatArray, bool]:  # pragma: no cover
    """Lower Cholesky factor of S; False when S is not positive definite (or NaN)."""
    k = S.shape[0]
    L = np.zeros((k, k))
    for a in range(k):
        for b in range(a + 1):
            acc = S[a, b]
            for c in range(b):
                acc -= L[a, c] * L[b, c]
            if a != b:
                L[a, b] = acc / L[b, b]
            elif acc > 1e-12 * S[a, a] and acc > 0.0:
                L[a, a] = math.sqrt(acc)
            else:
                return L, False
    return L, True


@njit(cache=True, nogil=True)
def innovations(
    x0: FloatArray,
    t: FloatArray,
    u: FloatArray,
    y: FloatArray,
    mask: FloatArray,
    m: eq.ModelArrays,
    q: FloatArray,
    r: FloatArray,
    max_step: float,
    linear: bool,
) -> tuple[FloatArray, FloatArray, FloatArray, bool]:  # pragma: no cover
    """An extended Kalman filter on the flight states alone, the coefficients and biases
    held at x0's: from the state x0 at t[0] (known exactly), predicting with Runge-Kutta
    steps of at most max_step and process noise of spectral density q [n_dynamic]
    (inputs linear between samples, or held at the earlier one when not linear),
    updating with the observed channels (mask > 0) at noise variances r [7]. Returns the
    whitened innovations L^-1 nu [N x 7] (0 where not observed), log det S per sample
    [N], the raw innovations [N x 7] and whether the run stayed finite. With q = 0 the
    innovations are the output errors."""
    N = t.shape[0]
    nd = m.n_dynamic
    e = np.zeros((N, N_OBS))
    raw = np.zeros((N, N_OBS))
    logdet = np.zeros(N)
    x = x0.copy()
    P = np.zeros((nd, nd))
    eye = np.eye(nd)
    for i in range(N):
        if i > 0:
            u1 = u[i] if linear else u[i - 1]
            x, P = _predict(x, P, u[i - 1], u1, t[i] - t[i - 1], m, q, max_step)
            if not np.all(np.isfinite(x)):
                return e, logdet, raw, False
        hx, H = eq.observe(x, u[i], m)
        idx = np.flatnonzero(mask[i] > 0.0)
        k = idx.shape[0]
        if k == 0:
            continue
        Hs = np.ascontiguousarray(H[idx][:, :nd])
        nu = y[i][idx] - hx[idx]
        S = Hs @ P @ Hs.T + np.diag(r[idx])
        L, ok = _cholesky(S)
        if not ok:  # no likelihood at these noise levels
            return e, logdet, raw, False
        w = np.linalg.solve(L, nu)
        for a in range(k):
            e[i, idx[a]] = w[a]
            raw[i, idx[a]] = nu[a]
            logdet[i] += 2.0 * math.log(L[a, a])
        K = np.linalg.solve(S, Hs @ P).T
        x[:nd] += K @ nu
        IKH = eye - K @ Hs
        P = IKH @ P @ IKH.T + K @ np.diag(r[idx]) @ K.T
        P = 0.5 * (P + P.T)
    return e, logdet, raw, True


@njit(cache=True, nogil=True)
def steady_innovations(
    x0: FloatArray,
    t: FloatArray,
    u: FloatArray,
    y: FloatArray,
    mask: FloatArray,
    m: eq.ModelArrays,
    K: FloatArray,
    max_step: float,
    linear: bool,
) -> tuple[FloatArray, bool]:  # pragma: no cover
    """A Kalman filter with the constant gain K [n_dynamic x 7] on the flight states, the
    coefficients and biases held at x0's: from x0 at t[0], predicting with Runge-Kutta
    steps of at most max_step (inputs as in `innovations`), correcting with the observed
    channels (mask > 0; a channel without a sample corrects nothing). Returns the
    innovations [N x 7] (0 where not observed) and whether the run stayed finite."""
    N = t.shape[0]
    nd = m.n_dynamic
    raw = np.zeros((N, N_OBS))
    x = x0.copy()
    for i in range(N):
        if i > 0:
            u0 = u[i - 1]
            u1 = u[i] if linear else u0
            span = t[i] - t[i - 1]
            steps = max(1, int(math.ceil(span / max_step - 1e-9)))
            for s in range(steps):
                ua = u0 + (u1 - u0) * (s / steps)
                ub = u0 + (u1 - u0) * ((s + 1) / steps)
                x = eq.rk4_step(x, ua, ub, span / steps, m)[0]
            if not np.all(np.isfinite(x)):
                return raw, False
        hx, _ = eq.observe(x, u[i], m)
        for c in range(N_OBS):
            if mask[i, c] > 0.0:
                raw[i, c] = y[i, c] - hx[c]
        # n_dynamic x 7 multiply-adds: less than entering BLAS for K @ raw[i] costs.
        for a in range(nd):
            for c in range(N_OBS):
                x[a] += K[a, c] * raw[i, c]
    return raw, True


def fit_label(method: str) -> str:
    """A fit's short name in tables and notes: "FE" for filter error (a Refined.method or
    a --method value), "OE" for output error."""
    return "FE" if method.replace("-", " ").startswith("filter error") else "OE"


@dataclass(frozen=True)
class Refined:
    """The maximum-likelihood fit of one record."""

    method: str
    """"output error" (no process noise) or "filter error" (process noise estimated:
    steady-state gain); ", noise held" added when the noise levels were held at the
    configured ones (filter error then runs the time-varying filter)."""
    names: tuple[str, ...]
    """Coefficient names."""
    coefficients: FloatArray
    crb_sigma: FloatArray
    """Cramer-Rao sigma of the coefficients (white residuals assumed)."""
    sigma: FloatArray
    """The sigma to trust: the Cramer-Rao bound corrected for the residuals' colour
    (Morelli-Klein), with structure_sigma and difference_sigma added in quadrature."""
    structure_sigma: FloatArray
    """How far each coefficient depends on how much each channel is trusted (the fit
    re-made with one channel's weight halved at a time; decision 0017's check, applied to
    the whole-record fit): 0 where the model holds. Where the filter it started from was
    checked too (filter_structure_sigma), the larger of the two (decision 0031)."""
    correlation: FloatArray
    """Correlation of the coefficients [p x p] (from the Morelli-Klein covariance)."""
    identifiability: tuple[str, ...]
    bias_names: tuple[str, ...]
    biases: FloatArray
    bias_sigma: FloatArray
    """Corrected sigma of the biases (as `sigma`)."""
    state0: FloatArray
    """Fitted initial flight state [V, alpha, theta, q]."""
    noise_sigma: FloatArray
    """Measurement noise sigma per observation channel [7] (NaN: not observed). Filter
    error with the noise estimated: what the innovations' variance leaves after the
    state's own uncertainty, sqrt(max(R - diag(C P C'), 0))."""
    process_noise: FloatArray
    """Process noise spectral density of V, alpha, theta, q (0 for output error; filter
    error: diag(F F'))."""
    residual_colour: FloatArray
    """Per channel: the information its residuals' autocorrelation leaves, relative to
    white residuals of the same variance, as seen through the parameters' sensitivities
    (trace of S^T Rvv S over trace of S^T rho(0) S): 1 for white residuals, larger when
    they are correlated in time (each sample then tells less)."""
    frames: int
    iterations: int
    converged: bool
    message: str
    choice: str = ""
    """Why this method, when it was chosen from the data ("auto": choose_method); empty
    when it was asked for by name."""
    difference_sigma: FloatArray | None = None
    """How far the fit lands from the filter it started from, beyond what their
    covariances allow (decision 0030, refine_run); None for a fit not started from a
    filter's run."""
    filter_structure_sigma: FloatArray | None = None
    """The structure sigma of the filter the fit started from (its check of the same
    record, weighting.structure_check; NaN where a coefficient was not checked), which
    the fit's structure_sigma does not fall below (decision 0031); None where the run
    made no check or refine_run was given a bare result."""

    @property
    def label(self) -> str:
        """The fit's short name in tables and notes (fit_label)."""
        return fit_label(self.method)

    @property
    def sigma_within_fit(self) -> FloatArray:
        """The corrected sigma from the fit alone: Morelli-Klein's with the structure
        sigma, without difference_sigma."""
        difference = 0.0 if self.difference_sigma is None else self.difference_sigma
        return np.asarray(np.sqrt(np.maximum(self.sigma**2 - difference**2, 0.0)))


class RefineProgress(NamedTuple):
    """Where a fit stands, after each Gauss-Newton iteration."""

    iterations: int
    """Gauss-Newton iterations so far."""
    cost: float
    """Negative log-likelihood (times 2, without its constant) the iteration started
    from."""
    step_sigma: float
    """Largest parameter step of the iteration, in sigmas (about); 0: none accepted."""
    runs: int
    """Filter runs (flights of the model over the record) so far."""


class RefineError(RuntimeError):
    """The fit could not be made (the model, flown over the record, leaves finite
    numbers from the start, or the record holds too few observations)."""


STEP_TOLERANCE = 1e-3
"""Gauss-Newton stops when no parameter moves by more than this share of its sigma."""
Q_FLOOR = 1e-14
"""Smallest process noise density filter error considers (at it: none to speak of)."""
LOG_F_RANGE = (0.5 * math.log(Q_FLOOR), math.log(1e3))
"""Bounds on the logarithm of each process noise distribution F_jj [SI / sqrt(s)] that
filter error searches within (F_jj^2 is the density)."""
EDGE = 1e-7
"""How far inside diag(K C) <= 1 a projected step aims (the edge's curvature)."""
COST_TOLERANCE = 1e-6
"""Filter error stops when an iteration changes the cost (-2 log likelihood) by less than
this per observed sample (the book's 1e-4 relative change of det R would be 1e-4 per
sample; its fit of HFB-320 is reached only below about 1e-6)."""
LAMBDA_RESTART = 1.0
"""The largest Levenberg-Marquardt damping a filter-error iteration starts from."""


class _Problem:
    """One record and the parameters free in the fit."""

    def __init__(
        self,
        model: Model,
        t: FloatArray,
        u: FloatArray,
        y: FloatArray,
        mask: FloatArray,
        max_step: float,
        linear: bool,
    ) -> None:
        self.model = model
        self.t, self.u, self.y, self.mask = t, u, y, mask
        self.max_step = max_step
        self.linear = linear
        self.runs = 0
        self._lock = threading.Lock()
        self.pool: ThreadPoolExecutor | None = None
        """Threads for the sensitivities' columns (None: the calling thread)."""

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
        self.count_run()
        out: tuple[FloatArray, FloatArray, FloatArray, bool] = innovations(
            x0,
            self.t,
            self.u,
            self.y,
            self.mask,
            self.model.arrays,
            q,
            r,
            self.max_step,
            self.linear,
        )
        return out

    def cost(self, x0: FloatArray, q: FloatArray, r: FloatArray) -> float:
        """Negative log-likelihood (without its constant): sum e^2 + log det S."""
        e, logdet, _, ok = self.run(x0, q, r)
        c = float(np.sum(e * e) + np.sum(logdet))
        return c if ok and math.isfinite(c) else math.inf

    def jacobian(
        self, x0: FloatArray, free: IntArray, q: FloatArray, r: FloatArray, e0: FloatArray
    ) -> FloatArray:
        """d e / d x0[free] by forward differences [N*7 x len(free)]."""

        def column(col: int) -> FloatArray:
            j = free[col]
            step = 1e-6 * max(abs(x0[j]), 1e-3)
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


def _gauss_newton(
    prob: _Problem,
    x: FloatArray,
    free: IntArray,
    q: FloatArray,
    r: FloatArray,
    iterations: int,
    relax: BoolArray | None = None,
    report: Callable[[int, float, float], None] | None = None,
) -> tuple[FloatArray, FloatArray, int, bool]:
    """Levenberg-Marquardt on the whitened innovations; returns the parameters, the
    measurement variances, iterations used, converged. With `relax` (output error: the
    observed channels), each iteration first sets the channels' variances to their mean
    squared output error, the closed-form maximum of the likelihood over R. `report`
    gets (iteration, cost it started from, step in sigmas) after each iteration."""
    lam = 1e-3
    for it in range(1, iterations + 1):
        if relax is not None:
            r = _fit_noise(prob, x, r, relax)
        e, logdet, _, ok = prob.run(x, q, r)
        if not ok:
            raise RefineError(
                "the model, flown over the record from its first frame, leaves finite numbers; "
                "fit a shorter window (--from/--to) or start nearer"
            )
        cost = float(np.sum(e * e) + np.sum(logdet))
        J = prob.jacobian(x, free, q, r, e)
        g = J.T @ e.ravel()
        A = J.T @ J
        d = np.sqrt(np.maximum(np.diag(A), 1e-300))
        An = A / np.outer(d, d)
        gn = g / d
        accepted = False
        moved = 0.0
        for _ in range(12):
            try:
                scaled = np.linalg.solve(An + lam * np.eye(len(gn)), gn)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            trial = x.copy()
            trial[free] -= scaled / d
            if prob.cost(trial, q, r) < cost:
                # The step in units of each parameter's Cramer-Rao sigma (about).
                moved = float(np.max(np.abs(scaled)))
                x = trial
                lam = max(lam / 10.0, 1e-9)
                accepted = True
                break
            lam *= 10.0
        if report is not None:
            report(it, cost, moved)
        if not accepted or moved < STEP_TOLERANCE:
            return x, r, it, True
    return x, r, iterations, False


class _Progress:
    """The fits' reports (iteration, cost, step), numbered on across the main fit and its
    re-weighted ones, as RefineProgress with the filter runs so far."""

    def __init__(self, progress: Callable[[RefineProgress], None] | None, prob: _Problem) -> None:
        self.progress = progress
        self.prob = prob
        self.iterations = 0

    def report(self, it: int, cost: float, step: float) -> None:
        self.iterations += 1
        if self.progress is not None:
            self.progress(RefineProgress(self.iterations, cost, step, self.prob.runs))


def _fit_noise(prob: _Problem, x: FloatArray, r: FloatArray, observed: BoolArray) -> FloatArray:
    """Output error's noise levels that maximise the likelihood at fixed parameters: each
    observed channel's variance is its mean squared output error (closed form)."""
    ro = np.flatnonzero(observed)
    _, _, raw, _ = prob.run(x, np.zeros(prob.model.arrays.n_dynamic), r)
    n_c = np.maximum(prob.mask.sum(axis=0), 1.0)
    r = r.copy()
    r[ro] = np.maximum(np.sum(raw * raw, axis=0)[ro] / n_c[ro], 1e-300)
    return r


class _SteadyFilterError:
    """Filter error with a steady-state gain (the module's docstring): the parameters are
    theta = [x[free], log diag F]; the innovations' covariance R is held within each
    Gauss-Newton iteration and set to their mean square between them."""

    def __init__(self, prob: _Problem, x: FloatArray, free: IntArray, observed: BoolArray) -> None:
        self.prob = prob
        self.x = x.copy()
        self.free = free
        self.obs = np.flatnonzero(observed)
        self.nd = prob.model.arrays.n_dynamic
        span = np.diff(prob.t)
        self.dt = float(np.median(span))
        self.counts = np.maximum(prob.mask.sum(axis=0), 1.0)

    def unpack(self, theta: FloatArray) -> tuple[FloatArray, FloatArray]:
        """The augmented state and diag F of theta."""
        x = self.x.copy()
        x[self.free] = theta[: len(self.free)]
        return x, np.exp(theta[len(self.free) :])

    def gain(
        self, theta: FloatArray, r: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray] | None:
        """The steady-state gain K [n_dynamic x 7], diag(K C) [n_dynamic], the state's
        covariance P and C (the observed channels' rows), linearised at the first frame;
        None where the Riccati equation has no stabilising solution."""
        x, f = self.unpack(theta)
        m = self.prob.model.arrays
        u0 = self.prob.u[0]
        _, A = eq.dynamics(x, u0, m)
        _, H = eq.observe(x, u0, m)
        nd, o = self.nd, self.obs
        C = H[o][:, :nd]
        try:
            P = solve_continuous_are(A[:nd, :nd].T, C.T, np.diag(f * f), np.diag(r[o]) * self.dt)
        except (np.linalg.LinAlgError, ValueError):
            return None
        if not np.all(np.isfinite(P)):
            return None
        K = np.zeros((nd, N_OBS))
        K[:, o] = P @ C.T / r[o]
        return K, np.diag(K[:, o] @ C), P, C

    def run(self, theta: FloatArray, r: FloatArray, bounded: bool = True) -> FloatArray | None:
        """The innovations [N x 7], or None where the gain does not exist, the flight
        leaves finite numbers or (when bounded) the gain over-corrects (diag(K C) > 1)."""
        g = self.gain(theta, r)
        if g is None or (bounded and np.max(g[1]) > 1.0):
            return None
        x, _ = self.unpack(theta)
        p = self.prob
        p.count_run()
        raw, ok = steady_innovations(
            x, p.t, p.u, p.y, p.mask, p.model.arrays, g[0], p.max_step, p.linear
        )
        return raw if ok else None

    def variances(self, raw: FloatArray, r: FloatArray) -> FloatArray:
        """R set to the innovations' mean square on the observed channels."""
        out = r.copy()
        o = self.obs
        out[o] = np.maximum(np.sum(raw * raw, axis=0)[o] / self.counts[o], 1e-300)
        return out

    def cost(self, r: FloatArray) -> float:
        """-2 log likelihood without its constant, R at the innovations' mean square."""
        return float(np.sum(self.counts[self.obs] * np.log(r[self.obs])))

    def held_cost(self, theta: FloatArray, r: FloatArray) -> float:
        """-2 log likelihood without its constant at a held R (theta feasible at it)."""
        raw = self.run(theta, r)
        assert raw is not None
        return float(np.sum(self.whitened(raw, r) ** 2) + self.cost(r))

    def stable(self, theta: FloatArray, r: FloatArray) -> bool:
        """Whether the gain at theta and R exists and does not over-correct."""
        g = self.gain(theta, r)
        return g is not None and bool(np.max(g[1]) <= 1.0)

    def feasible(self, theta: FloatArray, r: FloatArray) -> FloatArray | None:
        """theta, or with F scaled down (by bisection on a common factor) until the gain
        at R no longer over-corrects; None when no scale gives a run."""
        k = len(self.free)
        out = theta.copy()
        if not self.stable(theta, r):
            lo, hi = LOG_F_RANGE[0] - float(np.max(theta[k:])), 0.0
            shifted = theta.copy()
            shifted[k:] += lo
            if not self.stable(shifted, r):
                return None
            for _ in range(30):
                mid = 0.5 * (lo + hi)
                trial = theta.copy()
                trial[k:] += mid
                if self.stable(trial, r):
                    lo = mid
                else:
                    hi = mid
            out[k:] += lo
        return out if self.run(out, r) is not None else None

    def relaxed(self, theta: FloatArray, r: FloatArray) -> tuple[FloatArray, FloatArray]:
        """R set to the innovations' mean square at theta (feasible at r), and theta
        with F scaled down where the gain at the new R would over-correct."""
        raw = self.run(theta, r)
        assert raw is not None
        r = self.variances(raw, r)
        out = self.feasible(theta, r)
        if out is None:
            raise RefineError("the filter-error fit lost a stable gain; start nearer")
        return out, r

    def whitened(self, raw: FloatArray, r: FloatArray) -> FloatArray:
        out: FloatArray = raw / np.sqrt(r)
        return out

    def delta(self, theta: FloatArray, j: int) -> float:
        """The finite-difference step of theta[j] (log F's in absolute terms)."""
        return 1e-6 * max(abs(float(theta[j])), 1e-3) if j < len(self.free) else 1e-5

    def jacobian(self, theta: FloatArray, r: FloatArray, e0: FloatArray) -> FloatArray:
        """d e / d theta [N*7 x len(theta)] of the whitened innovations, by forward
        differences (backward where the forward point has no gain), across the
        diag(K C) <= 1 edge that a fit can end on."""

        def column(j: int) -> FloatArray:
            step = self.delta(theta, j)
            for sign in (1.0, -1.0):
                tp = theta.copy()
                tp[j] += sign * step
                raw = self.run(tp, r, bounded=False)
                if raw is not None:
                    out: FloatArray = (self.whitened(raw, r) - e0).ravel() / (sign * step)
                    return out
            return np.zeros(e0.size)

        J = np.empty((e0.size, theta.shape[0]))
        for j, values in enumerate(self.prob.columns(column, theta.shape[0])):
            J[:, j] = values
        return J

    def constraint(self, theta: FloatArray, r: FloatArray) -> tuple[FloatArray, FloatArray]:
        """diag(K C) - 1 [n_dynamic] (kept <= 0) and its gradient in theta."""
        g0 = self.gain(theta, r)
        assert g0 is not None
        c0 = g0[1] - 1.0
        G = np.zeros((c0.shape[0], theta.shape[0]))
        for j in range(theta.shape[0]):
            step = self.delta(theta, j)
            tp = theta.copy()
            tp[j] += step
            g = self.gain(tp, r)
            if g is not None:
                G[:, j] = (g[1] - 1.0 - c0) / step
        return c0, G

    def step(
        self,
        An: FloatArray,
        gn: FloatArray,
        d: FloatArray,
        lam: float,
        c0: FloatArray,
        G: FloatArray,
    ) -> FloatArray:
        """The Levenberg-Marquardt step in theta, projected so that the linearised
        diag(K C) stays <= 1 (a small quadratic programme when the free step would cross
        it)."""
        M = An + lam * np.eye(len(gn))
        z = np.linalg.solve(M, gn)
        Gz = -G / d[None, :]  # constraint change per unit of the scaled step
        if np.all(c0 + Gz @ z <= 0.0):
            out: FloatArray = -z / d
            return out
        sol = minimize(
            lambda v: 0.5 * v @ M @ v - gn @ v,
            np.zeros_like(z),
            jac=lambda v: M @ v - gn,
            constraints=[
                {"type": "ineq", "fun": lambda v: -(c0 + Gz @ v) - EDGE, "jac": lambda v: -Gz}
            ],
            method="SLSQP",
            options={"maxiter": 200, "ftol": 1e-12},
        )
        projected: FloatArray = -np.asarray(sol.x) / d
        return projected

    def fit(
        self,
        theta: FloatArray,
        r: FloatArray,
        iterations: int,
        report: Callable[[int, float, float], None] | None,
        relax: bool = True,
    ) -> tuple[FloatArray, FloatArray, int, bool]:
        """Constrained Levenberg-Marquardt on theta with R relaxed between iterations
        (or held, without relax); returns theta, R, iterations used, converged."""
        lo, hi = LOG_F_RANGE
        k = len(self.free)
        start = self.feasible(theta, r)
        if start is None:
            raise RefineError("no process noise level gives a stable filter from the start values")
        theta, r = self.relaxed(start, r) if relax else (start, r)
        cost = self.cost(r) if relax else self.held_cost(theta, r)
        lam = 1e-3
        tolerance = COST_TOLERANCE * float(np.sum(self.counts[self.obs]))
        for it in range(1, iterations + 1):
            # R moved since the last iteration, so did the cost's shape: the damping
            # starts again from at most LAMBDA_RESTART.
            lam = min(lam, LAMBDA_RESTART)
            raw = self.run(theta, r)
            assert raw is not None  # relaxed() left theta feasible at r
            e0 = self.whitened(raw, r)
            J = self.jacobian(theta, r, e0)
            g = J.T @ e0.ravel()
            A = J.T @ J
            d = np.sqrt(np.maximum(np.diag(A), 1e-300))
            An = A / np.outer(d, d)
            gn = g / d
            c0, G = self.constraint(theta, r)
            base = float(np.sum(e0 * e0))
            moved = 0.0
            for _ in range(12):
                trial = theta + self.step(An, gn, d, lam, c0, G)
                trial[k:] = np.clip(trial[k:], lo, hi)
                raw_t = self.run(trial, r)
                if raw_t is not None and float(np.sum(self.whitened(raw_t, r) ** 2)) < base:
                    moved = float(np.max(np.abs((trial - theta) * d)))
                    theta = trial
                    lam = max(lam / 10.0, 1e-9)
                    break
                lam *= 10.0
            if report is not None:
                report(it, cost, moved)
            if relax:
                theta, r = self.relaxed(theta, r)
                new = self.cost(r)
            else:
                new = self.held_cost(theta, r)
            done = abs(new - cost) < tolerance
            cost = new
            if done:
                return theta, r, it, True
        return theta, r, iterations, False


def _toeplitz_apply(rho: FloatArray, a: FloatArray) -> FloatArray:
    """T @ a for the symmetric Toeplitz T[i, l] = rho[|i - l|] (rho [N], a [N x p]), by FFT."""
    N = a.shape[0]
    size = 1 << int(math.ceil(math.log2(2 * N)))
    kernel = np.zeros(size)
    kernel[:N] = rho
    kernel[size - N + 1 :] = rho[1:][::-1]
    fk = np.fft.rfft(kernel)
    fa = np.fft.rfft(a, n=size, axis=0)
    return np.asarray(np.fft.irfft(fk[:, None] * fa, n=size, axis=0)[:N])


def _autocorrelation(r: FloatArray) -> FloatArray:
    """Biased sample autocorrelation of r [N] at lags 0..N-1 (positive semi-definite)."""
    N = r.shape[0]
    size = 1 << int(math.ceil(math.log2(2 * N)))
    f = np.fft.rfft(r, n=size)
    return np.asarray(np.fft.irfft(f * np.conj(f), n=size)[:N] / N)


def _sandwich(
    J: FloatArray, e: FloatArray, mask: FloatArray, observed: BoolArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """From the whitened residuals e [N x 7] and their sensitivities J [N x 7 x p]: the
    Cramer-Rao covariance M^-1, the Morelli-Klein covariance and each channel's residual
    colour (Refined.residual_colour)."""
    N = e.shape[0]
    M = np.einsum("ncp,ncq->pq", J, J)
    # A parameter the residuals do not feel (a process noise at its lower bound) has no
    # bound: NaN, and the others' without it.
    felt = np.diag(M) > 1e-12 * max(float(np.max(np.diag(M))), 1e-300)
    Minv = np.full_like(M, np.nan)
    sub = M[np.ix_(felt, felt)]
    try:
        Minv[np.ix_(felt, felt)] = np.linalg.inv(sub)
    except np.linalg.LinAlgError:
        Minv[np.ix_(felt, felt)] = np.linalg.pinv(sub)
    J = J[:, :, felt]
    middle = np.zeros((J.shape[2], J.shape[2]))
    colour = np.full(N_OBS, np.nan)
    for c in range(N_OBS):
        if not observed[c]:
            continue
        n_c = max(float(mask[:, c].sum()), 1.0)
        rho = _autocorrelation(e[:, c]) * (N / n_c)
        part = J[:, c, :].T @ _toeplitz_apply(rho, J[:, c, :])
        middle += part
        white = float(rho[0]) * float(np.sum(J[:, c, :] ** 2))
        colour[c] = float(np.trace(part)) / white if white > 0.0 else math.nan
    inner = Minv[np.ix_(felt, felt)]
    cov_mk = np.full_like(M, np.nan)
    cov_mk[np.ix_(felt, felt)] = inner @ middle @ inner
    return Minv, 0.5 * (cov_mk + cov_mk.T), colour


STRUCTURE_ITERATIONS = 4
"""Gauss-Newton iterations of each re-weighted fit (it starts from the fit's end)."""


def _structure_sigma(
    J3: FloatArray,
    k: int,
    observed: BoolArray,
    base: FloatArray,
    refit: Callable[[FloatArray], FloatArray],
) -> FloatArray:
    """The structure sigma of the first k parameters (decision 0017, the filters' check
    applied to a whole-record fit): sqrt(WEIGHT_SHARE * sum_c max(0, d_c^2 - |s_c^2 -
    s^2|)) over the observed channels c, where d_c is how far the fit moves from `base`
    when re-made with channel c's variance times VARIANCE_FACTOR (refit(scale) gives its
    first k parameters), and s_c, s the Cramer-Rao sigmas with and without that (from the
    whitened sensitivities J3 [N x 7 x p])."""
    per_channel = np.einsum("ncp,ncq->cpq", J3, J3)
    M = per_channel.sum(axis=0)
    crb2 = np.diag(np.linalg.pinv(M))[:k]
    excess = np.zeros(k)
    for c in np.flatnonzero(observed):
        scale = np.ones(N_OBS)
        scale[c] = VARIANCE_FACTOR
        try:
            d = refit(scale) - base
        except RefineError:  # no stable fit with this weight: the check has no move
            continue
        less = M - (1.0 - 1.0 / VARIANCE_FACTOR) * per_channel[c]
        excess += np.maximum(0.0, d * d - np.abs(np.diag(np.linalg.pinv(less))[:k] - crb2))
    return np.asarray(np.sqrt(WEIGHT_SHARE * excess))


def available_cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on every platform
        return os.cpu_count() or 1


_POOLS: dict[int, ThreadPoolExecutor] = {}
_POOLS_LOCK = threading.Lock()


def _thread_pool(threads: int | None) -> ThreadPoolExecutor | None:
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


@blas.one_thread_during
def refine(
    model: Model,
    t_s: FloatArray,
    inputs: FloatArray,
    observations: FloatArray,
    start: FloatArray,
    noise_sigma: FloatArray,
    process_noise: FloatArray,
    max_step_s: float,
    linear_inputs: bool = True,
    estimate_process_noise: bool = True,
    iterations: int = 100,
    progress: Callable[[RefineProgress], None] | None = None,
    hold_noise: bool = False,
    threads: int | None = None,
    structure_floor: FloatArray | None = None,
) -> Refined:
    """Maximum likelihood over the record (t_s [N], inputs [N x 2 or 3], observations
    [N x 7], NaN where missing), from the augmented state `start` (flight states at
    t_s[0], coefficients, biases), by the module docstring's methods: output error
    (estimate_process_noise False), filter error with a steady-state gain (the process
    noise distribution and the innovations' covariance estimated with the parameters), or
    with hold_noise the noise levels kept at noise_sigma and process_noise (the sensors'
    and the air's known levels; filter error then runs the time-varying filter) and only
    the parameters fitted. `progress` hears after each Gauss-Newton iteration where the
    fit stands. The sensitivities' columns run in `threads` threads (default: the cores
    this process may use); the fit is the same whatever their number. structure_floor
    (per entry of the augmented state, NaN where none): a structure sigma the fit's own
    check may not fall below (refine_run: the filter's check of the same record)."""
    t = np.ascontiguousarray(t_s, dtype=float)
    if t.shape[0] < 10 or np.any(np.diff(t) <= 0.0):
        raise RefineError("the fit needs at least 10 frames in increasing time order")
    u = np.ascontiguousarray([model.inputs(row) for row in inputs], dtype=float)
    y = np.asarray(observations, float)
    mask = np.isfinite(y).astype(float)
    observed = mask.sum(axis=0) >= 10
    mask[:, ~observed] = 0.0
    y = np.ascontiguousarray(np.where(mask > 0, y, 0.0))
    prob = _Problem(model, t, u, y, mask, max_step_s, linear_inputs)
    prob.pool = _thread_pool(threads)
    x = np.asarray(start, float).copy()
    nd = model.arrays.n_dynamic
    q = np.asarray(process_noise, float)[:nd].copy() if estimate_process_noise else np.zeros(nd)
    r = np.where(observed, np.asarray(noise_sigma, float) ** 2, 1.0)
    e0, _, _, ok = prob.run(x, q, r)
    if not ok:
        raise RefineError("the model, flown from the start values, leaves finite numbers")
    # Parameters the observations do not see (a bias of a channel without data) stay.
    probe = prob.jacobian(x, np.arange(x.shape[0]), q, r, e0)
    free = np.flatnonzero(np.linalg.norm(probe, axis=0) > 0.0)
    counter = _Progress(progress, prob)
    report = counter.report
    steady = estimate_process_noise and not hold_noise
    n = x.shape[0]
    k = len(free)
    refit: Callable[[FloatArray], FloatArray]
    if steady:
        fe = _SteadyFilterError(prob, x, free, observed)
        theta0 = np.concatenate([x[free], np.log(np.sqrt(np.maximum(q, Q_FLOOR)))])
        theta, r, total, converged = fe.fit(theta0, r, iterations, report)
        x, f = fe.unpack(theta)
        end_theta, end_r = theta, r

        def refit(scale: FloatArray) -> FloatArray:
            fit = fe.fit(end_theta, end_r * scale, STRUCTURE_ITERATIONS, report, relax=False)
            return fit[0][:k]

        raw = fe.run(theta, r)
        assert raw is not None
        e = fe.whitened(raw, r)
        J = fe.jacobian(theta, r, e)
        gain = fe.gain(theta, r)
        assert gain is not None
        _, _, P, C = gain
        state_var = np.zeros(N_OBS)
        state_var[fe.obs] = np.einsum("ij,jk,ik->i", C, P, C)
        q = f * f
        noise = np.where(observed, np.sqrt(np.maximum(r - state_var, 0.0)), np.nan)
    else:
        # Output error with the noise free: R in closed form inside each iteration; with
        # the noise held, output error or the time-varying filter at the held levels.
        relax = None if hold_noise else observed
        x, r, total, converged = _gauss_newton(prob, x, free, q, r, iterations, relax, report)
        e, _, _, _ = prob.run(x, q, r)
        J = prob.jacobian(x, free, q, r, e)
        noise = np.where(observed, np.sqrt(r), np.nan)
        end_x, end_r = x, r

        def refit(scale: FloatArray) -> FloatArray:
            fit = _gauss_newton(
                prob, end_x, free, q, end_r * scale, STRUCTURE_ITERATIONS, None, report
            )
            return fit[0][free]

    J3 = J.reshape(e.shape[0], N_OBS, J.shape[1])
    Minv, cov_mk, colour = _sandwich(J3, e, mask, observed)
    # The state's free entries lead the parameters (filter error's log F follow them).
    structure = np.full(n, np.nan)
    structure[free] = _structure_sigma(J3, k, observed, x[free], refit)
    if structure_floor is not None:
        structure[free] = np.fmax(structure[free], np.asarray(structure_floor, float)[free])
    crb = np.full(n, np.nan)
    mk = np.full(n, np.nan)
    crb[free] = np.sqrt(np.diag(Minv)[:k])
    # Morelli-Klein's and the structure's in quadrature, never below Cramer-Rao's.
    corrected = np.maximum(np.diag(cov_mk)[:k], 0.0) + structure[free] ** 2
    mk[free] = np.maximum(np.sqrt(corrected), crb[free])
    full = np.zeros((n, n))
    full[np.ix_(free, free)] = cov_mk[:k, :k]
    cs = model.coefficients
    corr = correlation_of(full[cs, cs])
    coefficients = x[cs].copy()
    bs = model.biases
    method = "filter error" if estimate_process_noise else "output error"
    if hold_noise:
        method += ", noise held"
    msg = "converged" if converged else f"stopped after {total} Gauss-Newton iterations"
    return Refined(
        method=method,
        names=model.names,
        coefficients=coefficients,
        crb_sigma=crb[cs],
        sigma=mk[cs],
        structure_sigma=structure[cs],
        correlation=corr,
        identifiability=identifiability(coefficients, mk[cs], corr),
        bias_names=model.bias_names,
        biases=x[bs].copy(),
        bias_sigma=mk[bs],
        state0=x[:N_FLIGHT].copy(),
        noise_sigma=noise,
        process_noise=q.copy(),
        residual_colour=colour,
        frames=int(t.shape[0]),
        iterations=counter.iterations,
        converged=converged,
        message=f"{msg} ({prob.runs} filter runs)",
    )


TURBULENT_SHARE = 0.5
"""method "auto", where the filters measured no level over the pass (a fixed level:
[filter.turbulence] adaptive = false): filter error when the level was applied in at
least this share of the final pass."""


def choose_method(result: EstimatorResult, kind: FilterKind = "IEKF") -> tuple[str, str]:
    """The whole-record fit for this run ("auto"; decision 0025): filter error where
    filter `kind`'s turbulence level averaged over its final pass stands at least
    [filter.turbulence] detection_sigma standard errors above zero (the filters found
    turbulence in the record as a whole), output error otherwise; and why, in words. With
    no level measured (a fixed one), filter error where it was applied in at least
    TURBULENT_SHARE of the pass."""
    fr = result.filters.get(kind)
    if fr is None or fr.track is None or len(fr.track.t) == 0:
        raise RefineError("no frames to refine (the run kept no history or saw no data)")
    threshold = result.config.filter.turbulence.detection_sigma
    if math.isfinite(fr.gust_pass_z):
        turbulent = fr.gust_pass_z >= threshold
        seen = (
            f"the {kind}'s turbulence level over its final pass, σ_w {fr.gust_pass_sigma:.2f} "
            f"m/s, is {fr.gust_pass_z:+.1f} standard errors from zero (turbulent from "
            f"{threshold:g})"
        )
    else:
        level = fr.track.gust_sigma[result.final_pass_from :]
        share = float(np.mean(level > 0.0)) if level.size else 0.0
        seen = f"the {kind} applied a turbulence level in {100.0 * share:.0f} % of its final pass"
        turbulent = share >= TURBULENT_SHARE
    if turbulent:
        return "filter-error", f"{seen}: turbulent air, so filter error"
    return "output-error", f"{seen}: calm air, so output error"


def refine_run(
    run: EstimatorResult | VehicleResult,
    method: str = "auto",
    kind: FilterKind = "IEKF",
    window_s: tuple[float | None, float | None] = (None, None),
    progress: Callable[[RefineProgress], None] | None = None,
    hold_noise: bool = False,
    threads: int | None = None,
) -> Refined:
    """Refine a finished run (an estimator's result, or a session's vehicle): fit the
    frames the estimator saw (optionally only those within window_s, seconds after the
    first frame), starting from filter `kind`'s final coefficients and biases and the
    first frame's measured flight states. method "auto":
    the one choose_method picks, with its reason in the fit's `choice`. hold_noise:
    the noise levels stay instead of being estimated: the measurement noise where the
    filters' final pass had it (the config's [filter] measurement_sigma, or the data's
    with measurement_noise = "data"), the process noise at the config's. threads: as
    refine's. A vehicle whose session made the structure check brings filter `kind`'s
    structure sigma, which the fit's own does not fall below (decision 0031)."""
    if isinstance(run, EstimatorResult):
        result, filter_structure = run, None
    else:
        result, check = run.result, run.structure
        filter_structure = None if check is None or check.skipped else check.sigma.get(kind)
    if method not in REFINE_METHODS:
        raise ValueError(f"refine method {method!r}: allowed {list(REFINE_METHODS)}")
    choice = ""
    if method == "auto":
        method, choice = choose_method(result, kind)
    fr = result.filters.get(kind)
    if fr is None or fr.track is None or len(fr.track.t) == 0:
        raise RefineError("no frames to refine (the run kept no history or saw no data)")
    tr = fr.track
    rel = tr.t - tr.t[0]
    lo = -math.inf if window_s[0] is None else window_s[0]
    hi = math.inf if window_s[1] is None else window_s[1]
    keep = (rel >= lo) & (rel <= hi)
    # Frames repeated at one time (a clock that stalled) carry no new interval to fly.
    idx = np.flatnonzero(keep)
    if idx.size:
        idx = idx[np.concatenate([[True], np.diff(tr.t[idx]) > 0.0])]
    if idx.size < 10:
        raise RefineError(f"only {idx.size} frames in the window {window_s}; 10 needed")
    config = result.config
    model = build_model(config, gust_states=False)
    start = np.zeros(model.n)
    start[model.coefficients] = fr.coefficients
    start[model.biases] = fr.biases
    first = idx[0]
    measured = tr.y[first, :N_FLIGHT] - _bias_on_flight(model, fr.biases)
    start[:N_FLIGHT] = np.where(np.isfinite(measured), measured, tr.x[first, :N_FLIGHT])
    tuning = config.filter
    floor = None
    if filter_structure is not None:
        floor = np.full(model.n, np.nan)
        floor[model.coefficients] = np.asarray(filter_structure, float)
    fit = refine(
        model,
        tr.t[idx],
        tr.u[idx],
        tr.y[idx],
        start,
        np.asarray(result.measurement_sigma or tuning.measurement_sigma, float),
        np.asarray(tuning.process_noise.states, float),
        MAX_STEP_S,
        linear_inputs=config.data.input_hold == "linear",
        estimate_process_noise=method == "filter-error",
        progress=progress,
        hold_noise=hold_noise,
        threads=threads,
        structure_floor=floor,
    )
    difference = difference_sigma(fit, fr.coefficients, fr.sigma)
    sigma = np.sqrt(fit.sigma**2 + difference**2)
    return replace(
        fit,
        choice=choice,
        difference_sigma=difference,
        filter_structure_sigma=None if floor is None else floor[model.coefficients],
        sigma=sigma,
        identifiability=identifiability(fit.coefficients, sigma, fit.correlation),
    )


def difference_sigma(
    fit: Refined, filter_coefficients: FloatArray, filter_sigma: FloatArray
) -> FloatArray:
    """How far the fit's coefficients land from a filter's estimate of the same record
    beyond what their covariances allow: sqrt(max(0, d^2 - |s_f^2 - s^2|)), d the
    difference, s_f the filter's covariance sigma and s the fit's Cramer-Rao sigma
    (decision 0030). Where the model holds both estimate the same values and d has about
    the variance their covariances differ by (Hausman 1978): nothing is added. Where it
    does not, the filter and the fit weigh the record differently (the filter's noise
    model against the fit's fitted or held one) and settle on different compromises;
    either may carry that much bias."""
    d = np.asarray(fit.coefficients, float) - np.asarray(filter_coefficients, float)
    allowed = np.abs(np.asarray(filter_sigma, float) ** 2 - fit.crb_sigma**2)
    excess = np.where(np.isfinite(allowed), np.maximum(0.0, d * d - allowed), 0.0)
    return np.asarray(np.sqrt(excess))


def _bias_on_flight(model: Model, biases: FloatArray) -> FloatArray:
    """The estimated biases on the directly observed flight-state channels [4]."""
    out = np.zeros(N_FLIGHT)
    for ch, b in zip(model.arrays.bias_channel, biases, strict=True):
        if ch < N_FLIGHT:
            out[ch] += b
    return out
