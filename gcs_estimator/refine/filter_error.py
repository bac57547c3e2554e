"""Filter error with a steady-state gain (turbulence, or anything the model misses).

The classical formulation (Maine and Iliff 1981; Jategaonkar 2015, ch. 5): a Kalman
filter with a steady-state gain corrects the flight states inside the fit
(flights.steady_innovations). The gain comes from the continuous Riccati equation
A P + P A' - P C' R^-1 C P / dt + F F' = 0, linearised at the first frame, where F is the
process noise's distribution (diagonal, estimated with the other parameters) and R the
innovations' covariance (diagonal), which each iteration sets to the innovations' mean
square (the relaxation method). Gauss-Newton steps are kept where the gain corrects no
state by more than its own innovation says (diag(K C) <= 1): at that edge the record's
measurement noise of a channel is spent, and the book's fit of HFB-320 lies on it.
Estimating the innovations' covariance directly, rather than the sensors' and the air's
noise apart, is what makes the noise identifiable from one record: the split between the
two is what a record tells least. Unlike the book, the initial state is fitted too: held
at the first frame's measurement, its error stays in the slow modes as a transient the
coefficients take up (decision 0021).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg import solve_continuous_are
from scipy.optimize import minimize

from gcs_estimator.arrays import BoolArray, FloatArray, IntArray
from gcs_estimator.model import equations as eq
from gcs_estimator.model.channels import N_OBS
from gcs_estimator.refine.flights import steady_innovations
from gcs_estimator.refine.output_error import Report, scaled_normal_equations
from gcs_estimator.refine.problem import Problem
from gcs_estimator.refine.result import RefineError

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


class SteadyFilter:
    """The steady-state filter of a record (the module's docstring) as a function of the
    parameters theta = [x[free], log diag F], at the innovations' covariance R: its gain,
    its innovations, the likelihood, and where the gain over-corrects."""

    def __init__(self, prob: Problem, x: FloatArray, free: IntArray, observed: BoolArray) -> None:
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
        m = self.prob.arrays(x)
        u0 = self.prob.u[0]
        xs = self.prob.state(x)
        _, A = eq.dynamics(xs, u0, m)
        _, H = eq.observe(xs, u0, m)
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
        u = p.inputs(x)
        arrays = p.arrays(x)
        parts = []
        for part, start in p.pieces(x):  # each piece from its own flight states
            raw, ok = steady_innovations(
                start,
                p.t[part],
                np.ascontiguousarray(u[part]),
                p.y[part],
                p.mask[part],
                arrays,
                g[0],
                p.max_step,
                p.linear,
            )
            if not ok:
                return None
            parts.append(raw)
        return parts[0] if len(parts) == 1 else np.vstack(parts)

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
        return float(np.sum(self.whitened(raw, r) ** 2) + self.cost(r)) + self.prior_cost(theta)

    def prior(self, theta: FloatArray) -> tuple[FloatArray, FloatArray]:
        """The factors' priors (Problem.prior) as rows over theta's columns."""
        x, _ = self.unpack(theta)
        e, J = self.prob.prior(x, self.free)
        return e, np.hstack([J, np.zeros((J.shape[0], theta.shape[0] - len(self.free)))])

    def prior_cost(self, theta: FloatArray) -> float:
        return self.prob.prior_cost(self.unpack(theta)[0])

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
        if j < len(self.free):
            return self.prob.step(int(self.free[j]), float(theta[j]))
        return 1e-5


def jacobian(sf: SteadyFilter, theta: FloatArray, r: FloatArray, e0: FloatArray) -> FloatArray:
    """d e / d theta [N*7 x len(theta)] of the whitened innovations, by forward
    differences (backward where the forward point has no gain), across the
    diag(K C) <= 1 edge that a fit can end on."""

    def column(j: int) -> FloatArray:
        step = sf.delta(theta, j)
        for sign in (1.0, -1.0):
            tp = theta.copy()
            tp[j] += sign * step
            raw = sf.run(tp, r, bounded=False)
            if raw is not None:
                out: FloatArray = (sf.whitened(raw, r) - e0).ravel() / (sign * step)
                return out
        return np.zeros(e0.size)

    J = np.empty((e0.size, theta.shape[0]))
    for j, values in enumerate(sf.prob.columns(column, theta.shape[0])):
        J[:, j] = values
    return J


def _constraint(
    sf: SteadyFilter, theta: FloatArray, r: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """diag(K C) - 1 [n_dynamic] (kept <= 0) and its gradient in theta."""
    g0 = sf.gain(theta, r)
    assert g0 is not None
    c0 = g0[1] - 1.0
    G = np.zeros((c0.shape[0], theta.shape[0]))
    for j in range(theta.shape[0]):
        step = sf.delta(theta, j)
        tp = theta.copy()
        tp[j] += step
        g = sf.gain(tp, r)
        if g is not None:
            G[:, j] = (g[1] - 1.0 - c0) / step
    return c0, G


def _step(
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
    sf: SteadyFilter,
    theta: FloatArray,
    r: FloatArray,
    iterations: int,
    report: Report | None,
    relax: bool = True,
) -> tuple[FloatArray, FloatArray, int, bool]:
    """Constrained Levenberg-Marquardt on theta with R relaxed between iterations
    (or held, without relax); returns theta, R, iterations used, converged."""
    lo, hi = LOG_F_RANGE
    k = len(sf.free)
    start = sf.feasible(theta, r)
    if start is None:
        raise RefineError("no process noise level gives a stable filter from the start values")
    theta, r = sf.relaxed(start, r) if relax else (start, r)
    cost = sf.cost(r) + sf.prior_cost(theta) if relax else sf.held_cost(theta, r)
    lam = 1e-3
    tolerance = COST_TOLERANCE * float(np.sum(sf.counts[sf.obs]))
    for it in range(1, iterations + 1):
        # R moved since the last iteration, so did the cost's shape: the damping
        # starts again from at most LAMBDA_RESTART.
        lam = min(lam, LAMBDA_RESTART)
        raw = sf.run(theta, r)
        assert raw is not None  # relaxed() left theta feasible at r
        e0 = sf.whitened(raw, r)
        ep, Jp = sf.prior(theta)
        An, gn, d = scaled_normal_equations(
            np.vstack([jacobian(sf, theta, r, e0), Jp]), np.concatenate([e0.ravel(), ep])
        )
        c0, G = _constraint(sf, theta, r)
        base = float(np.sum(e0 * e0)) + float(ep @ ep)
        moved = 0.0
        for _ in range(12):
            trial = theta + _step(An, gn, d, lam, c0, G)
            trial[k:] = np.clip(trial[k:], lo, hi)
            raw_t = sf.run(trial, r)
            if (
                raw_t is not None
                and float(np.sum(sf.whitened(raw_t, r) ** 2)) + sf.prior_cost(trial) < base
            ):
                moved = float(np.max(np.abs((trial - theta) * d)))
                theta = trial
                lam = max(lam / 10.0, 1e-9)
                break
            lam *= 10.0
        if report is not None:
            report(it, cost, moved)
        if relax:
            theta, r = sf.relaxed(theta, r)
            new = sf.cost(r) + sf.prior_cost(theta)
        else:
            new = sf.held_cost(theta, r)
        done = abs(new - cost) < tolerance
        cost = new
        if done:
            return theta, r, it, True
    return theta, r, iterations, False
