"""The compiled backend of the step contract (filters.core): the same maths as the numpy
reference (filters.reference), fused into one numba call per step.

One call builds the process noise, predicts (classical Runge-Kutta of x and of the
transition matrix of P), runs the (iterated) measurement update, checks the belief's
health and adapts the gust level. It exploits the structure of the augmented model: the
rows of F below the dynamic blocks are zero, so the transition matrix differs from I in
n_dynamic rows and Phi P Phi^T costs n_dynamic x n x n instead of n^3.
tests/filters/test_fast.py checks it against the reference, kernel and flight alike.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit
from numba.extending import register_jitable

from gcs_estimator.arrays import FloatArray, IntArray
from gcs_estimator.filters import core
from gcs_estimator.filters.core import FilterState, GustState, StepInfo, Tuning
from gcs_estimator.filters.hybrid import PSD_JITTER
from gcs_estimator.model import compiled  # noqa: F401  (makes the equations compilable)
from gcs_estimator.model.aircraft import Model
from gcs_estimator.model.channels import N_OBS
from gcs_estimator.model.equations import ModelArrays, observe, rk4_step

for _fn in (
    core.gust_applied,
    core.input_path,
    core.process_noise,
    core.gust_match,
    core.adapt_gust,
):
    register_jitable(_fn)


@njit(cache=True)
def _congruence(M: FloatArray, D: FloatArray) -> FloatArray:  # pragma: no cover
    """(I + E) M (I + E)^T for symmetric M, where E is zero but for its first d rows,
    D [d x n]: M + E M + M E^T + E M E^T at d x n x n instead of n^3."""
    DM = D @ M
    out = M.copy()
    n = M.shape[0]
    d = D.shape[0]
    for i in range(d):
        for j in range(n):
            out[i, j] += DM[i, j]
            out[j, i] += DM[i, j]
    DMD = DM @ np.ascontiguousarray(D.T)
    for i in range(d):
        for j in range(d):
            out[i, j] += DMD[i, j]
    return out


@njit(cache=True)
def _congruence_diag(q: FloatArray, D: FloatArray) -> FloatArray:  # pragma: no cover
    """_congruence(diag(q), D): D diag(q) is D with its columns scaled, exactly the
    products the matrix product would sum with zeros."""
    DM = np.empty_like(D)
    for i in range(D.shape[0]):
        for j in range(D.shape[1]):
            DM[i, j] = D[i, j] * q[j]
    out = np.diag(q)
    d = D.shape[0]
    for i in range(d):
        for j in range(q.shape[0]):
            out[i, j] += DM[i, j]
            out[j, i] += DM[i, j]
    DMD = DM @ np.ascontiguousarray(D.T)
    for i in range(d):
        for j in range(d):
            out[i, j] += DMD[i, j]
    return out


@njit(cache=True)
def _propagate(
    x: FloatArray,
    P: FloatArray,
    u0: FloatArray,
    u1: FloatArray,
    q: FloatArray,
    dt: float,
    max_step: float,
    m: ModelArrays,
) -> tuple[FloatArray, FloatArray]:  # pragma: no cover
    """hybrid.propagate for the aircraft: rows >= d = n_dynamic of F are zero, so the
    transition matrix differs from I in its first d rows only, and each Runge-Kutta stage
    of it is d x n. Q = diag(q); the inputs go linearly from u0 to u1 over dt."""
    if dt <= 0.0:
        return x.copy(), P.copy()
    steps = max(1, int(math.ceil(dt / max_step - 1e-9)))
    h = dt / steps
    d = m.n_dynamic
    still = np.zeros(2)
    du = u1 - u0
    for j in range(steps):
        ua = u0 + du * (j / steps)
        ub = u0 + du * ((j + 1) / steps)
        x, F1, F2, F3, F4 = rk4_step(x, ua, ub, still, h, m)
        # Stages of Phi' = F Phi, Phi(0) = I: K = F (I + c E) = F + c F[:, :d] D.
        K1 = np.ascontiguousarray(F1[:d])
        K2 = F2[:d] + 0.5 * h * (np.ascontiguousarray(F2[:d, :d]) @ K1)
        K3 = F3[:d] + 0.5 * h * (np.ascontiguousarray(F3[:d, :d]) @ K2)
        K4 = F4[:d] + h * (np.ascontiguousarray(F4[:d, :d]) @ K3)
        D = h / 6.0 * (K1 + 2.0 * K2 + 2.0 * K3 + K4)
        D_m = 0.25 * h * (K1 + K2)
        Qd = h / 6.0 * (np.diag(q) + 4.0 * _congruence_diag(q, D_m) + _congruence_diag(q, D))
        P = _congruence(P, D) + Qd
    return x, 0.5 * (P + P.T)


@njit(cache=True)
def _cholesky(S: FloatArray) -> tuple[FloatArray, bool]:  # pragma: no cover
    """Lower Cholesky factor of S plus a tiny diagonal (hybrid.PSD_JITTER); False if S is
    not positive definite (or not finite)."""
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
            if i != j:
                L[i, j] = acc / L[j, j]
                continue
            acc += jitter
            if not acc > 0.0:  # also catches NaN
                return L, False
            L[i, i] = math.sqrt(acc)
    return L, True


@njit(cache=True)
def _psd_solve(S: FloatArray, B: FloatArray) -> tuple[FloatArray, bool]:  # pragma: no cover
    """S^-1 B by Cholesky with a tiny diagonal; (garbage, False) if S is not PD."""
    L, ok = _cholesky(S)
    if not ok:
        return B.copy(), False
    m = S.shape[0]
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
def _select(
    y: FloatArray, hx: FloatArray, H: FloatArray, HP: FloatArray, R: FloatArray, gate: float
) -> np.ndarray:  # pragma: no cover
    """Channels present in y and, with gate > 0, within gate sigma of the prediction."""
    idx = np.empty(N_OBS, dtype=np.int64)
    m = 0
    for i in range(N_OBS):
        if not math.isfinite(y[i]):
            continue
        s_ii = 0.0
        for j in range(H.shape[1]):
            s_ii += HP[i, j] * H[i, j]
        s_ii += R[i, i]
        if gate > 0.0 and abs(y[i] - hx[i]) > gate * math.sqrt(s_ii):
            continue
        idx[m] = i
        m += 1
    return idx[:m]


@njit(cache=True)
def _moved(
    x_next: FloatArray, x_i: FloatArray, Pp: FloatArray, K1: FloatArray, HuP1: FloatArray
) -> float:  # pragma: no cover
    """Largest move of a component in EKF-posterior sigmas (the relinearisation gate)."""
    moved = 0.0
    for j in range(x_next.shape[0]):
        var = Pp[j, j]
        for a in range(K1.shape[1]):
            var -= K1[j, a] * HuP1[a, j]
        moved = max(moved, abs(x_next[j] - x_i[j]) / math.sqrt(max(var, 1e-300)))
    return moved


@njit(cache=True)
def _largest_step(
    x_next: FloatArray, x_i: FloatArray, sigma: FloatArray
) -> float:  # pragma: no cover
    biggest = 0.0
    for j in range(x_next.shape[0]):
        biggest = max(biggest, abs(x_next[j] - x_i[j]) / sigma[j])
    return biggest


@njit(cache=True)
def _iterate(
    xp: FloatArray,
    Pp: FloatArray,
    u: FloatArray,
    yu: FloatArray,
    Ru: FloatArray,
    idx: np.ndarray,
    hu: FloatArray,
    Hu: FloatArray,
    HuP: FloatArray,
    S: FloatArray,
    tun: Tuning,
    m: ModelArrays,
) -> tuple[FloatArray, FloatArray, FloatArray, int, bool]:  # pragma: no cover
    """The (iterated) update with the prior held fixed (hybrid.iekf_update), from h, H,
    H P and S at the prior on the channels used: returns the last iterate, gain and
    Jacobian, the iterations kept, and False if some S_i was not positive definite."""
    sigma = np.sqrt(np.diag(Pp))
    x_i = xp.copy()
    K = K1 = np.zeros((xp.shape[0], idx.shape[0]))
    Hu1 = Hu
    HuP1 = np.empty((idx.shape[0], xp.shape[0]))
    done = 0
    for it in range(tun.iterations):
        if it > 0:
            hx_i, H_i = observe(x_i, u, m)
            Hu = np.ascontiguousarray(H_i[idx])
            hu = hx_i[idx]
            HuP = Hu @ Pp
            S = HuP @ Hu.T + Ru
        Kt, ok = _psd_solve(S, HuP)
        if not ok:
            return xp, K, Hu, 0, False
        K = np.ascontiguousarray(Kt.T)
        x_next = xp + K @ (yu - hu - Hu @ (xp - x_i))
        if (
            it == 1
            and tun.relinearise > 0.0
            and _moved(x_next, x_i, Pp, K1, HuP1) < tun.relinearise
        ):
            # Keep the EKF update: re-linearising moved nothing by `relinearise` sigmas.
            return x_i, K1, Hu1, done, True
        done = it + 1
        biggest = _largest_step(x_next, x_i, sigma)
        x_i = x_next
        if it == 0:
            K1, Hu1, HuP1 = K, Hu, HuP
        if tun.tolerance > 0.0 and biggest < tun.tolerance:
            break
    return x_i, K, Hu, done, True


@njit(cache=True)
def _update(
    xp: FloatArray, Pp: FloatArray, u: FloatArray, y: FloatArray, tun: Tuning, m: ModelArrays
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, float, int, int]:  # pragma: no cover
    """Measurement update: (x+, P+, innovations [7], their sigmas [7], NIS, channels used,
    iterations); channels used -1 with NaN innovations and NIS when it failed."""
    e_out = np.full(N_OBS, np.nan)
    s_out = np.full(N_OBS, np.nan)
    hx, H = observe(xp, u, m)
    HP = H @ Pp
    idx = _select(y, hx, H, HP, tun.R, tun.gate)
    k = idx.shape[0]
    if k == 0:
        return xp, Pp, e_out, s_out, 0.0, 0, 0
    Hu = np.ascontiguousarray(H[idx])
    HuP = np.ascontiguousarray(HP[idx])
    hu = hx[idx]
    yu = y[idx]
    Ru = np.empty((k, k))
    for a in range(k):
        for b in range(k):
            Ru[a, b] = tun.R[idx[a], idx[b]]
    # Innovation statistics at the prior (NIS).
    S = HuP @ Hu.T + Ru
    e = yu - hu
    Se, ok = _psd_solve(S, e.reshape(k, 1))
    if not ok:
        return xp, Pp, e_out, s_out, math.nan, -1, 0
    x, K, Hu, done, ok = _iterate(xp, Pp, u, yu, Ru, idx, hu, Hu, HuP, S, tun, m)
    if not ok:
        return xp, Pp, e_out, s_out, math.nan, -1, 0
    nis = 0.0
    for a in range(k):
        nis += e[a] * Se[a, 0]
        e_out[idx[a]] = e[a]
        s_out[idx[a]] = math.sqrt(S[a, a])
    I_KH = np.eye(xp.shape[0]) - K @ Hu
    P = I_KH @ Pp @ np.ascontiguousarray(I_KH.T) + K @ Ru @ np.ascontiguousarray(K.T)
    return x, 0.5 * (P + P.T), e_out, s_out, nis, k, done


@njit(cache=True)
def _step(
    st: FilterState, t: float, u: FloatArray, y: FloatArray, tun: Tuning, m: ModelArrays
) -> tuple[FilterState, StepInfo, bool]:  # pragma: no cover
    u_prev, u_end = core.input_path(st.u, u, tun.linear_inputs)
    dt = t - st.t
    q, applied = core.process_noise(st, tun)
    xp, Pp = _propagate(st.x, st.P, u_prev, u_end, q, dt, tun.max_step_s, m)
    x, P, e, s, nis, used, done = _update(xp, Pp, u, y, tun, m)
    variances = np.diag(P).copy()
    healthy = variances.min() > 0.0 and math.isfinite(x.sum() + P.sum())
    gust = core.adapt_gust(st.gust, tun, m, dt, x, u, e, s, applied)
    new = FilterState(x, P, t, u.copy(), st.t_start, gust)
    info = StepInfo(
        np.sqrt(np.maximum(variances, 0.0)),
        nis,
        max(used, 0),
        done,
        e,
        s,
        math.sqrt(applied),
        used < 0,
        False,
        False,
    )
    return new, info, healthy


@njit(cache=True, nogil=True)
def _kernel(
    x: FloatArray,
    P: FloatArray,
    t_prev: float,
    u_prev: FloatArray,
    t_start: float,
    g_var: float,
    g_info: float,
    g_gain: float,
    g_num: float,
    g_den: float,
    g_sens: FloatArray,
    g_age: int,
    t: float,
    u: FloatArray,
    y: FloatArray,
    R: FloatArray,
    q_final: FloatArray,
    q_initial: FloatArray,
    q_decay_s: float,
    gust_unit: FloatArray,
    iterations: int,
    tolerance: float,
    relinearise: float,
    max_step_s: float,
    gate: float,
    adaptive: bool,
    adapt_time_s: float,
    detection2: float,
    prior_x: FloatArray,
    prior_sigma: FloatArray,
    gust_var0: float,
    linear_inputs: bool,
    k: FloatArray,
    axis: IntArray,
    regressor: IntArray,
    coef_start: int,
    n_dynamic: int,
    bias_channel: IntArray,
    bias_start: int,
) -> tuple:  # type: ignore[type-arg]  # pragma: no cover
    """_step over the fields of FilterState, Tuning and ModelArrays, in their order."""
    st = FilterState(
        x, P, t_prev, u_prev, t_start, GustState(g_var, g_info, g_gain, g_num, g_den, g_sens, g_age)
    )
    tun = Tuning(
        R,
        q_final,
        q_initial,
        q_decay_s,
        gust_unit,
        iterations,
        tolerance,
        relinearise,
        max_step_s,
        gate,
        adaptive,
        adapt_time_s,
        detection2,
        prior_x,
        prior_sigma,
        gust_var0,
        linear_inputs,
    )
    new, info, healthy = _step(
        st,
        t,
        u,
        y,
        tun,
        ModelArrays(k, axis, regressor, coef_start, n_dynamic, bias_channel, bias_start),
    )
    g = new.gust
    return (
        new.x,
        new.P,
        new.u,
        info.sigma,
        info.nis,
        info.n_used,
        info.iterations,
        info.innovation,
        info.innovation_sigma,
        info.gust_sigma,
        info.failed,
        healthy,
        g.var,
        g.info,
        g.gain,
        g.pass_num,
        g.pass_den,
        g.sens,
        g.sens_age,
    )


def kernel_step(
    state: FilterState, t: float, u: FloatArray, y: FloatArray, tuning: Tuning, model: Model
) -> tuple[FilterState, StepInfo, bool]:
    """Predict, update with y, adapt the gust level (core contract)."""
    t = float(t)
    kernel: Any = _kernel  # flat values in the fields' order (mypy cannot see through *)
    (x, P, u_held, sigma, nis, used, done, e, s, gust_sigma, failed, healthy, *gust) = kernel(
        state.x,
        state.P,
        state.t,
        state.u,
        state.t_start,
        *state.gust,
        t,
        u,
        y,
        *tuning,
        *model.arrays,
    )
    new = FilterState(x, P, t, u_held, state.t_start, GustState(*gust))
    return new, StepInfo(sigma, nis, used, done, e, s, gust_sigma, failed), healthy
