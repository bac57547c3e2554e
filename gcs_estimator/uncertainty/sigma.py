"""The sigma to trust, and what it is made of: of a filter's coefficient estimates (here),
and of the whole-record fit's (refine; the section at the end of this module).

A filter's covariance gives sigma_P = sqrt(diag P): how far its estimates would scatter
if its model and noise settings were right. Two checks at the end of a run widen it
where the data say they are not:

- movement (docs/decisions/0008): over the second half of the run the estimates moved
  r times as much (in variance) as the covariance said they would (movement_ratio); the
  movement factor is m = sqrt(max(1, r));
- structure (docs/decisions/0017): how far the estimates depend on how much each channel
  is trusted, beyond what the covariance allows (weighting.structure_check): sigma_S.

    sigma = sqrt((m sigma_P)^2 + sigma_S^2)

with m = 1 where the run was too short to judge the movement and sigma_S = 0 where the
structure was not checked. This sigma is the one the table, the JSON, the warnings and
the identifiability marks use; its parts are kept beside it (SigmaParts; the JSON's
sigma_parts).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from gcs_estimator.arrays import FloatArray

DELAY_WARNING_SIGMA = 3.0
"""A delay the whole-record fit finds this many of its sigmas from the one the filters
took the inputs with ([data] input_delay_s) is pointed out: the filters flew the inputs
at the wrong time, and their estimates carry it (decision 0044)."""

MOVEMENT_WINDOW_MIN_FRAMES = 50
"""Frames the movement check needs after the last restart (fewer: no correction)."""
MOVEMENT_BANDWIDTH = 0.25
"""Longest lag of the movement check, as a share of its window (Bartlett weights)."""


def movement_ratio(coefficients: FloatArray, sigma: FloatArray, start: int) -> FloatArray:
    """How much more a filter's coefficient estimates moved from frame `start` to the end
    than its own covariance said they would (variance ratio per coefficient; 1: as
    expected; NaN where the window says nothing).

    Under the filter's model the estimate of a constant is a martingale: its increments
    are uncorrelated, and the variance of their sum over the window is the variance
    the covariance lost there, sigma(start-1)^2 - sigma(end)^2. Model-structure error
    and coloured noise break both (the estimate drifts as the manoeuvre changes which
    error it absorbs, and increments correlate over seconds). The ratio of the
    increments' long-run variance (Bartlett-weighted autocovariance up to a quarter of
    the window) to that loss is the factor by which the filter overcounted its
    information; sigma * sqrt(max(1, ratio)) is the sigma it allows. It is the filter's
    analogue of the Morelli-Klein correction of an output-error fit's Cramer-Rao bound
    (docs/decisions/0008).

    The weighted sum is taken in O(N) as the sum of squared moving sums: with the
    increments d zero-padded, sum_t (d_t + ... + d_t+L)^2 = sum_k (L + 1 - |k|) acov(k),
    and a moving sum of increments is a difference of two estimates.

    Args:
        coefficients: the estimates after each frame [N x p].
        sigma: their covariance sigma after each frame [N x p].
        start: the window's first frame (movement_start).
    """
    p = coefficients.shape[1]
    w = coefficients.shape[0] - start
    if start < 1 or w < MOVEMENT_WINDOW_MIN_FRAMES:
        return np.full(p, np.nan)
    s2 = np.asarray(sigma[[start - 1, -1]], float) ** 2
    lag = max(1, int(MOVEMENT_BANDWIDTH * w))
    # Moving sums of lag + 1 increments d_t .. d_t+lag for t = -lag .. w - 1 (the
    # increments outside 0 .. w - 1 are zero): x[hi] - x[lo] with x the estimates.
    t = np.arange(-lag, w)
    hi = np.minimum(t + lag, w - 1) + 1
    lo = np.maximum(t, 0)
    moved = np.empty(p)
    for j in range(p):  # one column at a time: an hour's history stays a few MB
        x = np.asarray(coefficients[start - 1 :, j], float)
        sums = x[hi] - x[lo]
        moved[j] = (sums @ sums) / (lag + 1)
    expected = s2[0] - s2[1]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(expected > 1e-6 * s2[0], moved / expected, np.nan)
    return np.asarray(ratio)


def movement_start(frames: int, final_pass_from: int) -> int:
    """First frame of the movement check: the second half of the run, and never before
    the final pass's second frame (a pass converging from its prior moves by design)."""
    return max(frames // 2, final_pass_from + 1, 1)


class SigmaParts(NamedTuple):
    """What one coefficient's sigma to trust is made of (trusted_sigma)."""

    covariance: float
    """sigma_P: the filter covariance's sqrt(P_ii)."""
    movement_factor: float
    """m = sqrt(max(1, r)) (NaN: the run was too short to judge the movement)."""
    structure: float
    """sigma_S (NaN: the structure was not checked)."""
    inflation: float
    """sigma / sigma_P, at least 1 (NaN: neither check could be made)."""


class TrustedSigma(NamedTuple):
    """A filter's sigma to trust per coefficient, and its parts (each [p])."""

    sigma: FloatArray
    """sqrt((m sigma_P)^2 + sigma_S^2): the one to trust."""
    covariance: FloatArray
    movement_factor: FloatArray
    structure: FloatArray
    inflation: FloatArray

    def parts(self, i: int) -> SigmaParts:
        """Coefficient i's parts."""
        return SigmaParts(
            float(self.covariance[i]),
            float(self.movement_factor[i]),
            float(self.structure[i]),
            float(self.inflation[i]),
        )


def trusted_sigma(
    covariance: FloatArray, ratio: FloatArray, structure: FloatArray | None = None
) -> TrustedSigma:
    """The sigma to trust from its parts: sqrt((m sigma_P)^2 + sigma_S^2), m = sqrt(max(1,
    r)) (module docstring).

    Where a part is NaN it is left out (the run too short to judge the movement: m = 1;
    the structure not checked: sigma_S = 0); where the sum is not finite (a structure
    replay that diverged), the covariance's sigma stands alone.

    Args:
        covariance: sigma_P per coefficient.
        ratio: the movement ratio r per coefficient (movement_ratio; NaN: not judged).
        structure: sigma_S per coefficient (weighting.structure_check; None: not checked).
    """
    factor = np.sqrt(np.maximum(ratio, 1.0))
    moved = covariance * factor
    total = moved
    if structure is not None:
        total = np.hypot(np.where(np.isfinite(moved), moved, covariance), structure)
    with np.errstate(divide="ignore", invalid="ignore"):
        inflation = total / covariance
    return TrustedSigma(
        sigma=np.where(np.isfinite(total), total, covariance),
        covariance=covariance,
        movement_factor=factor,
        structure=np.full(len(covariance), np.nan) if structure is None else structure,
        inflation=inflation,
    )


def filter_sigma(
    coefficients: FloatArray,
    sigma: FloatArray,
    covariance: FloatArray,
    final_pass_from: int,
    structure: FloatArray | None = None,
) -> TrustedSigma:
    """A finished filter's sigma to trust: its movement judged over the second half of
    its run (movement_start), with its structure sigma where the check was made.

    Args:
        coefficients: the estimates after each frame [N x p] (the filter's track).
        sigma: their covariance sigma after each frame [N x p].
        covariance: the final covariance sigma sigma_P [p].
        final_pass_from: first frame of the final pass (after the last restart's swap).
        structure: sigma_S [p] (None: not checked).
    """
    start = movement_start(coefficients.shape[0], final_pass_from)
    return trusted_sigma(covariance, movement_ratio(coefficients, sigma, start), structure)


# ---- the whole-record fit (refine) ---------------------------------------------------
# The sigma to trust of a whole-record fit's estimates, and what it is made of.
#
# A fit's information M = sum S^T R^-1 S gives the Cramer-Rao sigma sigma_CR = sqrt(diag
# M^-1): how far the estimates would scatter if the residuals were white. Three checks
# widen it where the record says they are not, and a fourth compares the fit with the
# filter it started from:
#
# - Morelli-Klein (J. Aircraft 34(5), 1997): the covariance from the residuals' own
#   autocorrelation, M^-1 (sum_i sum_j S_i^T R^-1 Rvv(i - j) R^-1 S_j) M^-1, whose
#   diagonal is v_MK (covariance.sandwich);
# - structure (decision 0022): how far the fit moves when one channel at a time is trusted
#   half as much, beyond what the information given up explains: sigma_S
#   (structure.structure_sigma), never less than the filter's own check of the same record
#   found, sigma_SF (decision 0031);
# - difference (decision 0030): how far the fit lands from the filter it started from,
#   beyond what the two covariances allow: sigma_D (difference_sigma).
#
#     sigma_fit = max(sqrt(max(v_MK, 0) + max(sigma_S, sigma_SF)^2), sigma_CR)
#     sigma     = max(sqrt(sigma_fit^2 + sigma_D^2), sigma_F)
#
# sigma_fit is the fit's own (a fit started from no filter's run stops there). sigma_F is
# the sigma to trust of the filter the fit started from, over the same frames (decision
# 0057): the fit reads the record the filter read, with the same structure and the same
# timing; what the filter's checks found its estimates carry beyond its covariance (how
# far they moved, the channels' weights, timing, placement, the noise floor) the fit's
# residuals need not show (its Cramer-Rao and Morelli-Klein sigmas trust its own noise
# model, and a step between two samples pins its fitted delay at zero), so the fit is
# trusted no further than the filter. This sigma
# is the one the table, the JSON, the warnings and the identifiability marks use; its
# parts are kept beside it (FitSigma).


class FilterEstimate(NamedTuple):
    """The filter's estimate a fit started from, as far as the fit's sigma compares with
    it (each [p], over the coefficients)."""

    coefficients: FloatArray
    sigma: FloatArray
    """Its covariance sigma sqrt(diag P)."""
    structure: FloatArray | None = None
    """Its structure sigma (weighting.structure_check of the same record; NaN where a
    coefficient was not checked); None where the run made no check."""
    trusted: FloatArray | None = None
    """Its sigma to trust (filter_sigma) over the frames the fit reads; None where the
    fit reads other frames (a window) or the run has no summaries."""


class FitSigma(NamedTuple):
    """A fit's sigma to trust per parameter, and its parts (each [p]; NaN where the fit
    did not estimate a parameter)."""

    sigma: FloatArray
    """The one to trust: sqrt(sigma_fit^2 + sigma_D^2) (module docstring)."""
    cramer_rao: FloatArray
    """sigma_CR: white residuals assumed."""
    morelli_klein: FloatArray
    """sqrt(max(v_MK, 0)): the residuals' colour allowed for."""
    structure: FloatArray
    """The fit's structure sigma, at least filter_structure where that was given."""
    within_fit: FloatArray
    """sigma_fit: the fit's own, without the difference from the filter."""
    filter_structure: FloatArray | None = None
    """sigma_SF: the filter's structure sigma the fit's does not fall below; None where
    none was given."""
    difference: FloatArray | None = None
    """sigma_D; None for a fit not compared with a filter."""
    filter_trusted: FloatArray | None = None
    """sigma_F: the filter's sigma to trust the fit's does not fall below (decision
    0057); None where none was given."""


def fit_sigma(
    cramer_rao: FloatArray,
    morelli_klein_var: FloatArray,
    structure: FloatArray,
    filter_structure: FloatArray | None = None,
    difference: FloatArray | None = None,
    filter_trusted: FloatArray | None = None,
) -> FitSigma:
    """The sigma to trust from its parts (module docstring).

    Args:
        cramer_rao: sigma_CR per parameter.
        morelli_klein_var: v_MK, the Morelli-Klein covariance's diagonal (may round below
            zero: counted as zero).
        structure: the fit's own structure sigma.
        filter_structure: sigma_SF, the filter's (NaN where it has none; None: no check).
        difference: sigma_D (difference_sigma; None: not compared with a filter).
        filter_trusted: sigma_F, the filter's sigma to trust over the same frames (NaN
            where it has none; None: not given).
    """
    if filter_structure is not None:
        structure = np.fmax(structure, filter_structure)
    within = np.maximum(np.sqrt(np.maximum(morelli_klein_var, 0.0) + structure**2), cramer_rao)
    sigma = within if difference is None else np.sqrt(within**2 + difference**2)
    if filter_trusted is not None:
        sigma = np.fmax(sigma, filter_trusted)
    return FitSigma(
        sigma=np.asarray(sigma),
        cramer_rao=cramer_rao,
        morelli_klein=np.sqrt(np.maximum(morelli_klein_var, 0.0)),
        structure=structure,
        within_fit=within,
        filter_structure=filter_structure,
        difference=difference,
        filter_trusted=filter_trusted,
    )


def difference_sigma(
    coefficients: FloatArray, cramer_rao: FloatArray, filter_estimate: FilterEstimate
) -> FloatArray:
    """How far a fit's coefficients land from a filter's estimate of the same record
    beyond what their covariances allow: sqrt(max(0, d^2 - |s_f^2 - s^2|)), d the
    difference, s_f the filter's covariance sigma and s the fit's Cramer-Rao sigma
    (decision 0030). Where the model holds both estimate the same values and d has about
    the variance their covariances differ by (Hausman 1978): nothing is added. Where it
    does not, the filter and the fit weigh the record differently (the filter's noise
    model against the fit's fitted or held one) and settle on different compromises;
    either may carry that much bias. 0 where a sigma is not finite."""
    d = np.asarray(coefficients, float) - np.asarray(filter_estimate.coefficients, float)
    allowed = np.abs(np.asarray(filter_estimate.sigma, float) ** 2 - cramer_rao**2)
    excess = np.where(np.isfinite(allowed), np.maximum(0.0, d * d - allowed), 0.0)
    return np.asarray(np.sqrt(excess))
