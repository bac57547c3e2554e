"""The best a coefficient structure can do for a flight: output error on noise-free signals.

When an aircraft's aerodynamics hold more than the structure (JSBSim's alpha-dot terms, a
propeller slipstream on the tail), no coefficient values reproduce its flight exactly. A
filter fed that flight converges, at best, to the values that reproduce it most closely:
the maximum-likelihood (output-error) fit of the structure to the noise-free signals,
each channel weighted by the filter's measurement sigma. Errors against this best fit
show the filter; the distance from the best fit to JSBSim's linearised aerodynamics shows
what the structure misses.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from scipy.optimize import least_squares

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import AircraftConfig
from gcs_estimator.model import compiled  # noqa: F401  (registers the equations with numba)
from gcs_estimator.model import equations as eq
from gcs_estimator.model.aircraft import build_model
from gcs_estimator.model.channels import N_OBS


@njit(cache=True)
def _outputs(
    x0: FloatArray, t: FloatArray, u: FloatArray, m: eq.ModelArrays
) -> FloatArray:  # pragma: no cover
    """Fly x0 through the samples (inputs linear between them, one Runge-Kutta step per
    sample interval) and return h(x) at every sample."""
    out = np.empty((t.shape[0], N_OBS))
    x = x0.copy()
    still = np.zeros(2)
    for i in range(t.shape[0]):
        h, _ = eq.observe(x, u[i], m)
        out[i] = h
        if i + 1 < t.shape[0]:
            x = eq.rk4_step(x, u[i], u[i + 1], still, t[i + 1] - t[i], m)[0]
    return out


def best_fit(
    config: AircraftConfig,
    t_s: FloatArray,
    inputs: FloatArray,
    clean: FloatArray,
    start: FloatArray,
) -> FloatArray:
    """Coefficients of config's structure that reproduce the noise-free observations
    `clean` [N x 7] (sensors at the CG, no bias) best, starting from `start`."""
    model = build_model(config)
    u = np.ascontiguousarray(np.array([model.inputs(row) for row in inputs]))
    x0 = model.augment(clean[0, :4].copy(), np.asarray(start, float))
    weight = 1.0 / np.array(config.filter.measurement_sigma)
    scale = np.maximum(np.abs(x0), 1e-3)
    t = np.ascontiguousarray(t_s, dtype=float)

    def residual(z: FloatArray) -> FloatArray:
        return np.asarray(((clean - _outputs(z * scale, t, u, model.arrays)) * weight).ravel())

    sol = least_squares(residual, x0 / scale, x_scale="jac", method="lm", xtol=1e-10)
    return np.asarray(sol.x * scale)[model.coefficients]
