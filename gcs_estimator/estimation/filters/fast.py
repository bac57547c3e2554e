"""The compiled backend of the step contract (filters.core): the same maths as the numpy
reference (filters.reference), fused into one numba call per step.

One call builds the process noise, predicts (classical Runge-Kutta of x and of the
transition matrix of P), runs the (iterated) measurement update, checks the belief's
health and adapts the gust level. It exploits the structure of the augmented model: the
rows of F below the dynamic blocks are zero, so the transition matrix differs from I in
n_dynamic rows and Phi P Phi^T costs n_dynamic x n x n instead of n^3.

The estimator's runner keeps each filter's belief in one buffer that the call updates
where it lies (lane_kernel, Lane); kernel_step is the same call on a FilterState.
The step's own functions are inlined into the kernels (inline="always"): between
functions compiled apart, every array handed over is reference counted, and inlined
numba prunes most of those counts (a step about 8 % faster, bit for bit; a cold compile
some seconds longer). filters.small's loops stay compiled apart: inlined, those with
fastmath flags would lose them.
tests/filters/test_fast.py checks it against the reference, kernel and flight alike.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple, get_type_hints

import numpy as np
from numba import njit
from numba.extending import register_jitable

from gcs_estimator.arrays import FloatArray, IntArray
from gcs_estimator.estimation.filters import core, small
from gcs_estimator.estimation.filters.core import FilterState, GustState, StepInfo, Tuning
from gcs_estimator.estimation.filters.hybrid import PSD_JITTER
from gcs_estimator.model import compiled  # noqa: F401  (makes the equations compilable)
from gcs_estimator.model.aircraft import Model
from gcs_estimator.model.channels import N_OBS
from gcs_estimator.model.equations import ModelArrays, dynamics_rows, observe

for _fn in (
    core.plausible,
    core.pass_average,
    core.gust_applied,
    core.input_path,
    core.process_noise,
    core.measurement_noise,
    core.gust_match,
    core.adapt_gust,
):
    register_jitable(_fn)


@njit(cache=True, inline="always")
def _stage(F: FloatArray, K: FloatArray, c: float, d: int) -> FloatArray:  # pragma: no cover
    """F[:d] + c F[:d, :d] @ K: a Runge-Kutta stage of the transition matrix's top rows
    (the product's sums skip the zeros of F, in small.times's order)."""
    n = F.shape[1]
    out = np.empty((d, n))
    acc = np.empty(n)
    for i in range(d):
        acc[:] = 0.0
        for b in range(d):
            a = F[i, b]
            if a != 0.0:
                for j in range(n):
                    acc[j] += a * K[b, j]
        for j in range(n):
            out[i, j] = F[i, j] + c * acc[j]
    return out


@njit(cache=True, inline="always")
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


@njit(cache=True, inline="always")
def _rk4(
    x: FloatArray, u0: FloatArray, u1: FloatArray, h: float, m: ModelArrays
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:  # pragma: no cover
    """equations.rk4_step, bit for bit, with its vector sums as loops into one scratch
    vector (compiled, each numpy temporary of the original is an allocation)."""
    n = x.shape[0]
    um = np.empty(u0.shape[0])
    for i in range(u0.shape[0]):
        um[i] = u0[i] + 0.5 * (u1[i] - u0[i])
    f1, F1 = dynamics_rows(x, u0, m)
    xs = np.empty(n)
    for i in range(n):
        xs[i] = x[i] + 0.5 * h * f1[i]
    f2, F2 = dynamics_rows(xs, um, m)
    for i in range(n):
        xs[i] = x[i] + 0.5 * h * f2[i]
    f3, F3 = dynamics_rows(xs, um, m)
    for i in range(n):
        xs[i] = x[i] + h * f3[i]
    f4, F4 = dynamics_rows(xs, u1, m)
    for i in range(n):
        xs[i] = x[i] + h / 6.0 * (f1[i] + 2.0 * f2[i] + 2.0 * f3[i] + f4[i])
    return xs, F1, F2, F3, F4


@njit(cache=True, inline="always")
def _substeps(dt: float, max_step: float) -> tuple[int, float]:  # pragma: no cover
    """The Runge-Kutta steps over dt [s], none longer than max_step [s]: how many, and
    their length [s]."""
    steps = max(1, int(math.ceil(dt / max_step - 1e-9)))
    return steps, dt / steps


@njit(cache=True, inline="always")
def _substep_inputs(
    u0: FloatArray, u1: FloatArray, j: int, steps: int, ua: FloatArray, ub: FloatArray
) -> None:  # pragma: no cover
    """ua, ub <- the inputs at the start and the end of step j of `steps`, the inputs
    going linearly from u0 to u1 over the interval."""
    for i in range(u0.shape[0]):
        du = u1[i] - u0[i]
        ua[i] = u0[i] + du * (j / steps)
        ub[i] = u0[i] + du * ((j + 1) / steps)


@njit(cache=True, inline="always")
def propagate(
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
    of it is d x n. Q = diag(q); the inputs go linearly from u0 to u1 over dt. The
    filters' one prediction: their step's, and refine's filter error's."""
    P = P.copy()
    if dt <= 0.0:
        return x.copy(), P
    steps, h = _substeps(dt, max_step)
    d = m.n_dynamic
    n = x.shape[0]
    D = np.empty((d, n))
    D_m = np.empty((d, n))
    ua = np.empty(u0.shape[0])
    ub = np.empty(u0.shape[0])
    for j in range(steps):
        _substep_inputs(u0, u1, j, steps, ua, ub)
        x, F1, F2, F3, F4 = _rk4(x, ua, ub, h, m)
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


