"""The sigma to trust of a whole-record fit's estimates, and what it is made of.

A fit's information M = sum S^T R^-1 S gives the Cramer-Rao sigma sigma_CR = sqrt(diag
M^-1): how far the estimates would scatter if the residuals were white. Three checks
widen it where the record says they are not, and a fourth compares the fit with the
filter it started from:

- Morelli-Klein (J. Aircraft 34(5), 1997): the covariance from the residuals' own
  autocorrelation, M^-1 (sum_i sum_j S_i^T R^-1 Rvv(i - j) R^-1 S_j) M^-1, whose
  diagonal is v_MK (covariance.sandwich);
- structure (decision 0022): how far the fit moves when one channel at a time is trusted
  half as much, beyond what the information given up explains: sigma_S
  (structure.structure_sigma), never less than the filter's own check of the same record
  found, sigma_SF (decision 0031);
- difference (decision 0030): how far the fit lands from the filter it started from,
  beyond what the two covariances allow: sigma_D (difference_sigma).

    sigma_fit = max(sqrt(max(v_MK, 0) + max(sigma_S, sigma_SF)^2), sigma_CR)
    sigma     = sqrt(sigma_fit^2 + sigma_D^2)

sigma_fit is the fit's own (a fit started from no filter's run stops there). This sigma
is the one the table, the JSON, the warnings and the identifiability marks use; its
parts are kept beside it (FitSigma).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from gcs_estimator.arrays import FloatArray


class FilterEstimate(NamedTuple):
    """The filter's estimate a fit started from, as far as the fit's sigma compares with
    it (each [p], over the coefficients)."""

    coefficients: FloatArray
    sigma: FloatArray
    """Its covariance sigma sqrt(diag P)."""
    structure: FloatArray | None = None
    """Its structure sigma (weighting.structure_check of the same record; NaN where a
    coefficient was not checked); None where the run made no check."""


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


def fit_sigma(
    cramer_rao: FloatArray,
    morelli_klein_var: FloatArray,
    structure: FloatArray,
    filter_structure: FloatArray | None = None,
    difference: FloatArray | None = None,
) -> FitSigma:
    """The sigma to trust from its parts (module docstring).

    Args:
        cramer_rao: sigma_CR per parameter.
        morelli_klein_var: v_MK, the Morelli-Klein covariance's diagonal (may round below
            zero: counted as zero).
        structure: the fit's own structure sigma.
        filter_structure: sigma_SF, the filter's (NaN where it has none; None: no check).
        difference: sigma_D (difference_sigma; None: not compared with a filter).
    """
    if filter_structure is not None:
        structure = np.fmax(structure, filter_structure)
    within = np.maximum(np.sqrt(np.maximum(morelli_klein_var, 0.0) + structure**2), cramer_rao)
    sigma = within if difference is None else np.sqrt(within**2 + difference**2)
    return FitSigma(
        sigma=np.asarray(sigma),
        cramer_rao=cramer_rao,
        morelli_klein=np.sqrt(np.maximum(morelli_klein_var, 0.0)),
        structure=structure,
        within_fit=within,
        filter_structure=filter_structure,
        difference=difference,
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
