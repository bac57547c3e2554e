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
from typing import Any, NamedTuple

import numpy as np
from numba import njit
from numba.extending import register_jitable

from gcs_estimator.arrays import FloatArray, IntArray
from gcs_estimator.filters import core, small
from gcs_estimator.filters.core import FilterState, GustState, StepInfo, Tuning
from gcs_estimator.filters.hybrid import PSD_JITTER
from gcs_estimator.model import compiled  # noqa: F401  (makes the equations compilable)
from gcs_estimator.model.aircraft import Model
from gcs_estimator.model.channels import N_FLIGHT, N_OBS
from gcs_estimator.model.equations import ModelArrays, observe, rk4_step

for _fn in (
    core.plausible,
    core.pass_average,
    core.gust_applied,
    core.input_path,
    core.process_noise,
    core.gust_match,
    core.adapt_gust,
):
    register_jitable(_fn)


@njit(cache=True)
def _stage(F: FloatArray, K: FloatArray, c: float, d: int) -> FloatArray:  # pragma: no cover
    """F[:d] + c F[:d, :d] @ K: a Runge-Kutta stage of the transition matrix's top rows."""
    return F[:d] + c * small.times(F[:d, :d], K)


@njit(cache=True)
def _add_process_noise(
    P: FloatArray, q: FloatArray, D: FloatArray, D_m: FloatArray, h: float
) -> None:  # pragma: no cover
    """P += Qd, Simpson's rule for the integral of Phi(s) diag(q) Phi(s)^T over a step h:
    h/6 (diag(q) + 4 (I + E_m) diag(q) (I + E_m)^T + (I + E) diag(q) (I + E)^T), the
    transition matrix at mid-step and at the end being I + E_m and I + E (first d rows
    D_m and D, zero below)."""
    d, n = D.shape
    for j in range(n):
        P[j, j] += h * q[j]
    w = h / 6.0
    for i in range(d):
        for j in range(n):
            g = w * (4.0 * D_m[i, j] + D[i, j]) * q[j]
            P[i, j] += g
            P[j, i] += g
        for b in range(d):
            acc = 0.0
            for c in range(n):
                acc += (4.0 * D_m[i, c] * D_m[b, c] + D[i, c] * D[b, c]) * q[c]
            P[i, b] += w * acc


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
    P = P.copy()
    if dt <= 0.0:
        return x.copy(), P
    steps = max(1, int(math.ceil(dt / max_step - 1e-9)))
    h = dt / steps
    d = m.n_dynamic
    n = x.shape[0]
    du = u1 - u0
    D = np.empty((d, n))
    D_m = np.empty((d, n))
    for j in range(steps):
        ua = u0 + du * (j / steps)
        ub = u0 + du * ((j + 1) / steps)
        x, F1, F2, F3, F4 = rk4_step(x, ua, ub, h, m)
        # Stages of Phi' = F Phi, Phi(0) = I: K = F (I + c E) = F + c F[:, :d] D.
        K2 = _stage(F2, F1, 0.5 * h, d)
        K3 = _stage(F3, K2, 0.5 * h, d)
        K4 = _stage(F4, K3, h, d)
        for i in range(d):
            for c in range(n):
                D[i, c] = h / 6.0 * (F1[i, c] + 2.0 * K2[i, c] + 2.0 * K3[i, c] + K4[i, c])
                D_m[i, c] = 0.25 * h * (F1[i, c] + K2[i, c])
        small.congruence(P, D)
        _add_process_noise(P, q, D, D_m, h)
    small.symmetrise(P)
    return x, P


@njit(cache=True)
def _select(
    y: FloatArray, hx: FloatArray, H: FloatArray, HP: FloatArray, R: FloatArray, gate: float
) -> IntArray:  # pragma: no cover
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
def _rows(A: FloatArray, idx: IntArray) -> FloatArray:  # pragma: no cover
    out = np.empty((idx.shape[0], A.shape[1]))
    for a in range(idx.shape[0]):
        for j in range(A.shape[1]):
            out[a, j] = A[idx[a], j]
    return out


class _Linearised(NamedTuple):
    """The observation linearised at an iterate, on the channels used."""

    h: FloatArray
    H: FloatArray
    HP: FloatArray
    """H @ P-."""
    L: FloatArray
    """Cholesky factor of S = H P- H^T + R."""


