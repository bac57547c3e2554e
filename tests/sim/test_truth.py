"""The truth simulator: trim point, manoeuvre, sensor statistics, turbulence, seeding."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.model.channels import Channel
from sim.scenario import Manoeuvre, Turbulence, scenario_of
from sim.truth import _GustModel, elevator_offset_rad, simulate


def test_trim_matches_the_spec(noc_config: AircraftConfig) -> None:
    """docs/model.md: V = 24 m/s, alpha = 2.97 deg, elevator 0.42 deg, throttle 0.316,
    thrust 7.7 N (quoted to the digits given there)."""
    flight = simulate(noc_config, seed=1)
    trim = flight.trim
    assert trim.residual < 1e-9
    assert trim.state[0] == pytest.approx(24.0)
    assert math.degrees(trim.state[1]) == pytest.approx(2.97, abs=0.005)
    assert math.degrees(trim.inputs[0]) == pytest.approx(0.42, abs=0.005)
    assert trim.inputs[1] == pytest.approx(0.316, abs=0.0005)
    rho, s_prop = 1.225, 0.2027
    thrust = 0.5 * rho * s_prop * ((80 * trim.inputs[1]) ** 2 - 24.0**2)
    assert thrust == pytest.approx(7.7, abs=0.05)


def test_stays_trimmed_before_the_manoeuvre(noc_config: AircraftConfig) -> None:
    flight = simulate(noc_config, seed=1)
    before = flight.t_s < 2.0
    assert np.ptp(flight.states[before], axis=0).max() < 1e-9


def test_multistep_and_pulses() -> None:
    m = Manoeuvre()
    a = math.radians(3.0)
    expect = {
        1.9: 0.0,
        2.0: a,
        2.59: a,
        2.6: -a,
        2.99: -a,
        3.0: a,
        3.2: -a,
        3.4: 0.0,
        6.1: a,
        12.5: -a,
        14.1: 0.0,
        31.0: a,
        33.0: 0.0,
    }
    for t, v in expect.items():
        assert elevator_offset_rad(m, t) == pytest.approx(v), t


def test_sensor_noise_has_the_configured_sigma(noc_config: AircraftConfig) -> None:
    # with the climb-rate sensor (h_dot); the seven other channels' noise as without it
    without = simulate(noc_config, seed=3)
    assert np.isnan(without.measurements[:, Channel.HDOT]).all()
    flight = simulate(load_config("noc_uav", ["simulation.climb_rate=true"]), seed=3)
    np.testing.assert_array_equal(
        flight.measurements[:, : Channel.HDOT], without.measurements[:, : Channel.HDOT]
    )
    err = flight.measurements - flight.clean
    sigma = np.array(scenario_of(noc_config).sensors.noise_sigma)
    # 3001 samples: the sample sigma is within ~2.6 % of the true one at 3 standard errors.
    np.testing.assert_allclose(err.std(axis=0), sigma, rtol=0.04)
    # Zero mean: within 4 standard errors per channel.
    assert np.all(np.abs(err.mean(axis=0)) < 4 * sigma / math.sqrt(len(err)))


def test_bias_and_quantisation(noc_config: AircraftConfig) -> None:
    scenario = scenario_of(noc_config)
    sensors = replace(
        scenario.sensors,
        noise_sigma=(0.0,) * 7,
        bias=(0.0, math.radians(1.0), 0.0, 0.01, 0.0, 0.0, 0.5),
        quantum=(0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    )
    flight = simulate(noc_config, seed=1, scenario=replace(scenario, sensors=sensors))
    np.testing.assert_allclose(flight.measurements[:, 1] - flight.clean[:, 1], math.radians(1.0))
    np.testing.assert_allclose(flight.measurements[:, 6] - flight.clean[:, 6], 0.5)
    v = flight.measurements[:, 0]
    np.testing.assert_allclose(v / 0.1, np.round(v / 0.1), atol=1e-9)


def test_turbulence_moves_the_aircraft_with_the_set_intensity(noc_config: AircraftConfig) -> None:
    turb = Turbulence(sigma_u_mps=1.0, sigma_w_mps=0.8, length_u_m=200.0, length_w_m=50.0)
    calm = simulate(noc_config, seed=5)
    rough = simulate(noc_config, seed=5, scenario=replace(scenario_of(noc_config), turbulence=turb))
    before = calm.t_s < 2.0  # trimmed: any motion here is the gusts
    assert np.ptp(calm.states[before, 1]) < 1e-9
    # Alpha seen by the vane carries w_g/V: tenths of a degree to degrees at 0.8 m/s.
    assert 0.2 < math.degrees(np.std(rough.states[before, 1])) < 5.0


def test_pitch_gust_is_the_lagged_rate_of_the_vertical_gust() -> None:
    """With a wing span b the simulator's pitch gust is MIL-F-8785C's
    q_g = (s / V) / (1 + (4 b / (pi V)) s) w_g: here w_g's rate over V, differenced from
    the samples and lagged by 4 b / (pi V), against the q_g the model flew."""
    turb = Turbulence(sigma_u_mps=1.0, sigma_w_mps=0.8, length_u_m=200.0, length_w_m=50.0)
    V, span, dt = 24.0, 2.6, 0.002
    gusts = _GustModel(turb, V, np.random.default_rng(3), span)
    g = np.empty((20000, 3))
    for i in range(len(g)):
        g[i] = gusts.gust()
        gusts.step(dt)
    tau = 4.0 * span / (math.pi * V)
    lagged = np.zeros(len(g))
    rate = np.diff(g[:, 1]) / dt / V
    for i in range(1, len(g)):
        lagged[i] = lagged[i - 1] + (rate[i - 1] - lagged[i - 1]) * dt / tau
    gain = float(lagged @ g[:, 2] / (lagged @ lagged))
    assert np.corrcoef(lagged, g[:, 2])[0, 1] > 0.99
    assert gain == pytest.approx(1.0, abs=0.02)
    assert abs(g[0, 2]) < 1e-12  # it starts at rest
    # Without a span there is no pitch gust.
    assert _GustModel(turb, V, np.random.default_rng(3)).gust().shape == (2,)


def test_seeded_and_reproducible(noc_config: AircraftConfig) -> None:
    a = simulate(noc_config, seed=11)
    b = simulate(noc_config, seed=11)
    c = simulate(noc_config, seed=12)
    np.testing.assert_array_equal(a.measurements, b.measurements)
    assert not np.array_equal(a.measurements, c.measurements)


def test_servo_commands_are_whole_microseconds(noc_config: AircraftConfig) -> None:
    """The aircraft flies what its servos get, whole microseconds of PWM, so the inputs
    the station decodes from SERVO_OUTPUT_RAW are exactly the ones flown."""
    flight = simulate(noc_config, seed=1)
    link = noc_config.link
    elev_us = link.elevator_pwm_center_us + flight.inputs[:, 0] * link.elevator_us_per_rad
    span = link.throttle_pwm_max_us - link.throttle_pwm_min_us
    thr_us = link.throttle_pwm_min_us + flight.inputs[:, 1] * span
    np.testing.assert_allclose(elev_us, np.round(elev_us), atol=1e-9)
    np.testing.assert_allclose(thr_us, np.round(thr_us), atol=1e-9)
    # The manoeuvre still reaches its amplitude (3 deg = 50 us, not rounded away).
    assert np.ptp(elev_us) >= 2 * 50.0 - 1.0
