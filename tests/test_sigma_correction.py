"""A filter's sigma widened by how far its estimates moved (sigma.movement_ratio,
docs/decisions/0008): about 1 where the model is right, large where it is not, and the
sigma to trust honest on a flight read with a known model error."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from gcs_estimator.config import load_config
from gcs_estimator.outputs.diagnosis import (
    DISAGREE_SIGMAS,
    GUST_BURSTS,
    SIGN_SIGMAS,
    trust_warnings,
)
from gcs_estimator.outputs.results_json import results_dict
from gcs_estimator.runtime.session import run_recording
from gcs_estimator.uncertainty.metrics import NOT_IDENTIFIED
from gcs_estimator.uncertainty.result import VehicleResult
from gcs_estimator.uncertainty.sigma import (
    fit_sigma,
    movement_ratio,
    movement_start,
    trusted_sigma,
)
from sim.truth import Flight, simulate

WELL_EXCITED = ("CL0", "CLa", "CLde", "Cm0", "Cma", "Cmq", "Cmde")
NO_CHECK = "filter.structure_check=off"


def _martingale(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Recursive least squares of a constant from n unit-variance samples, prior
    variance 1: the estimate and its sigma after each sample (two independent columns)."""
    k = np.arange(1, n + 1)[:, None]
    samples = rng.standard_normal((n, 2))
    estimate = np.cumsum(samples, axis=0) / (k + 1.0)
    sigma = np.sqrt(1.0 / (k + 1.0)) * np.ones((1, 2))
    return estimate, sigma


def test_movement_is_the_bartlett_weighted_autocovariance_of_the_increments() -> None:
    """The O(N) moving-sum form against the definition written out: increments d from
    frame start - 1 on, their autocovariance to lag L (a quarter of the window), weighted
    1 - k / (L + 1), over the covariance's loss."""
    rng = np.random.default_rng(5)
    n, start = 700, 300
    est = np.cumsum(rng.standard_normal((n, 3)), axis=0) * [1.0, 0.1, 3.0]
    est[:, 1] += np.sin(np.arange(n) / 15.0)  # correlated increments
    sig = np.linspace(2.0, 1.0, n)[:, None] * np.ones((1, 3))
    w = n - start
    lag = int(0.25 * w)
    d = np.diff(est[start - 1 :], axis=0)
    want = []
    for j in range(3):
        acov = [float(d[k:, j] @ d[: w - k, j]) for k in range(lag + 1)]
        weights = [1.0] + [2.0 * (1.0 - k / (lag + 1)) for k in range(1, lag + 1)]
        want.append(np.dot(weights, acov) / (sig[start - 1, j] ** 2 - sig[-1, j] ** 2))
    np.testing.assert_allclose(movement_ratio(est, sig, start), want, rtol=1e-10)


def test_an_estimate_that_moves_as_its_covariance_says_needs_no_correction() -> None:
    rng = np.random.default_rng(1)
    ratios = []
    for _ in range(20):
        est, sig = _martingale(4000, rng)
        ratios.append(movement_ratio(est, sig, 2000))
    r = np.concatenate(ratios)
    assert 0.8 < float(np.median(r)) < 1.2
    assert np.all((r > 0.2) & (r < 3.0))


def test_correlated_or_drifting_increments_are_caught() -> None:
    """The same covariance, but increments that correlate over many frames (AR(1) with
    coefficient 0.95: long-run variance 39 times the white one), or a slow drift."""
    rng = np.random.default_rng(2)
    est, sig = _martingale(4000, rng)
    white = np.diff(est[1999:], axis=0)
    coloured = np.empty_like(white)
    coloured[0] = white[0]
    for i in range(1, len(white)):
        coloured[i] = 0.95 * coloured[i - 1] + math.sqrt(1 - 0.95**2) * white[i]
    moved = est.copy()
    moved[2000:] = est[1999] + np.cumsum(coloured, axis=0)
    assert np.all(movement_ratio(moved, sig, 2000) > 10.0)
    drifting = est + np.linspace(0.0, 0.2, len(est))[:, None]
    assert np.all(movement_ratio(drifting, sig, 2000) > 10.0)


def test_too_little_to_judge_is_said_not_guessed() -> None:
    est, sig = _martingale(100, np.random.default_rng(3))
    assert np.all(np.isnan(movement_ratio(est, sig, 80)))  # 20 frames
    flat = np.ones_like(sig)
    assert np.all(np.isnan(movement_ratio(est, flat, 50)))  # the covariance lost nothing
    assert movement_start(1000, 0) == 500
    assert movement_start(1000, 700) == 701


