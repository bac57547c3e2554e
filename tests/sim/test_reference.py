"""The output-error yardstick: exact on noise-free data, and the filters match it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.estimation.filters.core import MOTION_INPUTS
from gcs_estimator.runtime.session import run_recording
from sim.reference import output_error
from sim.scenario import mission, scenario_of
from sim.truth import simulate


def test_recovers_every_coefficient_from_noise_free_data(noc_config: AircraftConfig) -> None:
    scenario = scenario_of(noc_config)
    sensors = replace(scenario.sensors, noise_sigma=(0.0,) * 7)
    config = noc_config
    flight = simulate(config, seed=1, scenario=replace(scenario, sensors=sensors))
    # Start 20 % off every coefficient and 0.5 m/s, 0.01 rad off the initial state.
    start = np.concatenate(
        [flight.states[0] + np.array([0.5, 0.01, -0.01, 0.0]), flight.truth * 1.2]
    )
    fit = output_error(config, flight, start=start)
    np.testing.assert_allclose(fit.coefficients, flight.truth, rtol=1e-5)
    np.testing.assert_allclose(fit.state0, flight.states[0], atol=1e-7)
    assert fit.cost < 1e-10


def test_both_filters_end_at_the_maximum_likelihood_estimate_with_its_sigma(
    noc_config: AircraftConfig,
) -> None:
    """In calm air the output-error fit is the maximum-likelihood estimate, and its sigma
    the Cramer-Rao bound: an efficient, consistent filter ends where the fit does, as sure as it
    is, within a fraction of a sigma."""
    flight = simulate(noc_config, seed=4)
    fit = output_error(noc_config, flight)
    # Only sensor noise is left: the mean squared normalised residual of 21,007 numbers.
    assert abs(fit.cost - 1.0) < 0.03
    z = (fit.coefficients - flight.truth) / fit.sigma
    assert np.all(np.abs(z) < 4.0), z
    assert np.allclose(np.sqrt(np.diag(fit.covariance)), fit.sigma)
    fit_corr = fit.covariance / np.outer(fit.sigma, fit.sigma)

    # The covariance's sigma alone: no structure check (decision 0066).
    config = load_config(noc_config.source, ["filter.structure_check=off"])
    res = run_recording(config, flight.t_s, flight.inputs, flight.measurements).result
    for kind, f in res.filters.items():
        gap = (f.coefficients - fit.coefficients) / fit.sigma
        assert np.all(np.abs(gap) < 0.3), (kind, dict(zip(res.names, gap.round(2), strict=True)))
        # The whole covariance, not only its diagonal: the NEES weighs the correlations.
        corr = f.covariance / np.outer(f.sigma, f.sigma)
        assert np.max(np.abs(corr - fit_corr)) < 0.05, (kind, np.abs(corr - fit_corr).max())
        ratio = f.sigma / fit.sigma
        assert np.all(np.abs(ratio - 1.0) < 0.05), (
            kind,
            dict(zip(res.names, ratio.round(3), strict=True)),
        )


def test_a_missions_turns_are_flown_as_the_simulator_flew_them() -> None:
    """A mission's bank angle and roll and yaw rates move between their samples: the fit
    takes them linearly, as the filters do, and recovers the coefficients from the
    mission's noise-free signals (held from sample to sample, the turns' lift and pitch
    rate were misplaced and the fit of a noisy mission lay several sigmas off the truth)."""
    config = load_config("noc_uav", [*mission("none", 60.0)])
    scenario = scenario_of(config)
    sensors = replace(scenario.sensors, noise_sigma=(0.0,) * len(scenario.sensors.noise_sigma))
    flight = simulate(config, seed=1, scenario=replace(scenario, sensors=sensors))
    assert flight.inputs.shape[1] > MOTION_INPUTS and np.ptp(flight.inputs[:, 3]) > 0.3
    fit = output_error(config, flight)
    # In the sigmas the configured noise would give: held, the turns put CDde, CLq and
    # Cma near 1 sigma off on these noise-free signals (a residual of 1.4e-3 sensor
    # sigmas squared); taken linearly, every coefficient within a few thousandths.
    z = (fit.coefficients - flight.truth) / fit.sigma
    assert np.all(np.abs(z) < 0.05), z
    assert fit.cost < 1e-6