@njit(cache=True, inline="always")
def fly(
    x: FloatArray, u0: FloatArray, u1: FloatArray, dt: float, max_step: float, m: ModelArrays
) -> FloatArray:  # pragma: no cover
    """x over dt as propagate moves it, without a covariance: the model flown through the
    inputs (linear from u0 to u1) in the same Runge-Kutta steps (refine's flights)."""
    if dt <= 0.0:
        return x.copy()
    steps, h = _substeps(dt, max_step)
    ua = np.empty(u0.shape[0])
    ub = np.empty(u0.shape[0])
    for j in range(steps):
        _substep_inputs(u0, u1, j, steps, ua, ub)
        x = _rk4(x, ua, ub, h, m)[0]
    return x


@njit(cache=True, inline="always")
def _select(y: FloatArray) -> IntArray:  # pragma: no cover
    """The channels present in y."""
    idx = np.empty(N_OBS, dtype=np.int64)
    m = 0
    for i in range(N_OBS):
        if not math.isfinite(y[i]):
            continue
        idx[m] = i
        m += 1
    return idx[:m]


@njit(cache=True, inline="always")
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


@njit(cache=True, inline="always")
def _linearise(
    x: FloatArray, u: FloatArray, idx: IntArray, Pp: FloatArray, Ru: FloatArray, m: ModelArrays
) -> tuple[_Linearised, bool]:  # pragma: no cover
    hx, H_all = observe(x, u, m)
    if idx.shape[0] == N_OBS:  # every channel: nothing to pick
        H, h = H_all, hx
    else:
        H, h = _rows(H_all, idx), hx[idx]
    start, cols = small.nonzero_columns(H)
    HP = small.sparse_times(H, start, cols, Pp)
    L, ok = small.cholesky(small.gram(HP, H, Ru), PSD_JITTER)
    return _Linearised(h, H, HP, L), ok


@njit(cache=True, inline="always")
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


@njit(cache=True, inline="always")
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


@njit(cache=True, inline="always")
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
    x_i = xp.copy()
    lin = first
    Kt = Kt1 = np.empty((0, n))  # set at the first iteration (iterations >= 1)
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
        x_i = x_next
        if it == 0:
            Kt1 = Kt
    return x_i, Kt, lin, done, True