def test_the_sigma_to_trust_is_made_of_its_parts() -> None:
    """sigma = sqrt((m sigma_P)^2 + sigma_S^2), m = sqrt(max(1, r)): a ratio below 1
    never narrows the covariance's sigma, a part not judged (NaN) is left out, and where
    neither check was made the covariance's sigma stands, with no inflation to report."""
    cov = np.array([1.0, 2.0, 3.0, 4.0])
    ratio = np.array([4.0, 0.25, np.nan, np.nan])
    alone = trusted_sigma(cov, ratio)
    np.testing.assert_array_equal(alone.sigma, [2.0, 2.0, 3.0, 4.0])
    np.testing.assert_array_equal(alone.movement_factor[:2], [2.0, 1.0])
    assert np.all(np.isnan(alone.structure)) and np.all(np.isnan(alone.inflation[2:]))
    structure = np.array([1.5, 0.0, 4.0, np.nan])
    both = trusted_sigma(cov, ratio, structure)
    np.testing.assert_allclose(both.sigma, [2.5, 2.0, 5.0, 4.0], rtol=1e-15)
    parts = both.parts(2)
    assert (parts.covariance, parts.structure, parts.inflation) == (3.0, 4.0, 5.0 / 3.0)
    assert math.isnan(parts.movement_factor)


@pytest.fixture(scope="module")
def lagged_servo_flight() -> Flight:
    """A NOC flight whose elevator lags its command by 50 ms, read by filters told that
    the inputs hold between samples: a model error the filters cannot see."""
    flying = load_config("noc_uav", ["simulation.actuator_time_constant_s=0.05"])
    return simulate(flying, seed=1)


def test_a_fit_is_trusted_no_further_than_the_filter_it_started_from() -> None:
    """The whole-record fit's sigma is its own (Morelli-Klein with the structure, the
    difference from the filter) or the filter's sigma to trust, whichever is larger;
    where the filter has none (NaN) the fit's own stands (decision 0057)."""
    rng = np.random.default_rng(11)
    crb = rng.uniform(0.1, 1.0, 6)
    mk_var = (crb * rng.uniform(1.0, 3.0, 6)) ** 2
    structure = rng.uniform(0.0, 2.0, 6)
    difference = rng.uniform(0.0, 1.0, 6)
    own = fit_sigma(crb, mk_var, structure, difference=difference)
    filt = own.sigma * np.array([0.5, 2.0, 0.9, 3.0, math.nan, 1.0])
    floored = fit_sigma(crb, mk_var, structure, difference=difference, filter_trusted=filt)
    assert own.filter_trusted is None
    larger = np.fmax(own.sigma, filt)
    np.testing.assert_array_equal(floored.sigma, larger)
    assert floored.sigma[4] == own.sigma[4] and floored.sigma[3] == filt[3]
    # The fit's own parts are left as they were: only the sigma to trust is floored.
    np.testing.assert_array_equal(floored.within_fit, own.within_fit)


def test_a_model_error_the_filter_cannot_see_is_in_the_sigma_to_trust(
    lagged_servo_flight: Flight,
) -> None:
    flight = lagged_servo_flight
    told = load_config("noc_uav", ['data.input_hold="previous"'])
    vehicle = run_recording(told, flight.t_s, flight.inputs, flight.measurements)
    for kind, s in vehicle.summaries.items():
        well = [c for c in s.coefficients if c.name in WELL_EXCITED]
        z = np.array([(c.estimate - (c.truth or 0.0)) / c.sigma_parts.covariance for c in well])
        zc = np.array([c.z for c in well], float)
        assert np.mean(z**2) > 50.0, kind  # the covariance claims far too much
        assert np.mean(zc**2) < 3.0, (kind, zc.round(1))
        assert np.all(np.abs(zc) < 3.0), (kind, zc.round(1))
    warnings = trust_warnings(vehicle)
    assert any("moved more than the covariance allows" in w for w in warnings), warnings
    est = results_dict(vehicle)["filters"]["IEKF"]["estimates"]["Cma"]
    parts = est["sigma_parts"]
    assert est["sigma"] == pytest.approx(parts["covariance"] * parts["inflation"])
    assert parts["inflation"] > 2.0


