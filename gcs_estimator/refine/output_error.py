"""Output error, and filter error at held noise levels: Levenberg-Marquardt on the
whitened innovations of flights.innovations.

Output error (calm air) flies the model open loop (no process noise: its innovations are
the output errors). With the noise unknown, each Gauss-Newton iteration first sets each
channel's variance to its mean squared output error (the relaxation method; Jategaonkar
2015, ch. 4). With the noise held, the same iterations run the time-varying filter at
the held levels (filter error's exact likelihood for them).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from gcs_estimator.arrays import BoolArray, FloatArray, IntArray
from gcs_estimator.refine.problem import Problem
from gcs_estimator.refine.result import RefineError

STEP_TOLERANCE = 1e-3
"""Gauss-Newton stops when no parameter moves by more than this share of its sigma."""

Report = Callable[[int, float, float], None]
"""(iteration, cost it started from, largest step in sigmas), after each iteration."""


def scaled_normal_equations(
    J: FloatArray, e: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The Gauss-Newton normal equations of the residuals e and their sensitivities J
    [e.size x p], scaled to a unit diagonal: An = D^-1 J^T J D^-1, gn = D^-1 J^T e and
    d = diag(D) = sqrt(diag(J^T J)); the step in the parameters is -D^-1 solve(An, gn)."""
    A = J.T @ J
    d = np.sqrt(np.maximum(np.diag(A), 1e-300))
    return A / np.outer(d, d), (J.T @ e.ravel()) / d, d


def gauss_newton(
    prob: Problem,
    x: FloatArray,
    free: IntArray,
    q: FloatArray,
    r: FloatArray,
    iterations: int,
    relax: BoolArray | None = None,
    report: Report | None = None,
) -> tuple[FloatArray, FloatArray, int, bool]:
    """Levenberg-Marquardt on the whitened innovations; returns the parameters, the
    measurement variances, iterations used, converged. With `relax` (output error: the
    observed channels), each iteration first sets the channels' variances to their mean
    squared output error, the closed-form maximum of the likelihood over R. `report`
    gets (iteration, cost it started from, step in sigmas) after each iteration."""
    lam = 1e-3
    for it in range(1, iterations + 1):
        if relax is not None:
            r = fit_noise(prob, x, r, relax)
        e, logdet, _, ok = prob.run(x, q, r)
        if not ok:
            raise RefineError(
                "the model, flown over the record from its first frame, does not stay finite; "
                "fit a shorter window (--window FROM:TO) or start nearer"
            )
        cost = float(np.sum(e * e) + np.sum(logdet)) + prob.prior_cost(x)
        ep, Jp = prob.prior(x, free)
        An, gn, d = scaled_normal_equations(
            np.vstack([prob.jacobian(x, free, q, r, e), Jp]), np.concatenate([e.ravel(), ep])
        )
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


def fit_noise(prob: Problem, x: FloatArray, r: FloatArray, observed: BoolArray) -> FloatArray:
    """Output error's noise levels that maximise the likelihood at fixed parameters: each
    observed channel's variance is its mean squared output error (closed form)."""
    ro = np.flatnonzero(observed)
    _, _, raw, _ = prob.run(x, np.zeros(prob.model.arrays.n_dynamic), r)
    n_c = np.maximum(prob.mask.sum(axis=0), 1.0)
    r = r.copy()
    r[ro] = np.maximum(np.sum(raw * raw, axis=0)[ro] / n_c[ro], 1e-300)
    return r