@njit(cache=True, inline="always")
def _update(
    xp: FloatArray,
    Pp: FloatArray,
    u: FloatArray,
    y: FloatArray,
    R: FloatArray,
    tun: Tuning,
    m: ModelArrays,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, float, int, int]:  # pragma: no cover
    """Measurement update: (x+, P+, innovations [7], their sigmas [7], NIS, channels used,
    iterations); channels used -1 with NaN innovations and NIS when it failed."""
    e_out = np.full(N_OBS, np.nan)
    s_out = np.full(N_OBS, np.nan)
    hx, H = observe(xp, u, m)
    start, cols = small.nonzero_columns(H)
    HP = small.sparse_times(H, start, cols, Pp)
    idx = _select(y)
    k = idx.shape[0]
    if k == 0:
        return xp, Pp, e_out, s_out, 0.0, 0, 0
    if k == N_OBS:  # every channel, the common frame: nothing to pick
        Hu, HuP, hu = H, HP, hx
    else:
        Hu, HuP, hu = _rows(H, idx), _rows(HP, idx), hx[idx]
    Ru = np.empty((k, k))
    yu = np.empty(k)
    for a in range(k):
        yu[a] = y[idx[a]]
        for b in range(k):
            Ru[a, b] = R[idx[a], idx[b]]
    S = small.gram(HuP, Hu, Ru)
    L, ok = small.cholesky(S, PSD_JITTER)
    if not ok:
        return xp, Pp, e_out, s_out, math.nan, -1, 0
    first = _Linearised(hu, Hu, HuP, L)
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


