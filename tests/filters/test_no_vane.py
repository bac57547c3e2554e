"""Alpha without a vane (decision 0049): the climb rate informs alpha where the air is
calm or the gust states carry the vertical wind, and alpha's marks say so honestly."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from gcs_estimator.config import load_config
from gcs_estimator.estimation.estimator import FilterKind
from gcs_estimator.estimation.filters import core
from gcs_estimator.estimation.results import FilterResult
from gcs_estimator.estimation.warmstart import alpha_from_climb
from gcs_estimator.model.aircraft import build_model
from gcs_estimator.model.channels import Channel
from gcs_estimator.runtime.session import run_recording
from gcs_estimator.uncertainty.metrics import (
    CALM_FOR_CLIMB_MPS,
    NOT_IDENTIFIED,
    moves_with_alpha,
    needs_alpha_level,
    summarise,
    told_alpha_level,
    with_alpha_confound,
)
from sim.scenario import mission, scenario_of
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


def test_the_climb_rate_carries_the_vertical_wind_where_turbulence_is_white_noise() -> None:
    """Decision 0060: with white gust noise the climb rate's R gains sigma_w^2 2 L_w / V
    per frame interval, and only once a gust level is applied; the gust states carry
    the vertical wind themselves (nothing added)."""
    config = load_config("noc_uav")
    tuning = core.tuning_of(config, build_model(config), "EKF")
    turb = config.filter.turbulence
    per_var = 2.0 * turb.length_w_m / config.airframe.trim_airspeed_mps
    np.testing.assert_array_equal(core.measurement_noise(tuning, 0.0, 0.02), tuning.R)
    R = core.measurement_noise(tuning, 0.6, 0.02)
    added = np.diag(R - tuning.R)
    assert added[Channel.HDOT] == np.float64(0.6 * per_var / 0.02)
    assert np.count_nonzero(added) == 1
    states = load_config("noc_uav", ['filter.turbulence.model="states"'])
    tuned = core.tuning_of(states, build_model(states), "EKF")
    np.testing.assert_array_equal(core.measurement_noise(tuned, 0.6, 0.02), tuned.R)


def test_an_uninformed_alpha_adds_the_prior_to_its_coefficients_structure_sigma() -> None:
    names = ("CD0", "CDde", "CLa", "Cmq")
    prior = np.array([10.0, 10.0, 10.0, 100.0])
    out = with_alpha_confound(names, prior, np.array([3.0, 2.0, np.nan, 5.0]))
    np.testing.assert_allclose(out, [np.hypot(3.0, 10.0), 2.0, 10.0, np.hypot(5.0, 100.0)])
    np.testing.assert_allclose(with_alpha_confound(names, prior, None), [10.0, 0.0, 10.0, 100.0])


def test_turbulence_without_a_vane_or_gust_states_leaves_alphas_coefficients_unmarked() -> None:
    """In light turbulence with white gust noise the climb rate cannot tell alpha from the
    vertical wind: the intercepts and alpha derivatives are not identified, and their
    sigma holds it (no smaller than the prior's: decision 0060)."""
    overrides = [*mission("light", 40.0), "simulation.vane=false", *FAST]
    config = load_config("noc_uav", overrides)
    flight = simulate(config, seed=6)
    run = run_recording(config, flight.t_s, flight.inputs, flight.measurements)
    names = run.result.names
    prior = config.filter.initial_sigma.coefficients
    for s in run.summaries.values():
        for c in s.coefficients:
            if needs_alpha_level(c.name):
                assert c.identifiability == NOT_IDENTIFIED, c
            if moves_with_alpha(c.name):
                assert c.sigma >= prior[names.index(c.name)], c


def test_process_noise_on_alpha_counts_as_the_vertical_wind_it_may_be() -> None:
    """The same turbulent flight with the filters' gust level off and the process noise on
    alpha set to what the gusts are worth (as a filter-error fit's advice sets it:
    decision 0085): the innovations no longer read as turbulence, but the process noise
    tells of alpha moving beyond the model, which the climb rate cannot tell from a
    vertical wind; the intercepts and alpha derivatives stay not identified."""
    light = load_config("noc_uav", mission("light", 40.0))
    level = scenario_of(light).turbulence.sigma_w
    unit = light.filter.turbulence.unit(light.airframe.trim_airspeed_mps)[1]
    overrides = [
        *mission("light", 40.0),
        "simulation.vane=false",
        *FAST,
        "filter.turbulence.adaptive=false",
        f"filter.process_noise.alpha={level**2 * unit}",
    ]
    config = load_config("noc_uav", overrides)
    assert told_alpha_level(config) == pytest.approx(level)
    assert told_alpha_level(load_config("noc_uav")) < 0.01 * CALM_FOR_CLIMB_MPS
    flight = simulate(config, seed=6)
    run = run_recording(config, flight.t_s, flight.inputs, flight.measurements)
    names = run.result.names
    prior = config.filter.initial_sigma.coefficients
    for s in run.summaries.values():
        assert s.gust_pass_sigma == 0.0 or not np.isfinite(s.gust_pass_sigma), s.gust_pass_sigma
        for c in s.coefficients:
            if needs_alpha_level(c.name):
                assert c.identifiability == NOT_IDENTIFIED, c
            if moves_with_alpha(c.name):
                assert c.sigma >= prior[names.index(c.name)], c


def test_air_one_filter_reads_moving_leaves_both_filters_alpha_coefficients_unmarked() -> None:
    """The two filters fly one air: where one reads it moving (its pass's gust level above
    CALM_FOR_CLIMB_MPS), the other's alpha is no better told from the vertical wind, even
    if that filter read the air calm because its alpha took the wind in. The turbulent
    flight's summaries made again with the IEKF's gust reading zeroed: both filters'
    alpha coefficients keep the prior in their sigma; with both readings zeroed, the
    IEKF's would not (the reading is what decides)."""
    overrides = [*mission("light", 40.0), "simulation.vane=false", *FAST]
    config = load_config("noc_uav", overrides)
    flight = simulate(config, seed=6)
    run = run_recording(config, flight.t_s, flight.inputs, flight.measurements)
    result = run.result

    def calm(kind: FilterKind) -> FilterResult:
        fr = result.filters[kind]
        assert fr.track is not None
        track = dataclasses.replace(fr.track, gust_pass_sigma=0.0 * fr.track.gust_pass_sigma)
        return fr._replace(track=track)

    moving = result.filters["EKF"].track
    assert moving is not None and moving.gust_pass_sigma[-1] > CALM_FOR_CLIMB_MPS
    names = result.names
    prior = config.filter.initial_sigma.coefficients
    one_calm = result._replace(filters={**result.filters, "IEKF": calm("IEKF")})
    for s in summarise(one_calm, run.truth).values():
        for c in s.coefficients:
            if needs_alpha_level(c.name):
                assert c.identifiability == NOT_IDENTIFIED, (s.kind, c)
            if moves_with_alpha(c.name):
                assert c.sigma >= prior[names.index(c.name)], (s.kind, c)
    both_calm = result._replace(filters={k: calm(k) for k in result.filters})
    iekf = summarise(both_calm, run.truth)["IEKF"]
    assert any(
        c.sigma < prior[names.index(c.name)] for c in iekf.coefficients if moves_with_alpha(c.name)
    )
