"""Output-error maximum likelihood over a whole record: `gcs-estimator refine`.

The filters give an estimate and a covariance online. Once the flight is over, the
record can be fitted as a whole: the initial state, the coefficients and the sensor
biases that make the model, flown through the record's inputs from its first frame,
reproduce the observations best. Output error: with the noise covariance R unknown, each
Gauss-Newton iteration first sets R to the residuals' covariance (the relaxation method;
Jategaonkar 2015, ch. 4). Filter error: a Kalman filter on the flight states runs inside
the fit, and the process noise densities are estimated with R by maximising the
likelihood between Gauss-Newton passes. Both run through one kernel (`innovations`; with
no process noise its innovations are the output errors), which integrates the model as
the filters predict (Runge-Kutta steps of at most max_step_s, the configured input hold,
air density per sample, sensor placement); the sensitivities are forward differences.

Uncertainty, two ways:
- the Cramer-Rao bound, M^-1 with M = sum S^T R^-1 S: right when the residuals are
  white, which they are only when the model holds everything the aircraft does;
- the Morelli-Klein correction (J. Aircraft 34(5), 1997), which uses the residuals'
  own autocorrelation: M^-1 (sum_i sum_j S_i^T R^-1 Rvv(i - j) R^-1 S_j) M^-1. Coloured
  residuals (turbulence, what the structure misses) carry less information than white
  ones, and this bound says how much less. It is the sigma to trust on real data.

Output error assumes calm air: in turbulence the filters' estimates are the better ones,
and the residual colour shows it (the corrected sigma grows).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit
from scipy.optimize import minimize

from gcs_estimator.arrays import BoolArray, FloatArray, IntArray
from gcs_estimator.config import REFINE_METHODS
from gcs_estimator.estimator import EstimatorResult, FilterKind
from gcs_estimator.metrics import correlation_of, identifiability
from gcs_estimator.model import compiled  # noqa: F401  (registers the equations with numba)
from gcs_estimator.model import equations as eq
from gcs_estimator.model.aircraft import Model, build_model
from gcs_estimator.model.channels import N_FLIGHT, N_OBS


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


@njit(cache=True)
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


@dataclass(frozen=True)
class Refined:
    """The maximum-likelihood fit of one record."""

    method: str
    """"output error" (no process noise) or "filter error" (process noise estimated);
    ", noise held" added when the noise levels were held at the configured ones."""
    names: tuple[str, ...]
    """Coefficient names."""
    coefficients: FloatArray
    crb_sigma: FloatArray
    """Cramer-Rao sigma of the coefficients (white residuals assumed)."""
    sigma: FloatArray
    """Morelli-Klein sigma: the Cramer-Rao bound corrected for the residuals' colour."""
    correlation: FloatArray
    """Correlation of the coefficients [p x p] (from the corrected covariance)."""
    identifiability: tuple[str, ...]
    bias_names: tuple[str, ...]
    biases: FloatArray
    bias_sigma: FloatArray
    """Morelli-Klein sigma of the biases."""
    state0: FloatArray
    """Fitted initial flight state [V, alpha, theta, q]."""
    noise_sigma: FloatArray
    """Measurement noise sigma per observation channel [7] (NaN: not observed)."""
    process_noise: FloatArray
    """Process noise spectral density of V, alpha, theta, q (0 for output error)."""
    residual_colour: FloatArray
    """Per channel: the information its residuals' autocorrelation leaves, relative to
    white residuals of the same variance, as seen through the parameters' sensitivities
    (trace of S^T Rvv S over trace of S^T rho(0) S): 1 for white residuals, larger when
    they are correlated in time (each sample then tells less)."""
    frames: int
    iterations: int
    converged: bool
    message: str