def test_where_the_model_is_right_the_correction_stays_near_one() -> None:
    config = load_config("noc_uav")
    flight = simulate(config, seed=2)
    vehicle = run_recording(config, flight.t_s, flight.inputs, flight.measurements)
    check = vehicle.structure
    assert check is not None and not check.skipped
    for kind, s in vehicle.summaries.items():
        well = [i for i, c in enumerate(s.coefficients) if c.name in WELL_EXCITED]
        factors = np.array([s.coefficients[i].sigma_parts.inflation for i in well])
        assert np.all(np.isfinite(factors)) and np.all(factors >= 1.0)
        # The corrections for what the model misses (the movement, the channels'
        # weights) stay near one; the parts for what the data cannot decide (timing,
        # sensor placement: decision 0047) are priors, not model errors.
        cov = np.array([s.coefficients[i].sigma_parts.covariance for i in well])
        moved = np.array([s.coefficients[i].sigma_parts.movement_factor for i in well])
        own = np.hypot(moved * cov, check.parts["weights"][kind][well]) / cov
        assert float(np.median(own)) < 1.3, (kind, own.round(2))
        assert not any("moved more" in w for w in trust_warnings(vehicle)), kind


def test_a_turbulence_level_switched_on_and_off_by_what_the_model_misses_is_named() -> None:
    """Calm air, but the aircraft has a strong alpha-rate damping term the structure lacks.
    Its innovations come in the manoeuvres, where the level is not estimated
    (filter.turbulence.settle_s), so it stays off. Estimated on every frame (settle_s = 0)
    they read as bursts of turbulence, and the warnings say so and what to compare. The
    same structure on a flight it fits, calm or in steady light turbulence, raises
    nothing. The turbulence level's track alone: no structure check, which widens only
    the sigmas and runs after the pass (decision 0066)."""
    flown = load_config(
        "noc_uav",
        ['coefficients.Cm=["1", "alpha", "qhat", "elevator", "adhat"]', "truth.Cmadot=-150"],
    )
    flight = simulate(flown, seed=1)
    config = load_config("noc_uav", [NO_CHECK])
    vehicle = run_recording(config, flight.t_s, flight.inputs, flight.measurements)
    for kind, s in vehicle.summaries.items():
        assert s.gust_on_share < GUST_BURSTS[0], (kind, s.gust_on_share)
    assert not any("on and off" in w for w in trust_warnings(vehicle))
    every_frame = load_config("noc_uav", ["filter.turbulence.settle_s=0", NO_CHECK])
    vehicle = run_recording(every_frame, flight.t_s, flight.inputs, flight.measurements)
    for kind, s in vehicle.summaries.items():
        assert GUST_BURSTS[0] < s.gust_on_share < GUST_BURSTS[1], (kind, s.gust_on_share)
    named = [w for w in trust_warnings(vehicle) if "on and off" in w]
    assert len(named) == 2 and all("adaptive = false" in w for w in named), named
    for preset in ("none", "light"):
        air = load_config("noc_uav", [f'simulation.turbulence.preset="{preset}"', NO_CHECK])
        fitted = simulate(air, seed=1)
        run = run_recording(air, fitted.t_s, fitted.inputs, fitted.measurements)
        assert not any("on and off" in w for w in trust_warnings(run)), preset


def test_filters_that_end_apart_are_named_and_filters_that_agree_are_not() -> None:
    """Both filters read the same frames, so where the data fix a coefficient they end
    close together, and a NOC flight raises nothing. Moved apart by more than
    DISAGREE_SIGMAS of the larger sigma (as an IEKF that follows a ridge of the
    fit ends), a coefficient is named with both estimates; by less, it is not. A
    coefficient the data do not identify is left to the table."""
    config = load_config("noc_uav")
    flight = simulate(config, seed=3)
    vehicle = run_recording(config, flight.t_s, flight.inputs, flight.measurements)
    assert not any("end more than" in w for w in trust_warnings(vehicle))

    def moved(name: str, sigmas: float, mark: str | None = None) -> VehicleResult:
        iekf = vehicle.summaries["IEKF"]
        ekf = {c.name: c for c in vehicle.summaries["EKF"].coefficients}
        coefficients = tuple(
            c
            if c.name != name
            else replace(
                c,
                estimate=ekf[name].estimate + sigmas * max(c.sigma, ekf[name].sigma),
                identifiability=mark or c.identifiability,
            )
            for c in iekf.coefficients
        )
        summaries = {**vehicle.summaries, "IEKF": replace(iekf, coefficients=coefficients)}
        return replace(vehicle, summaries=summaries)

    def apart(v: VehicleResult) -> list[str]:
        return [w for w in trust_warnings(v) if "end more than" in w]

    named = apart(moved("Cma", 1.1 * DISAGREE_SIGMAS))
    assert len(named) == 1 and "Cma" in named[0] and "Cmq" not in named[0], named
    assert not apart(moved("Cma", 0.9 * DISAGREE_SIGMAS))
    assert not apart(moved("CDa", 10 * DISAGREE_SIGMAS, NOT_IDENTIFIED))


