"""Equation-error warm start: linear least squares of the coefficients on measured data.

The observation equations are linear in the coefficients once the states are measured
(docs/model.md, eq. 13-14):

    Cm = (qdot - Fe*arm/Iy) / (qbar*S*cbar/Iy)
    C_X = (a_x - Fe*cos(sigma_T)/m) / (qbar*S/m),  C_Z = (a_z + Fe*sin(sigma_T)/m) / (qbar*S/m)
    CL = C_X*sin(alpha) - C_Z*cos(alpha),  CD = -C_X*cos(alpha) - C_Z*sin(alpha)

and each of CD, CL, Cm is a sum of coefficients times regressors. Solving that gives a
linearisation point for the filters with no initial guess at all. It serves only as a
starting point: the filters re-run the data from the start with its sigma widened tenfold
(never wider than the configured prior). Where qdot is not measured it is differentiated
from q.

Noise in the alpha regressor biases the alpha coefficients towards zero (errors in
variables), so alpha, a state smooth between samples, is smoothed first: a zero-phase
quadratic Savitzky-Golay filter over 0.2 s passes the 2 Hz short period
(docs/decisions/0001). The alpha-rate regressor adhat, where the structure has one, is the
same filter's derivative.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from scipy.signal import savgol_coeffs

from gcs_estimator.arrays import FloatArray
from gcs_estimator.model import equations as eq
from gcs_estimator.model.aircraft import Model


class WarmStart(NamedTuple):
    """Least-squares coefficients, their formal sigma, and the samples used per axis."""

    beta: FloatArray
    sigma: FloatArray
    samples: tuple[int, int, int]


def _qdot_from_q(t: FloatArray, q: FloatArray) -> FloatArray:
    """Central-difference pitch acceleration [rad/s^2] from pitch rate samples."""
    out = np.full_like(q, np.nan)
    if len(q) >= 3:
        out[1:-1] = (q[2:] - q[:-2]) / (t[2:] - t[:-2])
    return out


SMOOTH_S = 0.2
"""Span of the Savitzky-Golay smoother of the alpha regressor [s]."""
BRIDGE_S = 0.3
"""A channel's samples are carried linearly to frames at most this far [s] from one of
them: a channel sent at 2.5 Hz among 10 Hz frames still reaches every frame, a gap of a
lost second does not."""


def _bridge(t: FloatArray, x: FloatArray, reach_s: float) -> FloatArray:
    """x linearly interpolated over its NaNs, NaN where the nearest real sample is more
    than reach_s away (and where x has fewer than two samples)."""
    finite = np.isfinite(x)
    if finite.sum() < 2:
        return x.copy()
    known = t[finite]
    filled = np.interp(t, known, x[finite])
    after = np.clip(np.searchsorted(known, t), 0, len(known) - 1)
    before = np.clip(after - 1, 0, len(known) - 1)
    nearest = np.minimum(np.abs(known[after] - t), np.abs(t - known[before]))
    out: FloatArray = np.where(nearest > reach_s, np.nan, filled)
    return out


def _smooth(t: FloatArray, x: FloatArray, span_s: float, deriv: int = 0) -> FloatArray:
    """Zero-phase quadratic Savitzky-Golay smoothing over span_s (deriv=1: the smoothed
    rate). Short gaps (a channel sent at a lower rate than the frames, a lost packet) are
    bridged linearly first; the ends, and samples farther than half a span from a real
    one, come back NaN. With fewer than 5 samples in the span the data come back as they
    are (the rate: NaN)."""
    finite = np.isfinite(x)
    unsmoothed = x if deriv == 0 else np.full_like(x, np.nan)
    if len(t) < 2 or finite.sum() < 2:
        return unsmoothed
    dt = float(np.median(np.diff(t)))
    n = int(span_s / dt) if dt > 0 else 0
    n = n if n % 2 == 1 else n - 1
    if n < 5 or n > len(x):
        return unsmoothed
    bridged = _bridge(t, x, 0.5 * span_s)
    filled = np.interp(t, t[finite], x[finite])
    out = np.full_like(x, np.nan)
    kernel = savgol_coeffs(n, 2, deriv=deriv, delta=dt)
    out[n // 2 : len(x) - n // 2] = np.convolve(filled, kernel, mode="valid")
    out[~np.isfinite(bridged)] = np.nan
    return out


def alpha_from_climb(y: FloatArray, inputs: FloatArray) -> FloatArray:
    """Angle of attack [rad] per frame from airspeed, pitch angle and climb rate
    (equations.alpha_from_climb, the bank from the inputs where they carry it); NaN where
    a channel is missing."""
    phi = inputs[:, 3] if inputs.shape[1] > 3 else np.zeros(len(y))
    if y.shape[1] <= 7:
        return np.full(len(y), np.nan)
    return np.array(
        [
            eq.alpha_from_climb(float(v), float(th), float(h), float(p))
            for v, th, h, p in zip(y[:, 0], y[:, 2], y[:, 7], phi, strict=True)
        ]
    )


def equation_error(
    model: Model,
    t_s: FloatArray,
    inputs: FloatArray,
    measurements: FloatArray,
    prior_mean: FloatArray,
    prior_sigma: FloatArray,
) -> WarmStart:
    """Regularised least squares of the coefficients on the given frames.

    The prior N(prior_mean, prior_sigma^2) keeps coefficients that the data do not yet
    excite at their prior values instead of letting the solve go singular.
    """
    k = model.k
    # Channels sent slower than the frames (or a packet lost) reach the frames between
    # their samples; a frame that needs a channel farther than BRIDGE_S from one is left out.
    y = np.column_stack([_bridge(t_s, col, BRIDGE_S) for col in np.asarray(measurements).T])
    V = y[:, 0]
    q = y[:, 3]
    qdot = y[:, 4].copy()
    if not np.isfinite(qdot).any():
        qdot = _qdot_from_q(t_s, q)
    # Back to the CG from where the sensors sit (model.equations: sensor placement).
    alpha = y[:, 1] + q * k[eq.VANE_X] / V
    if not np.isfinite(alpha).any():  # no vane: alpha = theta - gamma (decision 0049)
        alpha = alpha_from_climb(y, inputs)
    ax = y[:, 5] - qdot * k[eq.ACCEL_Z] + q * q * k[eq.ACCEL_X]
    az = y[:, 6] + qdot * k[eq.ACCEL_X] + q * q * k[eq.ACCEL_Z]
    de = inputs[:, 0]
    rho = inputs[:, 2] if inputs.shape[1] > 2 else np.full(len(V), k[eq.RHO])
    Fe = np.array(
        [
            eq.thrust(float(v), float(p), float(r), k)[0]
            for v, p, r in zip(V, inputs[:, 1], rho, strict=True)
        ]
    )
    m = k[eq.MASS]
    qbar = 0.5 * rho * V**2
    force = qbar * k[eq.AREA] / m
    alpha_s = _smooth(t_s, alpha, SMOOTH_S)
    alpha_rate = _smooth(t_s, alpha, SMOOTH_S, deriv=1) if eq.has_alpha_rate(model.arrays) else 0.0
    alpha = np.where(np.isfinite(alpha_s), alpha_s, alpha)  # also in the axis rotation
    Cm = (qdot - Fe * k[eq.ARM] / k[eq.IYY]) / (qbar * k[eq.AREA] * k[eq.CHORD] / k[eq.IYY])
    CX = (ax - Fe * math.cos(k[eq.SIGMA_T]) / m) / force
    CZ = (az + Fe * math.sin(k[eq.SIGMA_T]) / m) / force
    CL = CX * np.sin(alpha) - CZ * np.cos(alpha)
    CD = -CX * np.cos(alpha) - CZ * np.sin(alpha)
    kc = k[eq.CHORD] / (2 * k[eq.V0])
    regressors = np.column_stack(
        [np.ones_like(V), alpha_s, q * kc, de, V / k[eq.V0], alpha_rate * kc * np.ones_like(V)]
    )

    beta = np.array(prior_mean, float)
    sigma = np.array(prior_sigma, float)
    counts = [0, 0, 0]
    for a, target in enumerate((CD, CL, Cm)):
        idx = np.flatnonzero(model.arrays.axis == a)
        if len(idx) == 0:
            continue
        X = regressors[:, model.arrays.regressor[idx]]
        ok = np.isfinite(target) & np.all(np.isfinite(X), axis=1)
        if ok.sum() < len(idx) + 2:
            continue
        X, z = X[ok], target[ok]
        counts[a] = int(ok.sum())
        b0 = prior_mean[idx]
        info0 = np.diag(1.0 / prior_sigma[idx] ** 2)
        # Residual variance first from the unregularised fit, then the weighted solve.
        b_ls, *_ = np.linalg.lstsq(X, z, rcond=None)
        resid = z - X @ b_ls
        s2 = max(float(resid @ resid) / max(len(z) - len(idx), 1), 1e-12)
        A = X.T @ X / s2 + info0
        b = np.linalg.solve(A, X.T @ z / s2 + info0 @ b0)
        beta[idx] = b
        sigma[idx] = np.sqrt(np.diag(np.linalg.inv(A)))
    return WarmStart(beta, sigma, (counts[0], counts[1], counts[2]))
