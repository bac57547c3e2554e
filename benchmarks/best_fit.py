"""The best a coefficient structure can do for a flight: output error on noise-free signals.

When an aircraft's aerodynamics hold more than the structure (JSBSim's alpha-dot terms, a
propeller slipstream on the tail), no coefficient values reproduce its flight exactly. A
filter fed that flight converges, at best, to the values that reproduce it most closely:
the maximum-likelihood (output-error) fit of the structure to the noise-free signals,
each channel weighted by the filter's measurement sigma. Errors against this best fit
show the filter; the distance from the best fit to JSBSim's linearised aerodynamics shows
what the structure misses.

A turbulent flight is judged against its calm twin's best fit: the gusts are not in the
structure, and a fit to the turbulent flight, even flown through its own gusts (the
simulator knows them), is a poor target. Over 60 s its lift terms follow the phugoid
rather than the lift: on the 737, whose lift JSBSim makes exactly linear in the
structure's regressors, such a fit put CLa 5 % below JSBSim's own value while the calm
fit is within 1 %. What the gusts do show is how far the structure can follow the
turbulent flight at all: `reproduction` flies the calm fit through the flight's gusts
(the states the motion over the ground, the aerodynamics and the pitot and vane the
air-relative V and alpha, the aerodynamics the pitch rate less the pitch gust:
equations.fly_step), fits the initial state alone, and returns
the residual per channel in sensor sigmas.

Where the structure cannot reproduce the flight, what it gets closest to depends on how
the channels are weighed, and so does the best fit. `spread` says how sharp a target it
is: how far each coefficient moves when one channel's weight is halved or doubled. An
estimator that weighs the channels otherwise (a filter's process noise shifts the
weight between them) can differ from the best fit by that much and still be as right.
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
        out[i] = eq.observe_in_gust(x, u[i], gust[i], m)
        if i + 1 < t.shape[0]:
            g = 0.5 * (gust[i] + gust[i + 1])
            x = eq.fly_step(x, u[i], u[i + 1], g, t[i + 1] - t[i], m)
    return out


def _fit(
    config: AircraftConfig,
    t_s: FloatArray,
    inputs: FloatArray,
    clean: FloatArray,
    coefficients: FloatArray,
    gust: FloatArray | None,
    free_coefficients: bool,
    sigma: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Output error on the noise-free observations `clean` [N x 7] (sensors at the CG, no
    bias), flown through `gust` [N x 2] (u_g, w_g [m/s]: the air-relative V and alpha
    being V + u_g and alpha + w_g / V; none: calm air), the initial state always free,
    the coefficients from `coefficients` and free when `free_coefficients`, each channel
    weighted by 1 / `sigma` (default: the config's measurement sigmas); a third gust
    column is the pitch gust q_g [rad/s] (the aerodynamics see q - q_g). Returns the
    coefficients and the RMS residual per channel in units of its sigma."""
    model = build_model(config, gust_states=False)
    u = np.ascontiguousarray(np.array([model.inputs(row) for row in inputs]))
    g = np.zeros((len(t_s), 2)) if gust is None else np.ascontiguousarray(gust, dtype=float)
    first = clean[0, :4].copy()
    first[0] -= g[0, 0]  # the state is the motion over the ground
    first[1] -= g[0, 1] / first[0]
    x0 = model.augment(first, np.asarray(coefficients, float))
    n_free = x0.shape[0] if free_coefficients else 4
    # The channels `clean` holds, the first ones in the model's order (a flight without a
    # climb-rate column is fitted on the seven before it).
    c = clean.shape[1]
    weight = 1.0 / np.array(config.filter.measurement_sigma if sigma is None else sigma)[:c]
    scale = np.maximum(np.abs(x0), 1e-3)
    t = np.ascontiguousarray(t_s, dtype=float)

    def full(z: FloatArray) -> FloatArray:
        x = x0.copy()
        x[:n_free] = z * scale[:n_free]
        return x

    def residual(z: FloatArray) -> FloatArray:
        out = _outputs(full(z), t, u, g, model.arrays)[:, :c]
        return np.asarray(((clean - out) * weight).ravel())

    z0 = x0[:n_free] / scale[:n_free]
    sol = least_squares(residual, z0, x_scale="jac", method="lm", xtol=1e-10)
    rms = np.sqrt(np.mean(residual(sol.x).reshape(clean.shape) ** 2, axis=0))
    return full(sol.x)[model.coefficients], rms


def best_fit(
    config: AircraftConfig,
    t_s: FloatArray,
    inputs: FloatArray,
    clean: FloatArray,
    start: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """Coefficients of config's structure that reproduce the noise-free observations of a
    calm flight best, starting from `start`, and the fit's RMS residual per channel in
    sensor sigmas."""
    return _fit(config, t_s, inputs, clean, start, None, True)


def reproduction(
    config: AircraftConfig,
    t_s: FloatArray,
    inputs: FloatArray,
    clean: FloatArray,
    coefficients: FloatArray,
    gust: FloatArray,
) -> FloatArray:
    """How closely the structure with `coefficients`, flown through the flight's gusts
    from the initial state that fits best, reproduces its noise-free observations: the
    RMS residual per channel in sensor sigmas."""
    return _fit(config, t_s, inputs, clean, coefficients, gust, False)[1]


WEIGHT_FACTORS = (0.5, 2.0)
"""Each channel's weight is multiplied by these, one channel at a time (`spread`)."""


def spread(
    config: AircraftConfig,
    t_s: FloatArray,
    inputs: FloatArray,
    clean: FloatArray,
    best: FloatArray,
) -> FloatArray:
    """How sharp a target the calm best fit `best` is: per coefficient, the largest move
    [% of its value] of the best fit when one channel's weight is halved or doubled."""
    base = np.array(config.filter.measurement_sigma, float)
    moves = []
    for c in range(N_OBS):
        for factor in WEIGHT_FACTORS:
            sigma = base.copy()
            sigma[c] /= factor
            fit, _ = _fit(config, t_s, inputs, clean, best, None, True, sigma)
            moves.append(np.abs(fit - best) / np.maximum(np.abs(best), 1e-12))
    return np.asarray(100.0 * np.max(moves, axis=0))
