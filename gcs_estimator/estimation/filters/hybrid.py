"""Hybrid (continuous-discrete) extended and iterated extended Kalman filters.

Reference path: plain numpy, textbook symbols, any model given as callables. The
compiled path (filters.fast) fuses the same steps for the aircraft model and is tested
against this one.

Source: Meng, Liu and Veres (2010), sections III-IV; docs/model.md.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from gcs_estimator.arrays import BoolArray, FloatArray

Dynamics = Callable[[FloatArray, float], tuple[FloatArray, FloatArray]]
"""(x, s) -> (f(x), F = df/dx) at the fraction s in [0, 1] of the prediction interval
(the inputs, bound by the caller, may change over it)."""
Observation = Callable[[FloatArray], tuple[FloatArray, FloatArray]]
"""x -> (h(x), H = dh/dx), inputs already bound."""

PSD_JITTER = 1e-12
"""Relative diagonal added before a Cholesky factorisation, so that a covariance that is
positive definite only up to rounding still factors."""


class Belief(NamedTuple):
    """Gaussian belief N(x, P)."""

    x: FloatArray
    P: FloatArray


class UpdateInfo(NamedTuple):
    """Diagnostics of one measurement update.

    innovation e = y - h(x-) over the channels used, S = H P- H^T + R, NIS = e^T S^-1 e,
    used: boolean mask of the channels used, iterations: measurement-update iterations run.
    """

    innovation: FloatArray
    S: FloatArray
    nis: float
    used: BoolArray
    iterations: int


def symmetrize(P: FloatArray) -> FloatArray:
    return 0.5 * (P + P.T)


def psd_solve(S: FloatArray, B: FloatArray) -> FloatArray:
    """S^-1 B for symmetric positive definite S, by Cholesky with a tiny diagonal."""
    jitter = PSD_JITTER * float(np.max(np.abs(np.diag(S)), initial=1.0))
    return np.asarray(cho_solve(cho_factor(S + jitter * np.eye(S.shape[0])), B))


def propagate(f: Dynamics, belief: Belief, Q: FloatArray, dt: float, max_step: float) -> Belief:
    """Predict over dt: x' = f(x, t) by classical Runge-Kutta, P by its transition matrix.

    Steps no longer than max_step [s]; uneven measurement intervals are fine. Q is the
    continuous-time process noise spectral density (L = I). Over each step

        P+ = Phi P Phi^T + Qd,   Qd = h/6 (Q + 4 Phi_m Q Phi_m^T + Phi Q Phi^T),

    with Phi the Runge-Kutta solution of Phi' = F Phi from the same stages as x (fourth
    order, like x), Phi_m its second-order value at mid-step and Qd Simpson's rule for
    the integral of Phi(s) Q Phi(s)^T. A congruence keeps P positive semi-definite
    whatever the step. Runge-Kutta on P' = F P + P F^T + Q itself does not, on an F as far
    from normal as an aircraft's (docs/decisions/0002).
    """
    if dt <= 0.0:
        return belief
    steps = max(1, int(np.ceil(dt / max_step - 1e-9)))
    h = dt / steps
    x, P = belief.x, belief.P
    eye = np.eye(x.size)
    for j in range(steps):
        s0, sm, s1 = j / steps, (j + 0.5) / steps, (j + 1) / steps
        f1, F1 = f(x, s0)
        f2, F2 = f(x + 0.5 * h * f1, sm)
        f3, F3 = f(x + 0.5 * h * f2, sm)
        f4, F4 = f(x + h * f3, s1)
        x = x + h / 6.0 * (f1 + 2.0 * f2 + 2.0 * f3 + f4)
        K1 = F1
        K2 = F2 @ (eye + 0.5 * h * K1)
        K3 = F3 @ (eye + 0.5 * h * K2)
        K4 = F4 @ (eye + h * K3)
        Phi = eye + h / 6.0 * (K1 + 2.0 * K2 + 2.0 * K3 + K4)
        Phi_m = eye + 0.25 * h * (K1 + K2)
        Qd = h / 6.0 * (Q + 4.0 * Phi_m @ Q @ Phi_m.T + Phi @ Q @ Phi.T)
        P = Phi @ P @ Phi.T + Qd
    return Belief(x, symmetrize(P))


def available(y: FloatArray) -> BoolArray:
    """Channels present in a measurement vector (missing channels are NaN)."""
    return np.asarray(np.isfinite(y))


def ekf_update(
    h: Observation, belief: Belief, y: FloatArray, R: FloatArray
) -> tuple[Belief, UpdateInfo]:
    """EKF measurement update on the channels of y that are not NaN (Joseph form).

    K = P H^T (H P H^T + R)^-1,  x+ = x + K (y - h(x)),
    P+ = (I - K H) P (I - K H)^T + K R K^T
    """
    return iekf_update(h, belief, y, R, iterations=1)


def iekf_update(
    h: Observation,
    belief: Belief,
    y: FloatArray,
    R: FloatArray,
    iterations: int = 7,
    tolerance: float = 0.0,
    relinearise: float = 0.0,
    judged: slice | None = None,
) -> tuple[Belief, UpdateInfo]:
    """Iterated EKF measurement update (paper eq. 5-7), prior covariance held fixed.

        x_{i+1} = x- + K_i [y - h(x_i) - H_i (x- - x_i)],
        K_i = P- H_i^T (H_i P- H_i^T + R)^-1,  x_0 = x-.

    Runs `iterations` updates (1 is the EKF); stops early when no state moves by more
    than `tolerance` prior standard deviations. The covariance is formed once, in Joseph
    form, from the last K and H. Each measurement is used once: the prior is never
    replaced by an iterate (unlike implementations that feed the posterior back).

    With `relinearise` > 0 the iterations are kept only when the first re-linearisation
    moves some component by at least `relinearise` standard deviations of the EKF
    posterior; otherwise the EKF update is returned. Re-linearising at an iterate that the
    current measurement has already moved makes the Jacobian depend on that measurement's
    noise. When the states carry process noise (turbulence), the iterate then converges
    to the joint mode of (states, coefficients) at each step, which favours larger
    coefficient magnitudes (each step's alpha then needs to move less). That bias is a
    small fraction of a sigma per step, but it adds up over thousands of steps. Far from
    the solution (a zero start), the iterations move the estimate by many sigma and are
    kept. `judged` (default: all) names the components whose move decides: the filters
    pass the coefficients, because in turbulence the states move by more than a sigma
    with every gust while the linearisation point is right, and iterating on those moves
    is what biases the coefficients (docs/decisions/0024).
    """
    x_prior, P = belief
    used = available(y)
    n = x_prior.size
    hx, H = h(x_prior)
    e_all = y - hx
    S_all = H @ P @ H.T + R
    if not used.any():
        empty = np.zeros(0)
        return belief, UpdateInfo(empty, np.zeros((0, 0)), 0.0, used, 0)
    e = e_all[used]
    S = S_all[np.ix_(used, used)]
    nis = float(e @ psd_solve(S, e))

    yu, Ru = y[used], R[np.ix_(used, used)]
    # A state the prior holds exactly (a gust state in calm air) cannot move: floored, its
    # zero step counts as zero sigmas.
    sigma = np.maximum(np.sqrt(np.diag(P)), 1e-300)
    x_i = x_prior
    Hu = H[used]
    hu = hx[used]
    done = 0
    first: tuple[FloatArray, FloatArray] | None = None
    for it in range(iterations):
        if it > 0:
            hx_i, H_i = h(x_i)
            hu, Hu = hx_i[used], H_i[used]
        S_i = Hu @ P @ Hu.T + Ru
        K = psd_solve(S_i, Hu @ P).T
        x_next = x_prior + K @ (yu - hu - Hu @ (x_prior - x_i))
        if it == 1 and first is not None and relinearise > 0.0:
            K1, H1 = first
            post_sigma = np.sqrt(np.maximum(np.diag(P) - np.sum(K1 * (H1 @ P).T, axis=1), 1e-300))
            part = slice(None) if judged is None else judged
            if np.max(np.abs(x_next - x_i)[part] / post_sigma[part]) < relinearise:
                K, Hu = K1, H1
                break
        done = it + 1
        step = np.max(np.abs(x_next - x_i) / sigma)
        x_i = x_next
        if it == 0:
            first = (K, Hu)
        if tolerance > 0.0 and step < tolerance:
            break
    I_KH = np.eye(n) - K @ Hu
    P_post = I_KH @ P @ I_KH.T + K @ Ru @ K.T
    return Belief(x_i, symmetrize(P_post)), UpdateInfo(e, S, nis, used, done)