class RefineProgress(NamedTuple):
    """Where a fit stands, after each Gauss-Newton iteration."""

    round: int
    """Noise-estimation round (filter error: up to `rounds`; output error: 1)."""
    rounds: int
    iterations: int
    """Gauss-Newton iterations so far, over all rounds."""
    cost: float
    """Negative log-likelihood (without its constant) the iteration started from."""
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
"""Smallest process noise density the fit considers (below it: output error)."""


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

    def run(
        self, x0: FloatArray, q: FloatArray, r: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray, bool]:
        self.runs += 1
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
        J = np.empty((e0.size, len(free)))
        for col, j in enumerate(free):
            step = 1e-6 * max(abs(x0[j]), 1e-3)
            xp = x0.copy()
            xp[j] += step
            e, _, _, ok = self.run(xp, q, r)
            if not ok:
                xp[j] = x0[j] - step
                e, _, _, _ = self.run(xp, q, r)
                step = -step
            J[:, col] = (e - e0).ravel() / step
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
            _, r = _fit_noise(prob, x, q, r, relax, False)
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


def _reporter(
    progress: Callable[[RefineProgress], None], prob: _Problem, k: int, rounds: int, before: int
) -> Callable[[int, float, float], None]:
    """_gauss_newton's report of round k, its iterations counted after `before`."""

    def report(it: int, cost: float, step: float) -> None:
        progress(RefineProgress(k, rounds, before + it, cost, step, prob.runs))

    return report


def _fit_noise(
    prob: _Problem,
    x: FloatArray,
    q: FloatArray,
    r: FloatArray,
    observed: BoolArray,
    estimate_q: bool,
) -> tuple[FloatArray, FloatArray]:
    """The noise levels that maximise the likelihood at fixed parameters. Output error:
    each channel's variance is the mean squared output error (closed form). Filter
    error: the process noise densities and the measurement variances together, on their
    logarithms."""
    ro = np.flatnonzero(observed)
    if not estimate_q:
        _, _, raw, _ = prob.run(x, q, r)
        n_c = np.maximum(prob.mask.sum(axis=0), 1.0)
        r = r.copy()
        r[ro] = np.maximum(np.sum(raw * raw, axis=0)[ro] / n_c[ro], 1e-300)
        return q, r
    nq = len(q)

    def unpack(z: FloatArray) -> tuple[FloatArray, FloatArray]:
        rr = r.copy()
        rr[ro] = np.exp(z[nq:])
        return np.exp(z[:nq]), rr

    def f(z: FloatArray) -> float:
        return prob.cost(x, *unpack(z))

    z0 = np.concatenate([np.log(np.maximum(q, Q_FLOOR)), np.log(r[ro])])
    lo = np.concatenate([np.full(nq, math.log(Q_FLOOR)), np.log(r[ro]) - 20.0])
    hi = np.concatenate([np.full(nq, math.log(1e3)), np.log(r[ro]) + 20.0])
    sol = minimize(f, np.clip(z0, lo, hi), method="L-BFGS-B", bounds=list(zip(lo, hi, strict=True)))
    return unpack(sol.x)


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
    rounds: int = 8,
    iterations: int = 50,
    progress: Callable[[RefineProgress], None] | None = None,
    hold_noise: bool = False,
) -> Refined:
    """Maximum likelihood over the record (t_s [N], inputs [N x 2 or 3], observations
    [N x 7], NaN where missing), from the augmented state `start` (flight states at
    t_s[0], coefficients, biases): the parameters by Gauss-Newton on the whitened
    innovations, the noise levels (measurement sigmas, and the process noise of V, alpha,
    theta, q unless estimate_process_noise is False: output error) by maximising the
    likelihood between them, until neither moves. With hold_noise the noise levels stay
    at noise_sigma and process_noise (the sensors' and the air's known levels) and only
    the parameters are fitted. `progress` hears after each Gauss-Newton iteration where
    the fit stands."""
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
    x = np.asarray(start, float).copy()
    nd = model.arrays.n_dynamic
    q = (
        np.maximum(np.asarray(process_noise, float)[:nd], Q_FLOOR)
        if estimate_process_noise
        else np.zeros(nd)
    )
    r = np.where(observed, np.asarray(noise_sigma, float) ** 2, 1.0)
    e0, _, _, ok = prob.run(x, q, r)
    if not ok:
        raise RefineError("the model, flown from the start values, leaves finite numbers")
    # Parameters the observations do not see (a bias of a channel without data) stay.
    probe = prob.jacobian(x, np.arange(x.shape[0]), q, r, e0)
    free = np.flatnonzero(np.linalg.norm(probe, axis=0) > 0.0)
    total = 0
    converged = False
    cost = prob.cost(x, q, r)
    n_rounds = rounds if estimate_process_noise and not hold_noise else 1
    for k in range(1, n_rounds + 1):
        report = None if progress is None else _reporter(progress, prob, k, n_rounds, total)
        if estimate_process_noise and not hold_noise:
            q, r = _fit_noise(prob, x, q, r, observed, True)
        # Output error with the noise free: R in closed form inside each iteration.
        relax = None if hold_noise or estimate_process_noise else observed
        x, r, its, converged = _gauss_newton(prob, x, free, q, r, iterations, relax, report)
        total += its
        new = prob.cost(x, q, r)
        done = abs(cost - new) < 1e-6 * max(abs(new), 1.0)
        cost = new
        if done:
            break
    e, _, _, _ = prob.run(x, q, r)
    J = prob.jacobian(x, free, q, r, e).reshape(e.shape[0], N_OBS, len(free))
    M = np.einsum("ncp,ncq->pq", J, J)
    Minv = np.linalg.inv(M)
    middle = np.zeros_like(M)
    colour = np.full(N_OBS, np.nan)
    for c in range(N_OBS):
        if not observed[c]:
            continue
        n_c = max(float(mask[:, c].sum()), 1.0)
        rho = _autocorrelation(e[:, c]) * (t.shape[0] / n_c)
        part = J[:, c, :].T @ _toeplitz_apply(rho, J[:, c, :])
        middle += part
        white = float(rho[0]) * float(np.sum(J[:, c, :] ** 2))
        colour[c] = float(np.trace(part)) / white if white > 0.0 else math.nan
    cov_mk = Minv @ middle @ Minv
    cov_mk = 0.5 * (cov_mk + cov_mk.T)
    n = x.shape[0]
    crb = np.full(n, np.nan)
    mk = np.full(n, np.nan)
    crb[free] = np.sqrt(np.diag(Minv))
    # The correction never makes the bound smaller than Cramer-Rao's.
    mk[free] = np.maximum(np.sqrt(np.maximum(np.diag(cov_mk), 0.0)), crb[free])
    full = np.zeros((n, n))
    full[np.ix_(free, free)] = cov_mk
    cs = model.coefficients
    corr = correlation_of(full[cs, cs])
    coefficients = x[cs].copy()
    bs = model.biases
    noise = np.where(observed, np.sqrt(r), np.nan)
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
        iterations=total,
        converged=converged,
        message=f"{msg} ({prob.runs} filter runs)",
    )


