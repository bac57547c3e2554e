"""Thrust that is not logged (docs/decisions/0054): the propeller model's constants from a
spec sheet, the thrust's tolerance in the drag's sigma (the structure check), and `refine`
fitting the thrust with the coefficients where the flight tells them apart."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from gcs_estimator.config import AircraftConfig, ConfigError, load_config
from gcs_estimator.model import equations as eq
from gcs_estimator.model.aircraft import build_model, trim
from gcs_estimator.model.propeller import from_spec_sheet
from gcs_estimator.outputs.diagnosis import thrust_warnings, trust_warnings
from gcs_estimator.refine import refine_run
from gcs_estimator.runtime.session import run_recording
from gcs_estimator.uncertainty.metrics import IDENTIFIED
from sim.scenario import scenario_of
from sim.truth import elevator_offsets_rad, integrate, simulate

SPEC_SHEET = [
    "propulsion.prop_area_m2=0",
    "propulsion.prop_coefficient=0",
    "propulsion.motor_constant_mps=0",
    "propulsion.prop_diameter_m=0.3556",
    "propulsion.prop_pitch_m=0.1778",
    "propulsion.max_power_w=1000",
    "propulsion.max_rpm=9000",
]
"""A 14x7 propeller on a 1 kW motor turning it at 9000 rpm, at sea level (rho 1.225)."""


def test_the_spec_sheet_gives_the_constants_worked_by_hand() -> None:
    """By hand, for SPEC_SHEET:
    S  = pi 0.3556^2 / 4                          = 0.09931 m^2
    T0 = (0.6 * 1000 * sqrt(2 * 1.225 * 0.09931))^(2/3)
       = (600 * 0.49328)^(2/3) = 295.97^(2/3)     = 44.41 N
    k  = 0.1778 m * 9000 / 60 s                   = 26.67 m/s  (the pitch speed)
    C  = 2 T0 / (rho S k^2) = 88.82 / (0.12166 * 711.3) = 1.026
    Without pitch and rpm, k from the power: 3 sqrt(3) 0.75 * 1000 / (2 * 44.41) = 43.88 m/s.
    """
    c = from_spec_sheet(0.3556, 1000.0, 1.225, 0.1778, 9000.0)
    assert c.area_m2 == pytest.approx(0.09931, rel=1e-3)
    assert c.zero_thrust_mps == pytest.approx(26.67, rel=1e-4)
    assert c.coefficient == pytest.approx(1.026, rel=1e-3)
    assert (c.scale_sigma, c.speed_sigma) == (0.15, 0.15)
    assert from_spec_sheet(0.3556, 1000.0, 1.225).zero_thrust_mps == pytest.approx(43.88, rel=1e-3)
    # The model flies it: 44.41 N at full throttle standing still, none at the pitch speed.
    model = build_model(load_config("noc_uav", SPEC_SHEET))
    assert eq.thrust(0.0, 1.0, 1.225, model.k)[0] == pytest.approx(44.41, rel=1e-3)
    assert eq.thrust(26.67, 1.0, 1.225, model.k)[0] == pytest.approx(0.0, abs=1e-9)


def test_the_exact_keys_win_and_a_missing_key_is_named() -> None:
    exact = load_config("noc_uav", SPEC_SHEET[3:])  # both sets: the exact ones fly
    c = exact.propulsion.constants(1.225)
    assert (c.area_m2, c.coefficient, c.zero_thrust_mps) == (0.2027, 1.0, 80.0)
    assert (c.scale_sigma, c.speed_sigma) == (0.0, 0.0)  # exact: no tolerance
    told = load_config("noc_uav", ["propulsion.thrust_tolerance=0.2"]).propulsion
    assert told.constants(1.225).scale_sigma == 0.2
    with pytest.raises(ConfigError, match=r"\[propulsion\] motor_constant_mps: set all of"):
        load_config("noc_uav", ["propulsion.motor_constant_mps=0"])
    with pytest.raises(ConfigError, match=r"\[propulsion\] max_power_w: a number > 0 is needed"):
        load_config("noc_uav", SPEC_SHEET[:4])


THRUST_OFF = 1.2
"""The simulated aircraft's thrust against the airframe file's: 20 % more."""


def _thrust_off(config: AircraftConfig, speed: float = 1.0) -> AircraftConfig:
    """The aircraft with THRUST_OFF times the file's thrust (and `speed` times its
    zero-thrust airspeed)."""
    p = replace(config.propulsion, thrust_scale=THRUST_OFF, speed_scale=speed)
    return replace(config, propulsion=p)


def test_drag_is_not_identified_where_the_thrust_is_a_guess() -> None:
    """The NOC flight, throttle held, flown with 20 % more thrust than the airframe file
    says (its tolerance 15 %): the filters put the difference into the drag; the
    structure check's thrust part keeps CD0 from being marked identified, its sigma
    covers the error, and the report says what the flight puts the thrust at."""
    config = load_config("noc_uav", ["propulsion.thrust_tolerance=0.15"])
    fl = simulate(_thrust_off(config), seed=3)
    vehicle = run_recording(config, fl.t_s, fl.inputs, fl.measurements)
    check = vehicle.structure
    assert check is not None and not check.skipped
    assert check.tolerances["thrust"] == pytest.approx(0.15 * math.sqrt(3.0))
    cd0 = vehicle.result.names.index("CD0")
    for kind, s in vehicle.summaries.items():
        c = s.coefficients[cd0]
        assert c.identifiability != IDENTIFIED, kind
        assert abs(c.estimate - (c.truth or 0.0)) < 2.0 * c.sigma, (kind, c.estimate, c.sigma)
        # The thrust is what holds it back.
        assert check.parts["thrust"][kind][cd0] > 0.5 * c.sigma, kind
    # The elevator pulses change the airspeed enough for the likelihood to place the
    # thrust: about 20 % above the file's.
    offset, sd = check.found["thrust_scale"]
    assert abs(offset - (THRUST_OFF - 1.0)) < max(3.0 * sd, 0.02), (offset, sd)
    assert any(f"puts the thrust at ×{1.0 + offset:.3f}" in w for w in thrust_warnings(vehicle))


STEPPED = "simulation.manoeuvre.duration_s=36"
"""The throttle-step flight's length [s]: _throttle_steps' steps end at 32 s."""


def _throttle_steps(
    config: AircraftConfig, seed: int, step: float = 0.02, speed: float = 1.0
) -> tuple[np.ndarray, ...]:
    """The NOC manoeuvre with the throttle stepped up and down by `step` (0.02: about
    5 N on the NOC's propeller) for 6 s each, flown with _thrust_off's propeller in calm
    air, the sensors' noise added; the inputs as flown (no servo rounding). The config
    says how long (STEPPED: 36 s, the steps at 14 and 26 s, after the multisteps and the
    first pulse; the 60 s flight told the factors no better, decision 0062)."""
    flown = _thrust_off(config, speed)
    sim = scenario_of(flown)
    truth = np.array(flown.truth)
    model = build_model(flown, gust_states=False)
    trimmed = trim(model, truth)
    per = max(1, round(1.0 / (sim.sample_rate_hz * sim.integration_step_s)))
    dt = 1.0 / (sim.sample_rate_hz * per)
    n = int(sim.manoeuvre.duration_s * sim.sample_rate_hz) + 1
    t = np.arange(n) / sim.sample_rate_hz

    def inputs(times: np.ndarray) -> np.ndarray:
        throttle = np.full_like(times, trimmed.inputs[1])
        throttle[(times >= 14.0) & (times < 20.0)] += step
        throttle[(times >= 26.0) & (times < 32.0)] -= step
        elevator = trimmed.inputs[0] + elevator_offsets_rad(sim.manoeuvre, times)
        return np.column_stack([elevator, throttle])

    mid = (np.arange((n - 1) * per) + 0.5) * dt
    calm = np.zeros((mid.size + 1, 2))
    x0 = model.augment(trimmed.state, truth)
    _, clean = integrate(x0, inputs(mid), inputs(t), calm, dt, per, model.arrays)
    noise = np.array(sim.sensors.noise_sigma) * np.random.default_rng(seed).standard_normal(
        clean.shape
    )
    return t, inputs(t), clean + noise


def test_refine_fits_the_thrust_where_the_throttle_steps() -> None:
    config = load_config(
        "noc_uav", ["propulsion.thrust_tolerance=0.15", 'filter.structure_check="off"', STEPPED]
    )
    t, u, y = _throttle_steps(config, seed=3)
    fit = refine_run(run_recording(config, t, u, y))
    assert fit.factor_names == ("thrust",)
    (factor,), (sd,) = fit.factors, fit.factor_sigma
    assert abs(factor - THRUST_OFF) < 2.0 * sd, (factor, sd)
    assert sd < 0.5 * 0.15  # told apart from the drag: well inside its prior
    truth = np.array(config.truth)
    z = (fit.coefficients - truth) / fit.sigma
    assert np.all(np.abs(z) < 3.0), dict(zip(fit.names, z.round(2), strict=True))
    assert "thrust x1.20" in fit.factor_text()


def test_a_spec_sheet_propeller_is_fitted_within_its_tolerance() -> None:
    """A 14x7 propeller at 12000 rpm on 1 kW (SPEC_SHEET's, faster), flown with 20 % more
    thrust and a zero-thrust airspeed 5 % lower than derived, the throttle stepped by
    0.05: `refine` fits both factors with the coefficients. Throttle steps at one airspeed
    tell the thrust at that throttle, less the split between the static thrust and the
    zero-thrust airspeed: each factor and every coefficient within 3 of its sigma, and
    the report says which factor the flight did not tell from the drag."""
    config = load_config(
        "noc_uav",
        [*SPEC_SHEET[:-1], "propulsion.max_rpm=12000", 'filter.structure_check="off"', STEPPED],
    )
    t, u, y = _throttle_steps(config, seed=3, step=0.05, speed=0.95)
    vehicle = run_recording(config, t, u, y)
    fit = refine_run(vehicle)
    assert fit.factor_names == ("thrust", "zero-thrust airspeed")
    assert np.all(np.abs(fit.factors - [THRUST_OFF, 0.95]) < 3.0 * fit.factor_sigma), (
        fit.factor_text()
    )
    z = (fit.coefficients - np.array(config.truth)) / fit.sigma
    assert np.all(np.abs(z) < 3.0), dict(zip(fit.names, z.round(2), strict=True))
    loose = [
        n
        for n, s, p in zip(fit.factor_names, fit.factor_sigma, fit.factor_prior_sigma, strict=True)
        if s >= 0.5 * p
    ]
    said = [w for w in trust_warnings(vehicle, fit) if "cannot tell" in w]
    assert bool(loose) == bool(said), (loose, said)
