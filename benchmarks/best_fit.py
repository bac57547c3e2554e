"""The best a coefficient structure can do for a flight: output error on noise-free signals.

When an aircraft's aerodynamics hold more than the structure (JSBSim's alpha-dot terms, a
propeller slipstream on the tail), no coefficient values reproduce its flight exactly. A
filter fed that flight converges, at best, to the values that reproduce it most closely:
the maximum-likelihood (output-error) fit of the structure to the noise-free signals,
each channel weighted by the filter's measurement sigma. Errors against this best fit
show the filter; the distance from the best fit to JSBSim's linearised aerodynamics shows
what the structure misses.

In turbulence the fit flies the structure through the flight's own gusts (the simulator
knows them): the states are then the motion over the ground, the aerodynamics and the
pitot and vane see the air-relative V and alpha (equations.fly_step). The unmodelled
terms weigh differently once gusts move alpha apart from q (an alpha-dot term no longer
follows q), so a calm flight's best fit is not the target for a turbulent one. How
closely the fit reproduces the flight (its residual per channel, in sensor sigmas) says
how far the structure can be trusted there at all: JSBSim's rotational turbulence, which
the gust input leaves out, is one thing it cannot follow.
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
    x0: FloatArray, t: FloatArray, u: FloatArray, gust: FloatArray, m: eq.ModelArrays
) -> FloatArray:  # pragma: no cover
    """Fly x0 through the samples (inputs linear between them, the gust at its mean over
    each interval, one Runge-Kutta step per interval: equations.fly_step) and return what
    noise-free sensors at the CG read at every sample."""
    out = np.empty((t.shape[0], N_OBS))
    x = x0.copy()
    for i in range(t.shape[0]):
        h, _ = eq.observe(eq.air_relative(x, gust[i]), u[i], m)
        out[i] = h
        if i + 1 < t.shape[0]:
            g = 0.5 * (gust[i] + gust[i + 1])
            x = eq.fly_step(x, u[i], u[i + 1], g, t[i + 1] - t[i], m)
    return out


def best_fit(
    config: AircraftConfig,
    t_s: FloatArray,
    inputs: FloatArray,
    clean: FloatArray,
    start: FloatArray,
    gust: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Coefficients of config's structure that reproduce the noise-free observations
    `clean` [N x 7] (sensors at the CG, no bias) best, starting from `start`; `gust`
    [N x 2]: the flight's gusts (u_g, w_g [m/s]: the air-relative V and alpha being
    V + u_g and alpha + w_g / V), none in calm air. Returns the coefficients and the
    fit's RMS residual per channel in units of the channel's measurement sigma."""
    model = build_model(config, gust_states=False)
    u = np.ascontiguousarray(np.array([model.inputs(row) for row in inputs]))
    g = np.zeros((len(t_s), 2)) if gust is None else np.ascontiguousarray(gust, dtype=float)
    first = clean[0, :4].copy()
    first[0] -= g[0, 0]  # the state is the motion over the ground
    first[1] -= g[0, 1] / first[0]
    x0 = model.augment(first, np.asarray(start, float))
    weight = 1.0 / np.array(config.filter.measurement_sigma)
    scale = np.maximum(np.abs(x0), 1e-3)
    t = np.ascontiguousarray(t_s, dtype=float)

    def residual(z: FloatArray) -> FloatArray:
        return np.asarray(((clean - _outputs(z * scale, t, u, g, model.arrays)) * weight).ravel())

    sol = least_squares(residual, x0 / scale, x_scale="jac", method="lm", xtol=1e-10)
    rms = np.sqrt(np.mean(residual(sol.x).reshape(clean.shape) ** 2, axis=0))
    return np.asarray(sol.x * scale)[model.coefficients], rms
