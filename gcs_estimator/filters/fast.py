"""Compiled filter step for the aircraft model: the same maths as filters.hybrid, fused.

One call predicts (classical Runge-Kutta of x and of the transition matrix of P) and runs
the (iterated) measurement update, exploiting the structure of the augmented model: the
coefficient rows of F are zero, so the transition matrix differs from I in 4 rows and
Phi P Phi^T costs 4 x n x n instead of n^3. tests/filters/test_fast.py checks it against
the numpy reference path step by step.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from gcs_estimator.model.aircraft import Model
from gcs_estimator.model.equations import N_OBS, N_STATE, FloatArray, IntArray, dynamics, observe

PSD_JITTER = 1e-12  # same meaning as filters.hybrid.PSD_JITTER


@njit(cache=True)
def _congruence(M: FloatArray, D: FloatArray) -> FloatArray:  # pragma: no cover
    """(I + E) M (I + E)^T for symmetric M, where E is zero but for its first N_STATE
    rows, D: M + E M + M E^T + E M E^T at 4 x n x n instead of n^3."""
    DM = D @ M
    out = M.copy()
    n = M.shape[0]
    for i in range(N_STATE):
        for j in range(n):
            out[i, j] += DM[i, j]
            out[j, i] += DM[i, j]
    DMD = DM @ np.ascontiguousarray(D.T)
    for i in range(N_STATE):
        for j in range(N_STATE):
            out[i, j] += DMD[i, j]
    return out


@njit(cache=True)
def _propagate(
    x: FloatArray,
    P: FloatArray,
    u: FloatArray,
    Q: FloatArray,
    dt: float,
    max_step: float,
    k: FloatArray,
    axis: IntArray,
    regressor: IntArray,
) -> tuple[FloatArray, FloatArray]:  # pragma: no cover
    """hybrid.propagate for the aircraft: rows >= N_STATE of F are zero (coefficients
    have no dynamics), so the transition matrix differs from I in its first N_STATE
    rows only, and each Runge-Kutta stage of it is N_STATE x n."""
    if dt <= 0.0:
        return x.copy(), P.copy()
    steps = max(1, int(math.ceil(dt / max_step - 1e-9)))
    h = dt / steps
    for _ in range(steps):
        f1, F1 = dynamics(x, u, k, axis, regressor)
        f2, F2 = dynamics(x + 0.5 * h * f1, u, k, axis, regressor)
        f3, F3 = dynamics(x + 0.5 * h * f2, u, k, axis, regressor)
        f4, F4 = dynamics(x + h * f3, u, k, axis, regressor)
        x = x + h / 6.0 * (f1 + 2.0 * f2 + 2.0 * f3 + f4)
        # Stages of Phi' = F Phi, Phi(0) = I: K = F (I + c E) = F + c F[:, :N] D.
        K1 = np.ascontiguousarray(F1[:N_STATE])
        K2 = F2[:N_STATE] + 0.5 * h * (np.ascontiguousarray(F2[:N_STATE, :N_STATE]) @ K1)
        K3 = F3[:N_STATE] + 0.5 * h * (np.ascontiguousarray(F3[:N_STATE, :N_STATE]) @ K2)
        K4 = F4[:N_STATE] + h * (np.ascontiguousarray(F4[:N_STATE, :N_STATE]) @ K3)
        D = h / 6.0 * (K1 + 2.0 * K2 + 2.0 * K3 + K4)
        D_m = 0.25 * h * (K1 + K2)
        Qd = h / 6.0 * (Q + 4.0 * _congruence(Q, D_m) + _congruence(Q, D))
        P = _congruence(P, D) + Qd
    return x, 0.5 * (P + P.T)


@njit(cache=True)
def _psd_solve(S: FloatArray, B: FloatArray) -> tuple[FloatArray, bool]:  # pragma: no cover
    """S^-1 B by Cholesky with a tiny diagonal; (garbage, False) if S is not PD."""
    m = S.shape[0]
    scale = 1.0
    for i in range(m):
        scale = max(scale, abs(S[i, i]))
    jitter = PSD_JITTER * scale
    L = np.zeros((m, m))
    for i in range(m):
        for j in range(i + 1):
            acc = S[i, j]
            for c in range(j):
                acc -= L[i, c] * L[j, c]
            if i == j:
                acc += jitter
                if not acc > 0.0:  # also catches NaN
                    return B.copy(), False
                L[i, i] = math.sqrt(acc)
            else:
                L[i, j] = acc / L[j, j]
    # Forward then back substitution: S^-1 B = L^-T L^-1 B.
    Z = np.empty_like(B)
    for col in range(B.shape[1]):
        for i in range(m):
            acc = B[i, col]
            for j in range(i):
                acc -= L[i, j] * Z[j, col]
            Z[i, col] = acc / L[i, i]
        for i in range(m - 1, -1, -1):
            acc = Z[i, col]
            for j in range(i + 1, m):
                acc -= L[j, i] * Z[j, col]
            Z[i, col] = acc / L[i, i]
    return Z, True


@njit(cache=True)
def _step(
    x: FloatArray,
    P: FloatArray,
    u_prev: FloatArray,
    dt: float,
    u: FloatArray,
    y: FloatArray,
    Q: FloatArray,
    R: FloatArray,
    iterations: int,
    tolerance: float,
    relinearise: float,
    max_step: float,
    gate: float,
    k: FloatArray,
    axis: IntArray,
    regressor: IntArray,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, float, int, int]:  # pragma: no cover
    n = x.shape[0]
    xp, Pp = _propagate(x, P, u_prev, Q, dt, max_step, k, axis, regressor)
    e_out = np.full(N_OBS, np.nan)
    s_out = np.full(N_OBS, np.nan)

    hx, H = observe(xp, u, k, axis, regressor)
    HP = H @ Pp
    idx = np.empty(N_OBS, dtype=np.int64)
    m = 0
    for i in range(N_OBS):
        if math.isfinite(y[i]):
            s_ii = 0.0
            for j in range(n):
                s_ii += HP[i, j] * H[i, j]
            s_ii += R[i, i]
            e_i = y[i] - hx[i]
            if gate > 0.0 and abs(e_i) > gate * math.sqrt(s_ii):
                continue
            idx[m] = i
            m += 1
    if m == 0:
        return xp, Pp, e_out, s_out, 0.0, 0, 0
    idx = idx[:m]
    yu = np.empty(m)
    Ru = np.empty((m, m))
    for a in range(m):
        yu[a] = y[idx[a]]
        for b in range(m):
            Ru[a, b] = R[idx[a], idx[b]]
    Hu = np.ascontiguousarray(H[idx])
    hu = hx[idx]
    # Innovation statistics at the prior (NIS).
    S = Hu @ Pp @ Hu.T + Ru
    e = yu - hu
    Se, ok = _psd_solve(S, e.reshape(m, 1))
    if not ok:
        return xp, Pp, e_out, s_out, math.nan, -1, 0
    nis = 0.0
    for a in range(m):
        nis += e[a] * Se[a, 0]
        e_out[idx[a]] = e[a]
        s_out[idx[a]] = math.sqrt(S[a, a])

    sigma = np.sqrt(np.diag(Pp))
    x_i = xp.copy()
    K = np.zeros((n, m))
    K1 = K  # the first (EKF) iteration's gain, Jacobian and H P, for the gate
    Hu1 = Hu
    HuP1 = np.empty((m, n))
    done = 0
    for it in range(iterations):
        if it > 0:
            hx_i, H_i = observe(x_i, u, k, axis, regressor)
            Hu = np.ascontiguousarray(H_i[idx])
            hu = hx_i[idx]
        HuP = Hu @ Pp
        S_i = HuP @ Hu.T + Ru
        Kt, ok = _psd_solve(S_i, HuP)
        if not ok:
            return xp, Pp, e_out, s_out, math.nan, -1, 0
        K = np.ascontiguousarray(Kt.T)
        r = yu - hu - Hu @ (xp - x_i)
        x_next = xp + K @ r
        if it == 1 and relinearise > 0.0:
            # Keep the EKF update unless re-linearising moved some component by more
            # than `relinearise` of its (EKF) posterior sigma (see hybrid.iekf_update).
            moved = 0.0
            for j in range(n):
                var = Pp[j, j]
                for a in range(m):
                    var -= K1[j, a] * HuP1[a, j]
                moved = max(moved, abs(x_next[j] - x_i[j]) / math.sqrt(max(var, 1e-300)))
            if moved < relinearise:
                K = K1
                Hu = Hu1
                break
        done = it + 1
        biggest = 0.0
        for j in range(n):
            biggest = max(biggest, abs(x_next[j] - x_i[j]) / sigma[j])
        x_i = x_next
        if it == 0:
            K1 = K
            Hu1 = Hu
            HuP1 = HuP
        if tolerance > 0.0 and biggest < tolerance:
            break
    I_KH = np.eye(n) - K @ Hu
    P_post = I_KH @ Pp @ np.ascontiguousarray(I_KH.T) + K @ Ru @ np.ascontiguousarray(K.T)
    return x_i, 0.5 * (P_post + P_post.T), e_out, s_out, nis, m, done


def step(
    x: FloatArray,
    P: FloatArray,
    u_prev: FloatArray,
    dt: float,
    u: FloatArray,
    y: FloatArray,
    Q: FloatArray,
    R: FloatArray,
    iterations: int,
    tolerance: float,
    relinearise: float,
    max_step: float,
    gate: float,
    model: Model,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, float, int, int]:
    """Predict over dt [s] with inputs u_prev held, then update with y (NaN = missing).

    Returns x+, P+, innovation [7] and its sigma [7] (NaN for unused channels), NIS,
    channels used, iterations run. Same contract as hybrid.propagate + hybrid.iekf_update,
    except that it never raises: if an innovation covariance is not positive definite the
    update is skipped and channels used is -1 (the caller counts and reports it).
    """
    out: tuple[FloatArray, FloatArray, FloatArray, FloatArray, float, int, int] = _step(
        x,
        P,
        u_prev,
        float(dt),
        u,
        y,
        Q,
        R,
        int(iterations),
        float(tolerance),
        float(relinearise),
        float(max_step),
        float(gate),
        model.k,
        model.axis,
        model.regressor,
    )
    return out


@njit(cache=True)
def _dynamics(
    x: FloatArray, u: FloatArray, k: FloatArray, axis: IntArray, regressor: IntArray
) -> tuple[FloatArray, FloatArray]:  # pragma: no cover
    return dynamics(x, u, k, axis, regressor)


@njit(cache=True)
def _observe(
    x: FloatArray, u: FloatArray, k: FloatArray, axis: IntArray, regressor: IntArray
) -> tuple[FloatArray, FloatArray]:  # pragma: no cover
    return observe(x, u, k, axis, regressor)


def model_f(model: Model, x: FloatArray, u: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Compiled model.f: dynamics and Jacobian (same equations, for the simulator)."""
    out: tuple[FloatArray, FloatArray] = _dynamics(x, u, model.k, model.axis, model.regressor)
    return out


def model_h(model: Model, x: FloatArray, u: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Compiled model.h: observations and Jacobian."""
    out: tuple[FloatArray, FloatArray] = _observe(x, u, model.k, model.axis, model.regressor)
    return out


@njit(cache=True)
def gust_match(
    e: FloatArray, s: FloatArray, G: FloatArray
) -> tuple[float, float]:  # pragma: no cover
    """Weighted covariance-matching sums of one step (see FilterRunner.adapt_turbulence):
    num = sum w (min(e^2, 25 S) - S), den = sum w G, w = G / (2 S^2), over the channels
    whose innovation e and its sigma s are present."""
    num = 0.0
    den = 0.0
    for c in range(e.shape[0]):
        S = s[c] * s[c]
        if not (math.isfinite(e[c]) and S > 0.0):  # also catches NaN sigma
            continue
        w = G[c] / (2.0 * S * S)
        num += w * (min(e[c] * e[c], 25.0 * S) - S)
        den += w * G[c]
    return num, den