def test_a_channel_the_data_never_hold_is_named() -> None:
    """A flight without any alpha (a CSV column left empty, a vehicle without an AOA
    message): the warnings say so by name, beside what the filters could not identify;
    without qdot, which a flight may lack (the README's CSV layout), nothing is said."""
    config = load_config("noc_uav", ["simulation.manoeuvre.duration_s=12"])
    flight = simulate(config, seed=4)
    said = {}
    for channel in (1, 4):  # alpha, qdot
        y = flight.measurements.copy()
        y[:, channel] = np.nan
        run = run_recording(config, flight.t_s, flight.inputs, y)
        said[channel] = [w for w in trust_warnings(run) if "in these data at all" in w]
        assert not any("elevator did not move" in w for w in trust_warnings(run))
    assert len(said[1]) == 1 and said[1][0].startswith("no alpha in these data at all")
    assert "weak at best" in said[1][0] and "climb rate" not in said[1][0]
    assert said[4] == []
    # With a climb rate, alpha comes from the flight path: in calm air only (0049).
    climbing = load_config(
        "noc_uav", ["simulation.manoeuvre.duration_s=12", "simulation.climb_rate=true"]
    )
    flight = simulate(climbing, seed=4)
    y = flight.measurements.copy()
    y[:, 1] = np.nan
    run = run_recording(climbing, flight.t_s, flight.inputs, y)
    (line,) = [w for w in trust_warnings(run) if "in these data at all" in w]
    assert line.startswith("no alpha") and "climb rate" in line and "calm air only" in line


def test_an_elevator_that_never_moves_is_named() -> None:
    """The aircraft manoeuvres but the elevator read is flat (the wrong servo channel or
    column): the moment coefficients cannot be told apart, and the warnings say where to
    look rather than only that the noise model does not fit."""
    config = load_config("noc_uav", ["simulation.manoeuvre.duration_s=12"])
    flight = simulate(config, seed=4)
    u = flight.inputs.copy()
    u[:, 0] = u[0, 0]
    run = run_recording(config, flight.t_s, u, flight.measurements)
    still = [w for w in trust_warnings(run) if "elevator did not move" in w]
    assert len(still) == 1 and "[link] elevator_servo" in still[0]


def test_an_elevator_read_with_its_sign_reversed_is_named() -> None:
    """The elevator read with its sign reversed (a servo mounted the other way, a
    calibration's sign): Cmde comes out positive and CLde negative, which no conventional
    aircraft has; the warnings name Cmde, far from zero in every filter, and CLde wherever
    its sigma shown puts it SIGN_SIGMAS from zero (the structure check's parts may not),
    and the likely cause. The same flight read right raises no such warning."""
    config = load_config("noc_uav", ["simulation.manoeuvre.duration_s=12"])
    flight = simulate(config, seed=4)
    named = {}
    runs = {}
    for sign in (1.0, -1.0):
        u = flight.inputs.copy()
        u[:, 0] *= sign
        runs[sign] = run = run_recording(config, flight.t_s, u, flight.measurements)
        named[sign] = [w for w in trust_warnings(run) if "of the sign no conventional" in w]
    assert named[1.0] == []
    expected = {"EKF: Cmde", "IEKF: Cmde"}
    for kind, summary in runs[-1.0].summaries.items():
        clde = next(c for c in summary.coefficients if c.name == "CLde")
        assert clde.estimate < 0, (kind, clde.estimate)
        if -clde.estimate > SIGN_SIGMAS * clde.sigma:
            expected.add(f"{kind}: CLde")
    assert {w.split(" came out")[0] for w in named[-1.0]} == expected
    assert all("sign reversed" in w for w in named[-1.0])


def test_a_thrust_model_short_of_the_aircrafts_is_named() -> None:
    """The throttle read at half its value (a PWM range or a propeller guess that gives
    the model half the thrust): the drag left to explain the acceleration comes out
    negative, far from zero, and the warnings name CD0 in both filters with the thrust
    model as the likely cause. The same flight read right names nothing (the test above)."""
    config = load_config("noc_uav", ["simulation.manoeuvre.duration_s=12"])
    flight = simulate(config, seed=4)
    u = flight.inputs.copy()
    u[:, 1] *= 0.5
    run = run_recording(config, flight.t_s, u, flight.measurements)
    named = [w for w in trust_warnings(run) if "of the sign no conventional" in w]
    assert {w.split(" came out")[0] for w in named} == {"EKF: CD0", "IEKF: CD0"}, named
    assert all("thrust falls short" in w for w in named)
