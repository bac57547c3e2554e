"""Output-error maximum likelihood on a simulated flight: the yardstick for the filters.

In calm air the simulated measurements are the model's outputs plus white noise of known
sigma, so the maximum-likelihood estimate of the coefficients (and the initial state) is
the weighted least-squares fit of the whole record, integrated with the simulator's own
integrator. It is asymptotically efficient: its errors show what the data allow, seed by
seed, independently of any filter. The benchmark runs it next to the filters.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import AircraftConfig
from gcs_estimator.estimation.filters.core import MOTION_INPUTS
from gcs_estimator.model.aircraft import build_model
from sim.scenario import scenario_of
from sim.truth import Flight, integrate


@dataclass(frozen=True)
class OutputErrorFit:
    state0: FloatArray
    """Estimated initial state [V, alpha, theta, q]."""
    coefficients: FloatArray
    sigma: FloatArray
    """1-sigma of the coefficients from the Fisher information at the fit (Cramer-Rao)."""
    covariance: FloatArray
    """The coefficients' Cramer-Rao covariance [p x p] (the initial state's part of the
    inverse Fisher information left out)."""
    cost: float
    """Mean squared normalised residual (1 when the fit leaves only the sensor noise)."""


def output_error(
    config: AircraftConfig,
    flight: Flight,
    start: FloatArray | None = None,
    until_s: float | None = None,
) -> OutputErrorFit:
    """Fit initial state and coefficients to the flight's measurements, each channel
    weighted by the configured filter's measurement sigma. start: augmented state to
    start from (default: the flight's first true state and the true coefficients, the
    most favourable start). until_s: use only the samples up to this time."""
    model = build_model(config, gust_states=False)
    sim = scenario_of(config)
    per_sample = max(1, round(1.0 / (sim.sample_rate_hz * sim.integration_step_s)))
    dt = 1.0 / (sim.sample_rate_hz * per_sample)
    n = len(flight.t_s) if until_s is None else int(np.searchsorted(flight.t_s, until_s, "right"))
    u_samples = np.ascontiguousarray(flight.inputs[:n], dtype=float)
    # The manoeuvre switches on sample times: the commands hold from one sample to the next.
    u_steps = np.repeat(u_samples[:-1], per_sample, axis=0)
    if u_samples.shape[1] > MOTION_INPUTS:
        # The lateral motion (bank, roll and yaw rate) moves between its samples: taken
        # linearly, at each step's middle, as the filters take it (core.MOTION_INPUTS).
        # Held, it misplaced the turns' lift and pitch rate, and the fit of a mission
        # lay several of its sigmas off the truth along combinations it holds well.
        frac = (np.tile(np.arange(per_sample), n - 1) + 0.5) / per_sample
        lo = u_steps[:, MOTION_INPUTS:]
        hi = np.repeat(u_samples[1:, MOTION_INPUTS:], per_sample, axis=0)
        u_steps[:, MOTION_INPUTS:] = lo + frac[:, None] * (hi - lo)
    no_gust = np.zeros((u_steps.shape[0] + 1, 2))
    weight = 1.0 / np.array(config.filter.measurement_sigma)
    y = flight.measurements[:n]
    if start is None:
        start = model.augment(flight.states[0], flight.truth)
    scale = np.maximum(np.abs(start), 1e-3)

    measured = np.isfinite(y)  # a channel the flight lacks (no climb-rate sensor) left out

    def residual(z: FloatArray) -> FloatArray:
        _, h = integrate(z * scale, u_steps, u_samples, no_gust, dt, per_sample, model.arrays)
        return np.asarray(((y - h) * weight)[measured])

    sol = least_squares(residual, start / scale, x_scale="jac", method="lm", xtol=1e-12)
    x = sol.x * scale
    J = sol.jac / scale
    cov = np.linalg.inv(J.T @ J)
    sigma = np.sqrt(np.diag(cov))
    return OutputErrorFit(
        state0=x[model.flight],
        coefficients=x[model.coefficients],
        sigma=sigma[model.coefficients],
        covariance=cov[model.coefficients, model.coefficients],
        cost=float(np.mean(sol.fun**2)),
    )
