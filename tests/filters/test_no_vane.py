"""Alpha without a vane (decision 0049): the climb rate informs alpha where the air is
calm or the gust states carry the vertical wind, and alpha's marks say so honestly."""

from __future__ import annotations

import numpy as np

from gcs_estimator.config import load_config
from gcs_estimator.estimation.warmstart import alpha_from_climb
from gcs_estimator.model.channels import Channel
from gcs_estimator.runtime.session import run_recording
from gcs_estimator.uncertainty.metrics import NOT_IDENTIFIED, needs_alpha_level
from sim.scenario import mission
from sim.truth import simulate

FAST = ['filter.structure_check="off"']


def test_the_warm_starts_alpha_is_theta_less_the_path_angle_banked_or_not() -> None:
    """alpha from V, theta, h-dot and phi is the simulator's own alpha in calm air,
    wings level and in the mission's turns (to the climb rate's noise)."""
    config = load_config(
        "noc_uav", [*mission("none", 60.0), "simulation.sensors.noise_sigma.h_dot=0"]
    )
    flight = simulate(config, seed=3)
    y = flight.clean.copy()
    alpha = alpha_from_climb(y, flight.inputs)
    np.testing.assert_allclose(alpha, flight.states[:, 1], atol=1e-9)


def test_a_calm_flight_without_a_vane_is_within_three_sigma() -> None:
    """80 s of the calm mission with no vane: alpha comes from the climb rate; every
    coefficient of both filters within 3 sigma of the truth."""
    config = load_config("noc_uav", [*mission("none", 80.0), "simulation.vane=false", *FAST])
    flight = simulate(config, seed=5)
    assert not np.isfinite(flight.measurements[:, Channel.ALPHA]).any()
    run = run_recording(config, flight.t_s, flight.inputs, flight.measurements)
    for kind, s in run.summaries.items():
        z = np.array([c.z for c in s.coefficients], float)
        print(kind, "no vane, calm: max |z|", f"{np.max(np.abs(z)):.2f}")
        assert np.all(np.abs(z) < 3.0), z


def test_turbulence_without_a_vane_or_gust_states_leaves_alphas_coefficients_unmarked() -> None:
    """In light turbulence with white gust noise the climb rate cannot tell alpha from the
    vertical wind: the intercepts and alpha derivatives are not identified."""
    overrides = [*mission("light", 40.0), "simulation.vane=false", *FAST]
    config = load_config("noc_uav", overrides)
    flight = simulate(config, seed=6)
    run = run_recording(config, flight.t_s, flight.inputs, flight.measurements)
    for s in run.summaries.values():
        for c in s.coefficients:
            if needs_alpha_level(c.name):
                assert c.identifiability == NOT_IDENTIFIED, c