@njit(cache=True)
def _linearise(
    x: FloatArray, u: FloatArray, idx: IntArray, Pp: FloatArray, Ru: FloatArray, m: ModelArrays
) -> tuple[_Linearised, bool]:  # pragma: no cover
    hx, H_all = observe(x, u, m)
    H = _rows(H_all, idx)
    start, cols = small.nonzero_columns(H)
    HP = small.sparse_times(H, start, cols, Pp)
    L, ok = small.cholesky(small.gram(HP, H, Ru), PSD_JITTER)
    return _Linearised(hx[idx], H, HP, L), ok


@njit(cache=True)
def _moved(
    x_next: FloatArray,
    x_i: FloatArray,
    Pp: FloatArray,
    Kt1: FloatArray,
    HP1: FloatArray,
    judged: tuple[int, int],
) -> float:  # pragma: no cover
    """Largest move of a component in x[judged[0]:judged[1]] (the coefficients), in
    EKF-posterior sigmas: the relinearisation gate (hybrid.iekf_update)."""
    moved = 0.0
    for j in range(judged[0], judged[1]):
        var = Pp[j, j]
        for a in range(Kt1.shape[0]):
            var -= Kt1[a, j] * HP1[a, j]
        moved = max(moved, abs(x_next[j] - x_i[j]) / math.sqrt(max(var, 1e-300)))
    return moved


@njit(cache=True)
def _gain_step(
    xp: FloatArray, x_i: FloatArray, yu: FloatArray, lin: _Linearised
) -> tuple[FloatArray, FloatArray]:  # pragma: no cover
    """The gain's transpose Kt = S^-1 H P- and the next iterate
    x- + K (y - h(x_i) - H (x- - x_i))."""
    Kt = small.cholesky_solve(lin.L, lin.HP)
    k, n = Kt.shape
    r = yu - lin.h
    for j in range(n):
        d = xp[j] - x_i[j]
        if d == 0.0:  # all of them at the first iterate, the prior itself
            continue
        for a in range(k):
            r[a] -= lin.H[a, j] * d
    x_next = xp.copy()
    for a in range(k):
        for j in range(n):
            x_next[j] += Kt[a, j] * r[a]
    return Kt, x_next


@njit(cache=True)
def _iterate(
    xp: FloatArray,
    Pp: FloatArray,
    u: FloatArray,
    yu: FloatArray,
    Ru: FloatArray,
    idx: IntArray,
    first: _Linearised,
    tun: Tuning,
    m: ModelArrays,
) -> tuple[FloatArray, FloatArray, _Linearised, int, bool]:  # pragma: no cover
    """The (iterated) update with the prior held fixed (hybrid.iekf_update), from the
    linearisation at the prior: returns the last iterate, the gain's transpose and the
    linearisation it came from, the iterations kept, and False if some S_i was not
    positive definite."""
    n = xp.shape[0]
    check = tun.tolerance > 0.0
    # The prior sigmas, for the early stop only (a state held exactly cannot move).
    sigma = np.sqrt(np.maximum(np.diag(Pp), 1e-300)) if check else Pp[0]
    x_i = xp.copy()
    lin = first
    Kt = Kt1 = np.zeros((idx.shape[0], n))
    done = 0
    for it in range(tun.iterations):
        if it > 0:
            lin, ok = _linearise(x_i, u, idx, Pp, Ru, m)
            if not ok:
                return xp, Kt, lin, 0, False
        Kt, x_next = _gain_step(xp, x_i, yu, lin)
        if (
            it == 1
            and tun.relinearise > 0.0
            and _moved(
                x_next, x_i, Pp, Kt1, first.HP, (m.coef_start, m.coef_start + m.axis.shape[0])
            )
            < tun.relinearise
        ):
            # Keep the EKF update: re-linearising moved nothing by `relinearise` sigmas.
            return x_i, Kt1, first, done, True
        done = it + 1
        biggest = 0.0
        if check:
            for j in range(n):
                biggest = max(biggest, abs(x_next[j] - x_i[j]) / sigma[j])
        x_i = x_next
        if it == 0:
            Kt1 = Kt
        if check and biggest < tun.tolerance:
            break
    return x_i, Kt, lin, done, True