@njit(cache=True, inline="always")
def _step(
    st: FilterState, t: float, u: FloatArray, y: FloatArray, tun: Tuning, m: ModelArrays
) -> tuple[FilterState, StepInfo, bool]:  # pragma: no cover
    u_prev, u_end = core.input_path(st.u, u, tun.linear_inputs)
    dt = t - st.t
    q, applied = core.process_noise(st, tun)
    xp, Pp = propagate(st.x, st.P, u_prev, u_end, q, dt, tun.max_step_s, m)
    R = core.measurement_noise(tun, applied, dt)
    x, P, e, s, nis, used, done = _update(xp, Pp, u, y, R, tun, m)
    sigma = np.empty(P.shape[0])
    smallest = math.inf
    for i in range(P.shape[0]):
        smallest = min(smallest, P[i, i])
        sigma[i] = math.sqrt(max(P[i, i], 0.0))
    healthy = (
        smallest > 0.0 and math.isfinite(x.sum() + P.sum()) and core.plausible(x, tun.state_max)
    )
    gust = core.adapt_gust(st.gust, tun, m, t, dt, x, u, e, s, applied)
    new = FilterState(x, P, t, u.copy(), gust)
    info = StepInfo(
        sigma,
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


# ---- Tuning and ModelArrays as two flat arrays ---------------------------------------
# A step's call hands the compiled code two arrays instead of the 28 fields of a Tuning
# and its aircraft's ModelArrays (numba's dispatch cost grows with every argument). The
# layout follows from the two NamedTuples' fields and their declared types, in pack
# alone: the int array opens with a directory, two entries (start, stop) per field in
# declaration order, saying where its values lie: in the float array for float scalars
# and arrays, in the int array after the directory for int and bool scalars and int
# arrays. The kernel finds each field through its slot in the directory (TUNING_SLOTS,
# MODEL_SLOTS: the records themselves with slot numbers for values), never an offset.


def _goes_to_floats(hint: Any) -> bool:
    """Whether a field of this declared type is packed into the float array."""
    if hint in (float, FloatArray):
        return True
    if hint in (int, bool, IntArray):
        return False
    raise TypeError(f"pack does not know fields of type {hint}")


_AS_FLOATS = tuple(
    _goes_to_floats(hint)
    for record in (Tuning, ModelArrays)
    for hint in get_type_hints(record).values()
)
"""Per slot (the fields of Tuning, then ModelArrays): whether its values go into the
float array, else into the int array."""
_DIRECTORY = 2 * len(_AS_FLOATS)

TUNING_SLOTS: Any = Tuning._make(range(len(Tuning._fields)))
"""A Tuning whose fields hold their directory slots (typed Any: ints, not the fields'
types)."""
MODEL_SLOTS: Any = ModelArrays._make(range(len(Tuning._fields), len(_AS_FLOATS)))
"""The same for ModelArrays, whose slots follow Tuning's."""


def pack(tuning: Tuning, m: ModelArrays) -> tuple[FloatArray, IntArray]:
    """Tuning and ModelArrays as (floats, ints) for the kernels (unpacked by _unpack),
    every value as it is (the float64 values themselves, whole numbers as int64)."""
    floats: list[float] = []
    ints: list[int] = [0] * _DIRECTORY
    for slot, (value, as_floats) in enumerate(zip((*tuning, *m), _AS_FLOATS, strict=True)):
        values = np.asarray(value, np.float64 if as_floats else np.int64).ravel().tolist()
        into: list[Any] = floats if as_floats else ints
        ints[2 * slot] = len(into)
        into.extend(values)
        ints[2 * slot + 1] = len(into)
    return np.array(floats, np.float64), np.array(ints, np.int64)


@njit(cache=True, inline="always")
def _floats(tf: FloatArray, ti: IntArray, slot: int) -> FloatArray:  # pragma: no cover
    """A float array field (pack's layout), a view of tf."""
    return tf[ti[2 * slot] : ti[2 * slot + 1]]


@njit(cache=True, inline="always")
def _float(tf: FloatArray, ti: IntArray, slot: int) -> float:  # pragma: no cover
    return float(tf[ti[2 * slot]])


@njit(cache=True, inline="always")
def _ints(ti: IntArray, slot: int) -> IntArray:  # pragma: no cover
    """An int array field (pack's layout), a view of ti."""
    return ti[ti[2 * slot] : ti[2 * slot + 1]]


@njit(cache=True, inline="always")
def _int(ti: IntArray, slot: int) -> int:  # pragma: no cover
    return int(ti[ti[2 * slot]])


@njit(cache=True, inline="always")
def _unpack(tf: FloatArray, ti: IntArray) -> tuple[Tuning, ModelArrays]:  # pragma: no cover
    """pack's inverse, its arrays views of the two: each field through its slot."""
    t, a = TUNING_SLOTS, MODEL_SLOTS
    tun = Tuning(
        R=_floats(tf, ti, t.R).reshape((N_OBS, N_OBS)),
        q=_floats(tf, ti, t.q),
        gust_unit=_floats(tf, ti, t.gust_unit),
        iterations=_int(ti, t.iterations),
        relinearise=_float(tf, ti, t.relinearise),
        max_step_s=_float(tf, ti, t.max_step_s),
        adaptive=_int(ti, t.adaptive) != 0,
        detection2=_float(tf, ti, t.detection2),
        prior_sigma=_floats(tf, ti, t.prior_sigma),
        gust_var0=_float(tf, ti, t.gust_var0),
        linear_inputs=_int(ti, t.linear_inputs) != 0,
        state_max=_floats(tf, ti, t.state_max),
        settle_s=_float(tf, ti, t.settle_s),
        r_gust=_floats(tf, ti, t.r_gust),
    )
    model = ModelArrays(
        k=_floats(tf, ti, a.k),
        axis=_ints(ti, a.axis),
        regressor=_ints(ti, a.regressor),
        coef_start=_int(ti, a.coef_start),
        n_dynamic=_int(ti, a.n_dynamic),
        bias_channel=_ints(ti, a.bias_channel),
        bias_start=_int(ti, a.bias_start),
    )
    return tun, model


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


# ---- a belief kept in one buffer, stepped in place (Lane) -----------------------
# The estimator's runner steps each filter once per frame. Handing a belief over as
# FilterState and back costs more than a third of a step (numba's dispatch of its fields,
# boxing the arrays of the new belief and the step's report, and the named tuples built
# around them), so the runner keeps each belief in one float buffer that the kernel
# updates where it lies, and the step's report in one output row that the kernel fills.
# Layout of the buffer: a head of scalars, t and the gust estimate's scalar fields in
# their order (HEAD_SLOTS), then x [n], P [n x n], u, sens [N_OBS].

_HEAD_GUST = tuple(f for f in GustState._fields if f != "sens")
"""The gust estimate's scalar fields, in the head after t."""
_SENS_AT = GustState._fields.index("sens")
_SENS_AGE_AT = GustState._fields.index("sens_age")
BELIEF_HEAD = 1 + len(_HEAD_GUST)
"""Floats of the buffer's head."""
HEAD_SLOTS: Any = GustState._make(
    _HEAD_GUST.index(f) + 1 if f != "sens" else -1 for f in GustState._fields
)
"""A GustState whose scalar fields hold their place in the head (t is at 0; typed Any:
ints, not the fields' types)."""


def belief_buffer(state: FilterState) -> FloatArray:
    """A FilterState as one buffer (a new array; belief_of is its inverse)."""
    g = state.gust
    head = [state.t, *(float(getattr(g, f)) for f in _HEAD_GUST)]
    return np.concatenate((head, state.x, np.ravel(state.P), state.u, g.sens)).astype(np.float64)


def belief_of(buf: FloatArray, n: int) -> FilterState:
    """The FilterState a buffer holds, as arrays of its own (the buffer moves on)."""
    o = BELIEF_HEAD
    x = buf[o : o + n].copy()
    P = buf[o + n : o + n + n * n].reshape(n, n).copy()
    u = buf[o + n + n * n : buf.shape[0] - N_OBS].copy()
    sens = buf[buf.shape[0] - N_OBS :].copy()
    fields = buf[1:BELIEF_HEAD].tolist()  # the head's gust fields, in GustState's order
    fields.insert(_SENS_AT, sens)
    fields[_SENS_AGE_AT] = int(fields[_SENS_AGE_AT])
    return FilterState(x, P, float(buf[0]), u, GustState._make(fields))


def output_width(n: int) -> int:
    """Floats of a step's output row: x [n], sigma [n], NIS, channels used, gust sigma,
    its pass average, innovations [N_OBS], their sigmas [N_OBS] (estimator.History's row),
    then iterations, failed, repaired, diverged."""
    return 2 * n + 4 + 2 * N_OBS + 4


@njit(cache=True, inline="always")
def _belief_views(buf: FloatArray, n: int, nu: int) -> FilterState:  # pragma: no cover
    """The FilterState a buffer holds, its arrays views of the buffer."""
    o = BELIEF_HEAD
    x = buf[o : o + n]
    P = buf[o + n : o + n + n * n].reshape((n, n))
    u = buf[o + n + n * n : o + n + n * n + nu]
    sens = buf[o + n + n * n + nu :]
    h = HEAD_SLOTS
    g = GustState(
        var=buf[h.var],
        info=buf[h.info],
        gain=buf[h.gain],
        pass_num=buf[h.pass_num],
        pass_den=buf[h.pass_den],
        sens=sens,
        sens_age=int(buf[h.sens_age]),
        input_ref=buf[h.input_ref],
        t_moved=buf[h.t_moved],
        t_still=buf[h.t_still],
    )
    return FilterState(x, P, buf[0], u, g)


@njit(cache=True, inline="always")
def _lane_step(
    buf: FloatArray,
    t: float,
    u: FloatArray,
    y: FloatArray,
    tun: Tuning,
    m: ModelArrays,
    out: FloatArray,
) -> int:  # pragma: no cover
    """_step on the belief in buf, written back into it, and the step's report into out
    (output_width's layout): 0 healthy, 1 healthy with a failed update, 2 unhealthy (the
    belief in buf is the step's, for the contract to repair or restart)."""
    n = tun.q.shape[0]
    st = _belief_views(buf, n, u.shape[0])
    new, info, healthy = _step(st, t, u, y, tun, m)
    g, h = new.gust, HEAD_SLOTS
    buf[0] = new.t
    buf[h.var] = g.var
    buf[h.info] = g.info
    buf[h.gain] = g.gain
    buf[h.pass_num] = g.pass_num
    buf[h.pass_den] = g.pass_den
    buf[h.sens_age] = g.sens_age
    buf[h.input_ref] = g.input_ref
    buf[h.t_moved] = g.t_moved
    buf[h.t_still] = g.t_still
    # Element by element: numba's slice assignment costs more than these copies.
    o = BELIEF_HEAD
    for i in range(n):
        buf[o + i] = new.x[i]
        out[i] = new.x[i]
        out[n + i] = info.sigma[i]
    o += n
    for i in range(n):
        for j in range(n):
            buf[o + i * n + j] = new.P[i, j]
    o += n * n
    for i in range(new.u.shape[0]):
        buf[o + i] = new.u[i]
    o += new.u.shape[0]
    for i in range(N_OBS):
        buf[o + i] = g.sens[i]
    o = 2 * n
    out[o] = info.nis
    out[o + 1] = info.n_used
    out[o + 2] = info.gust_sigma
    out[o + 3] = info.gust_pass_sigma
    for i in range(N_OBS):
        out[o + 4 + i] = info.innovation[i]
        out[o + 4 + N_OBS + i] = info.innovation_sigma[i]
    o += 4 + 2 * N_OBS
    out[o] = info.iterations
    out[o + 1] = 1.0 if info.failed else 0.0
    out[o + 2] = 0.0
    out[o + 3] = 0.0
    if not healthy:
        return 2
    return 1 if info.failed else 0


@njit(cache=True, nogil=True)
def lane_kernel(
    buf: FloatArray,
    t: float,
    u: FloatArray,
    y: FloatArray,
    tf: FloatArray,
    ti: IntArray,
    out: FloatArray,
) -> int:  # pragma: no cover
    """_lane_step with the Tuning and ModelArrays packed (pack)."""
    tun, m = _unpack(tf, ti)
    return _lane_step(buf, t, u, y, tun, m, out)


@njit(cache=True, nogil=True)
def lane_block_kernel(
    buf: FloatArray,
    ts: FloatArray,
    us: FloatArray,
    ys: FloatArray,
    tf: FloatArray,
    ti: IntArray,
    out: FloatArray,
) -> tuple[int, int, bool]:  # pragma: no cover
    """_lane_step over the frames in order, up to and including the first that leaves an
    unhealthy belief: (frames stepped, failed updates among the healthy ones, whether
    the last one left the belief healthy); out holds the last one's report."""
    tun, m = _unpack(tf, ti)
    failed = 0
    for i in range(ts.shape[0]):
        status = _lane_step(buf, ts[i], us[i], ys[i], tun, m, out)
        if status == 2:
            return i + 1, failed, False
        failed += status
    return ts.shape[0], failed, True


@njit(cache=True, nogil=True)
def lane_rows_kernel(
    buf: FloatArray,
    ts: FloatArray,
    us: FloatArray,
    ys: FloatArray,
    tf: FloatArray,
    ti: IntArray,
    out: FloatArray,
) -> tuple[int, int, bool]:  # pragma: no cover
    """lane_block_kernel keeping every step's report: out[i] is frame i's row (out has a
    row per frame), up to and including the first step that leaves an unhealthy belief."""
    tun, m = _unpack(tf, ti)
    failed = 0
    for i in range(ts.shape[0]):
        status = _lane_step(buf, ts[i], us[i], ys[i], tun, m, out[i])
        if status == 2:
            return i + 1, failed, False
        failed += status
    return ts.shape[0], failed, True


def kernel_step(
    state: FilterState, t: float, u: FloatArray, y: FloatArray, tuning: Tuning, model: Model
) -> tuple[FilterState, StepInfo, bool]:
    """Predict, update with y, adapt the gust level (core contract): the lane's kernel on
    a buffer of the state's own."""
    tf, ti = _packed(tuning, model)
    buf = belief_buffer(state)
    n = state.x.shape[0]
    row = np.empty(output_width(n))
    status = lane_kernel(buf, float(t), u, y, tf, ti, row)
    return belief_of(buf, n), core.info_of_row(row, n), status != 2
