"""The structure sigma of a whole-record fit (decision 0022): decision 0017's check of
the filters applied to the fit. Each observed channel in turn is trusted half as much
(its variance times weighting.VARIANCE_FACTOR) and the fit re-made from its end; where the
model holds, the fit moves no more than the information given up allows, and where it
does not, the channels pull the fit different ways and it moves further.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from gcs_estimator.arrays import BoolArray, FloatArray
from gcs_estimator.model.channels import N_OBS
from gcs_estimator.refine.result import RefineError
from gcs_estimator.uncertainty.weighting import VARIANCE_FACTOR, WEIGHT_SHARE

STRUCTURE_ITERATIONS = 4
"""Gauss-Newton iterations of each re-weighted fit (it starts from the fit's end)."""


def structure_sigma(
    J3: FloatArray,
    k: int,
    observed: BoolArray,
    base: FloatArray,
    refit: Callable[[FloatArray], FloatArray],
    prior: FloatArray | None = None,
) -> FloatArray:
    """The structure sigma of the first k parameters (decision 0017, the filters' check
    applied to a whole-record fit): sqrt(WEIGHT_SHARE * sum_c max(0, d_c^2 - |s_c^2 -
    s^2|)) over the observed channels c, where d_c is how far the fit moves from `base`
    when re-made with channel c's variance times VARIANCE_FACTOR (refit(scale) gives its
    first k parameters), and s_c, s the Cramer-Rao sigmas with and without that (from the
    whitened sensitivities J3 [N x 7 x p], with the priors' information `prior` [p x p])."""
    per_channel = np.einsum("ncp,ncq->cpq", J3, J3)
    M = per_channel.sum(axis=0) + (0.0 if prior is None else prior)
    crb2 = np.diag(np.linalg.pinv(M))[:k]
    excess = np.zeros(k)
    for c in np.flatnonzero(observed):
        scale = np.ones(N_OBS)
        scale[c] = VARIANCE_FACTOR
        try:
            d = refit(scale) - base
        except RefineError:  # no stable fit with this weight: the check has no move
            continue
        less = M - (1.0 - 1.0 / VARIANCE_FACTOR) * per_channel[c]
        excess += np.maximum(0.0, d * d - np.abs(np.diag(np.linalg.pinv(less))[:k] - crb2))
    return np.asarray(np.sqrt(WEIGHT_SHARE * excess))