@njit(cache=True)
def _update(
    xp: FloatArray, Pp: FloatArray, u: FloatArray, y: FloatArray, tun: Tuning, m: ModelArrays
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, float, int, int]:  # pragma: no cover
    """Measurement update: (x+, P+, innovations [7], their sigmas [7], NIS, channels used,
    iterations); channels used -1 with NaN innovations and NIS when it failed."""
    e_out = np.full(N_OBS, np.nan)
    s_out = np.full(N_OBS, np.nan)
    hx, H = observe(xp, u, m)
    start, cols = small.nonzero_columns(H)
    HP = small.sparse_times(H, start, cols, Pp)
    idx = _select(y, hx, H, HP, tun.R, tun.gate)
    k = idx.shape[0]
    if k == 0:
        return xp, Pp, e_out, s_out, 0.0, 0, 0
    Hu = _rows(H, idx)
    HuP = _rows(HP, idx)
    Ru = np.empty((k, k))
    yu = np.empty(k)
    for a in range(k):
        yu[a] = y[idx[a]]
        for b in range(k):
            Ru[a, b] = tun.R[idx[a], idx[b]]
    S = small.gram(HuP, Hu, Ru)
    L, ok = small.cholesky(S, PSD_JITTER)
    if not ok:
        return xp, Pp, e_out, s_out, math.nan, -1, 0
    first = _Linearised(hx[idx], Hu, HuP, L)
    # Innovation statistics at the prior (NIS).
    e = yu - first.h
    Se = small.cholesky_solve(L, e.reshape(k, 1))
    x, Kt, lin, done, ok = _iterate(xp, Pp, u, yu, Ru, idx, first, tun, m)
    if not ok:
        return xp, Pp, e_out, s_out, math.nan, -1, 0
    nis = 0.0
    for a in range(k):
        nis += e[a] * Se[a, 0]
        e_out[idx[a]] = e[a]
        s_out[idx[a]] = math.sqrt(S[a, a])
    P = small.joseph(Pp, Kt, lin.H, lin.HP, Ru)
    return x, P, e_out, s_out, nis, k, done


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
    healthy = (
        variances.min() > 0.0
        and math.isfinite(x.sum() + P.sum())
        and core.plausible(x, tun.state_max)
    )
    gust = core.adapt_gust(st.gust, tun, m, t, dt, x, u, e, s, applied)
    new = FilterState(x, P, t, u.copy(), st.t_start, gust)
    info = StepInfo(
        np.sqrt(np.maximum(variances, 0.0)),
        nis,
        max(used, 0),
        done,
        e,
        s,
        math.sqrt(applied),
        math.sqrt(core.pass_average(gust.var, gust.pass_num, gust.pass_den)),
        used < 0,
        False,
        False,
    )
    return new, info, healthy


# The packed form of a filter's Tuning and its aircraft's ModelArrays: two flat arrays, so
# that a step's call hands the compiled code 17 values instead of 39 (the dispatch cost
# grows with every argument). Scalar fields first, then the arrays back to back.
_TF_SCALARS = (
    "q_decay_s",
    "tolerance",
    "relinearise",
    "max_step_s",
    "gate",
    "adapt_time_s",
    "detection2",
    "gust_var0",
    "still_band",
    "settle_s",
    "max_wait_s",
    "pass_detection2",
)
_TI_HEAD = 9
"""iterations, adaptive, linear_inputs, coef_start, n_dynamic, bias_start, then the
lengths of axis (= regressor) and bias_channel, then n."""


def pack(tuning: Tuning, m: ModelArrays) -> tuple[FloatArray, IntArray]:
    """Tuning and ModelArrays as (floats, ints) for _kernel (unpacked by _unpack)."""
    n = tuning.q_final.shape[0]
    floats = [np.array([getattr(tuning, f) for f in _TF_SCALARS], float)]
    floats += [np.ravel(tuning.R)]
    floats += [tuning.q_final, tuning.q_initial, tuning.gust_unit]
    floats += [tuning.prior_x, tuning.prior_sigma, tuning.state_max, m.k]
    head = [
        tuning.iterations,
        int(tuning.adaptive),
        int(tuning.linear_inputs),
        m.coef_start,
        m.n_dynamic,
        m.bias_start,
        m.axis.shape[0],
        m.bias_channel.shape[0],
        n,
    ]
    ints = np.concatenate([np.array(head), m.axis, m.regressor, m.bias_channel])
    return np.concatenate(floats).astype(np.float64), ints.astype(np.int64)