def refine_run(
    result: EstimatorResult,
    method: str = "output-error",
    kind: FilterKind = "IEKF",
    window_s: tuple[float | None, float | None] = (None, None),
    progress: Callable[[RefineProgress], None] | None = None,
    hold_noise: bool = False,
) -> Refined:
    """Refine a finished run: fit the frames the estimator saw (optionally only those
    within window_s, seconds after the first frame), starting from filter `kind`'s final
    coefficients and biases and the first frame's measured flight states. hold_noise:
    the noise levels stay instead of being estimated: the measurement noise where the
    filters' final pass had it (the config's [filter] measurement_sigma, or the data's
    with measurement_noise = "data"), the process noise at the config's."""
    if method not in REFINE_METHODS:
        raise ValueError(f"refine method {method!r}: allowed {list(REFINE_METHODS)}")
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
    return refine(
        model,
        tr.t[idx],
        tr.u[idx],
        tr.y[idx],
        start,
        np.asarray(result.measurement_sigma or tuning.measurement_sigma, float),
        np.asarray(tuning.process_noise.states, float),
        tuning.max_step_s,
        linear_inputs=config.data.input_hold == "linear",
        estimate_process_noise=method == "filter-error",
        progress=progress,
        hold_noise=hold_noise,
    )


def _bias_on_flight(model: Model, biases: FloatArray) -> FloatArray:
    """The estimated biases on the directly observed flight-state channels [4]."""
    out = np.zeros(N_FLIGHT)
    for ch, b in zip(model.arrays.bias_channel, biases, strict=True):
        if ch < N_FLIGHT:
            out[ch] += b
    return out
