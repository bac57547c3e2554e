"""The covariance of a fit's parameters: the Cramer-Rao bound, and the Morelli-Klein
correction for coloured residuals.

- The Cramer-Rao bound, M^-1 with M = sum S^T R^-1 S: right when the residuals are
  white, which they are only when the model holds everything the aircraft does;
- the Morelli-Klein correction (J. Aircraft 34(5), 1997), which uses the residuals' own
  autocorrelation: M^-1 (sum_i sum_j S_i^T R^-1 Rvv(i - j) R^-1 S_j) M^-1. Coloured
  residuals (turbulence, what the structure misses) carry less information than white
  ones, and this bound says how much less.
"""

from __future__ import annotations

import math

import numpy as np

from gcs_estimator.arrays import BoolArray, FloatArray
from gcs_estimator.model.channels import N_OBS


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


def sandwich(
    J: FloatArray,
    e: FloatArray,
    mask: FloatArray,
    observed: BoolArray,
    prior: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """From the whitened residuals e [N x 7] and their sensitivities J [N x 7 x p]: the
    Cramer-Rao covariance M^-1, the Morelli-Klein covariance and each channel's residual
    colour (Refined.residual_colour). prior [p x p]: the information of priors on some
    parameters (white: it adds to M and to the sandwich's middle alike)."""
    N = e.shape[0]
    M = np.einsum("ncp,ncq->pq", J, J)
    if prior is not None:
        M = M + prior
    # A parameter the residuals do not feel (a process noise at its lower bound) has no
    # bound: NaN, and the others' without it.
    felt = np.diag(M) > 1e-12 * max(float(np.max(np.diag(M))), 1e-300)
    Minv = np.full_like(M, np.nan)
    sub = M[np.ix_(felt, felt)]
    try:
        Minv[np.ix_(felt, felt)] = np.linalg.inv(sub)
    except np.linalg.LinAlgError:
        Minv[np.ix_(felt, felt)] = np.linalg.pinv(sub)
    J = J[:, :, felt]
    middle = np.zeros((J.shape[2], J.shape[2]))
    colour = np.full(N_OBS, np.nan)
    for c in range(N_OBS):
        if not observed[c]:
            continue
        n_c = max(float(mask[:, c].sum()), 1.0)
        rho = _autocorrelation(e[:, c]) * (N / n_c)
        part = J[:, c, :].T @ _toeplitz_apply(rho, J[:, c, :])
        middle += part
        white = float(rho[0]) * float(np.sum(J[:, c, :] ** 2))
        colour[c] = float(np.trace(part)) / white if white > 0.0 else math.nan
    if prior is not None:
        middle += prior[np.ix_(felt, felt)]
    inner = Minv[np.ix_(felt, felt)]
    cov_mk = np.full_like(M, np.nan)
    cov_mk[np.ix_(felt, felt)] = inner @ middle @ inner
    return Minv, 0.5 * (cov_mk + cov_mk.T), colour