@njit(cache=True)
def _unpack(tf: FloatArray, ti: IntArray) -> tuple[Tuning, ModelArrays]:  # pragma: no cover
    """pack's inverse, as views of the two arrays."""
    n = ti[8]
    n_coef = ti[6]
    o = len(_TF_SCALARS)
    R = tf[o : o + N_OBS * N_OBS].reshape((N_OBS, N_OBS))
    o += N_OBS * N_OBS
    tun = Tuning(
        R,
        tf[o : o + n],
        tf[o + n : o + 2 * n],
        tf[0],
        tf[o + 2 * n : o + 3 * n],
        ti[0],
        tf[1],
        tf[2],
        tf[3],
        tf[4],
        ti[1] != 0,
        tf[5],
        tf[6],
        tf[o + 3 * n : o + 4 * n],
        tf[o + 4 * n : o + 5 * n],
        tf[7],
        ti[2] != 0,
        tf[o + 5 * n : o + 5 * n + N_FLIGHT],
        tf[8],
        tf[9],
        tf[10],
        tf[11],
    )
    h = _TI_HEAD
    model = ModelArrays(
        tf[o + 5 * n + N_FLIGHT :],
        ti[h : h + n_coef],
        ti[h + n_coef : h + 2 * n_coef],
        ti[3],
        ti[4],
        ti[h + 2 * n_coef :],
        ti[5],
    )
    return tun, model


@njit(cache=True)
def _state_of(
    x: FloatArray,
    P: FloatArray,
    u_prev: FloatArray,
    sens: FloatArray,
    t_prev: float,
    t_start: float,
    gust: tuple[float, ...],
    g_age: int,
) -> FilterState:  # pragma: no cover
    """A FilterState from its fields as _state_args hands them over: gust holds
    GustState's float fields in order (all but sens and sens_age), in one tuple so that
    both kernels take them as one argument (at about the dispatch cost of scalars)."""
    var, info, gain, num, den, ref, moved, still = gust
    g = GustState(var, info, gain, num, den, sens, g_age, ref, moved, still)
    return FilterState(x, P, t_prev, u_prev, t_start, g)


@njit(cache=True)
def _handed_back(st: FilterState, info: StepInfo) -> tuple:  # type: ignore[type-arg]  # pragma: no cover
    """A step's belief and outputs as _belief_and_info takes them: the arrays in one
    vector (each array returned costs more to hand back than the arithmetic of a row of
    the update), then the scalars, the gust estimate's as _state_of takes them."""
    g = st.gust
    vec = np.concatenate((st.x, info.sigma, info.innovation, info.innovation_sigma, st.u, g.sens))
    return (
        st.t,
        st.P,
        vec,
        info.nis,
        info.n_used,
        info.iterations,
        info.gust_sigma,
        info.gust_pass_sigma,
        info.failed,
        (g.var, g.info, g.gain, g.pass_num, g.pass_den, g.input_ref, g.t_moved, g.t_still),
        g.sens_age,
    )


@njit(cache=True, nogil=True)
def _kernel(
    x: FloatArray,
    P: FloatArray,
    u_prev: FloatArray,
    sens: FloatArray,
    t_prev: float,
    t_start: float,
    gust: tuple[float, ...],
    g_age: int,
    t: float,
    u: FloatArray,
    y: FloatArray,
    tf: FloatArray,
    ti: IntArray,
) -> tuple:  # type: ignore[type-arg]  # pragma: no cover
    """_step over the fields of FilterState, and Tuning and ModelArrays packed:
    (healthy, the new belief and the step's outputs)."""
    tun, m = _unpack(tf, ti)
    st = _state_of(x, P, u_prev, sens, t_prev, t_start, gust, g_age)
    new, info, healthy = _step(st, t, u, y, tun, m)
    return (healthy, *_handed_back(new, info))


@njit(cache=True, nogil=True)
def _kernel_block(
    x: FloatArray,
    P: FloatArray,
    u_prev: FloatArray,
    sens: FloatArray,
    t_prev: float,
    t_start: float,
    gust: tuple[float, ...],
    g_age: int,
    ts: FloatArray,
    us: FloatArray,
    ys: FloatArray,
    tf: FloatArray,
    ti: IntArray,
) -> tuple:  # type: ignore[type-arg]  # pragma: no cover
    """_step over the frames ts, us, ys in order, as long as each leaves a healthy belief:
    (the frames done, the failed updates among them, the belief after the last of them
    and the outputs of that step; of the first frame, unhealthy, when none was done)."""
    tun, m = _unpack(tf, ti)
    st = _state_of(x, P, u_prev, sens, t_prev, t_start, gust, g_age)
    new, info, healthy = _step(st, ts[0], us[0], ys[0], tun, m)
    last = info
    done = 0
    failed = 0
    while healthy:
        st = new
        last = info
        failed += 1 if info.failed else 0
        done += 1
        if done == ts.shape[0]:
            break
        new, info, healthy = _step(st, ts[done], us[done], ys[done], tun, m)
    return (done, failed, *_handed_back(st, last))


