"""The model flown over the record from an initial state, as the fits need it (compiled).

Both flights predict with the filters' own compiled functions (estimation.filters.fast:
propagate, fly; filters.small for the Cholesky factor and the update), so the fits and
the filters integrate the model, its transition and its process noise the same way:

- `innovations`: an extended Kalman filter on the flight states, the coefficients and
  biases held (their covariance zero). With no process noise the covariance stays zero
  and its innovations are output error's; with process noise at held levels it is
  filter error's time-varying filter, the exact likelihood at those levels.
- `steady_innovations`: a Kalman filter with a constant gain (filter error's
  steady-state formulation).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from gcs_estimator.arrays import FloatArray
from gcs_estimator.estimation.filters import small
from gcs_estimator.estimation.filters.fast import fly, propagate
from gcs_estimator.model import compiled  # noqa: F401  (registers the equations with numba)
from gcs_estimator.model.channels import N_OBS
from gcs_estimator.model.equations import ModelArrays, observe


@njit(cache=True, nogil=True)
def innovations(
    x0: FloatArray,
    t: FloatArray,
    u: FloatArray,
    y: FloatArray,
    mask: FloatArray,
    m: ModelArrays,
    q: FloatArray,
    r: FloatArray,
    max_step: float,
    linear: bool,
) -> tuple[FloatArray, FloatArray, FloatArray, bool]:  # pragma: no cover
    """An extended Kalman filter on the flight states alone, the coefficients and biases
    held at x0's: from the state x0 at t[0] (known exactly), predicting as the filters do
    (fast.propagate: Runge-Kutta steps of at most max_step, process noise of spectral
    density q [n_dynamic]; inputs linear between samples, or held at the earlier one when
    not linear), updating with the observed channels (mask > 0) at noise variances r [7].
    Returns the whitened innovations L^-1 nu [N x 7] (0 where not observed), log det S
    per sample [N], the raw innovations [N x 7] and whether the run stayed finite. With
    q = 0 the innovations are the output errors."""
    N = t.shape[0]
    n = x0.shape[0]
    e = np.zeros((N, N_OBS))
    raw = np.zeros((N, N_OBS))
    logdet = np.zeros(N)
    x = x0.copy()
    P = np.zeros((n, n))
    qn = np.zeros(n)
    qn[: m.n_dynamic] = q
    for i in range(N):
        if i > 0:
            u1 = u[i] if linear else u[i - 1]
            x, P = propagate(x, P, u[i - 1], u1, qn, t[i] - t[i - 1], max_step, m)
            if not np.all(np.isfinite(x)):
                return e, logdet, raw, False
        hx, H = observe(x, u[i], m)
        idx = np.flatnonzero(mask[i] > 0.0)
        k = idx.shape[0]
        if k == 0:
            continue
        Hs = np.ascontiguousarray(H[idx])
        nu = y[i][idx] - hx[idx]
        R = np.diag(r[idx])
        start, cols = small.nonzero_columns(Hs)
        HP = small.sparse_times(Hs, start, cols, P)
        L, ok = small.cholesky(small.gram(HP, Hs, R), 0.0)
        if not ok:  # no likelihood at these noise levels
            return e, logdet, raw, False
        w = np.linalg.solve(L, nu)
        for a in range(k):
            e[i, idx[a]] = w[a]
            raw[i, idx[a]] = nu[a]
            logdet[i] += 2.0 * math.log(L[a, a])
        Kt = small.cholesky_solve(L, HP)
        for a in range(k):
            for j in range(n):
                x[j] += Kt[a, j] * nu[a]
        P = small.joseph(P, Kt, Hs, HP, R)
    return e, logdet, raw, True


@njit(cache=True, nogil=True)
def steady_innovations(
    x0: FloatArray,
    t: FloatArray,
    u: FloatArray,
    y: FloatArray,
    mask: FloatArray,
    m: ModelArrays,
    K: FloatArray,
    max_step: float,
    linear: bool,
) -> tuple[FloatArray, bool]:  # pragma: no cover
    """A Kalman filter with the constant gain K [n_dynamic x 7] on the flight states, the
    coefficients and biases held at x0's: from x0 at t[0], flying the model as the filters
    do (fast.fly; inputs as in `innovations`), correcting with the observed channels
    (mask > 0; a channel without a sample corrects nothing). Returns the innovations
    [N x 7] (0 where not observed) and whether the run stayed finite."""
    N = t.shape[0]
    nd = m.n_dynamic
    raw = np.zeros((N, N_OBS))
    x = x0.copy()
    for i in range(N):
        if i > 0:
            u1 = u[i] if linear else u[i - 1]
            x = fly(x, u[i - 1], u1, t[i] - t[i - 1], max_step, m)
            if not np.all(np.isfinite(x)):
                return raw, False
        hx, _ = observe(x, u[i], m)
        for c in range(N_OBS):
            if mask[i, c] > 0.0:
                raw[i, c] = y[i, c] - hx[c]
        # n_dynamic x 7 multiply-adds: less than entering BLAS for K @ raw[i] costs.
        for a in range(nd):
            for c in range(N_OBS):
                x[a] += K[a, c] * raw[i, c]
    return raw, True