PACKED_KEPT = 4096
"""Filters whose packed settings are kept: two per vehicle, far more than a station
estimates at once (link.max_vehicles)."""

_PACKED: dict[tuple[int, int], tuple[Tuning, Model, FloatArray, IntArray]] = {}
"""pack's results by the identity of (tuning, model); the entry holds both, so an id is
never reused while its entry lives."""


def _packed(tuning: Tuning, model: Model) -> tuple[FloatArray, IntArray]:
    key = (id(tuning), id(model))
    hit = _PACKED.get(key)
    if hit is not None and hit[0] is tuning and hit[1] is model:
        return hit[2], hit[3]
    if len(_PACKED) >= PACKED_KEPT:
        _PACKED.clear()
    tf, ti = pack(tuning, model.arrays)
    _PACKED[key] = (tuning, model, tf, ti)
    return tf, ti


def _state_args(state: FilterState) -> tuple[Any, ...]:
    """A FilterState's fields, flat, as the kernels take them (_state_of)."""
    x, P, t, u, t_start, g = state
    var, info, gain, num, den, sens, age, ref, moved, still = g
    return (x, P, u, sens, t, t_start, (var, info, gain, num, den, ref, moved, still), age)


_tuple = tuple.__new__
"""A NamedTuple built from all its fields in order, without its keyword-handling __new__:
three of them per step, at about half the cost each."""


def _belief_and_info(
    start: FilterState, n_inputs: int, out: tuple[Any, ...], at: int
) -> tuple[FilterState, StepInfo]:
    """The belief and outputs a kernel handed back (_handed_back's values, from out[at]),
    views of its vector."""
    t, P, vec, nis, used, iterations, gust_sigma, pass_sigma, failed, gust, age = out[at:]
    var, info, gain, num, den, ref, moved, still = gust
    n = start.x.shape[0]
    o = 2 * n + 2 * N_OBS
    p = o + n_inputs
    sens = vec[p:]
    g = _tuple(GustState, (var, info, gain, num, den, sens, age, ref, moved, still))
    new = _tuple(FilterState, (vec[:n], P, t, vec[o:p], start.t_start, g))
    e, s = vec[2 * n : 2 * n + N_OBS], vec[2 * n + N_OBS : o]
    fields = (
        vec[n : 2 * n],
        nis,
        used,
        iterations,
        e,
        s,
        gust_sigma,
        pass_sigma,
        failed,
        False,
        False,
    )
    return new, _tuple(StepInfo, fields)


def kernel_step(
    state: FilterState, t: float, u: FloatArray, y: FloatArray, tuning: Tuning, model: Model
) -> tuple[FilterState, StepInfo, bool]:
    """Predict, update with y, adapt the gust level (core contract)."""
    tf, ti = _packed(tuning, model)
    kernel: Any = _kernel  # flat values in the fields' order (mypy cannot see through *)
    out = kernel(*_state_args(state), float(t), u, y, tf, ti)
    new, info = _belief_and_info(state, u.shape[0], out, 1)
    return new, info, out[0]


def kernel_block(
    state: FilterState,
    ts: FloatArray,
    us: FloatArray,
    ys: FloatArray,
    tuning: Tuning,
    model: Model,
) -> tuple[int, int, FilterState, StepInfo | None]:
    """kernel_step over frames (rows of ts, us, ys) in one compiled call, up to the first
    that leaves an unhealthy belief (for the step contract to handle, kernel_step again):
    (frames done, failed updates among them, the belief after them, the last one's
    outputs; None when none was done). Each step is kernel_step's, bit for bit."""
    tf, ti = _packed(tuning, model)
    kernel: Any = _kernel_block
    out = kernel(
        *_state_args(state),
        np.ascontiguousarray(ts, dtype=np.float64),
        np.ascontiguousarray(us, dtype=np.float64),
        np.ascontiguousarray(ys, dtype=np.float64),
        tf,
        ti,
    )
    done, failed = out[0], out[1]
    if done == 0:
        return 0, 0, state, None
    new, info = _belief_and_info(state, us.shape[1], out, 2)
    return done, failed, new, info
