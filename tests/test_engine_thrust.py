"""A piston engine or turboprop from its spec sheet ([propulsion] engine; model.propeller):
the throttle sets the thrust power, the static thrust is the actuator disc's, and the
filters' Jacobian of it is right (decision 0054, amended)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gcs_estimator.config import ConfigError, load_config
from gcs_estimator.model import equations as eq
from gcs_estimator.model.aircraft import build_model, trim
from gcs_estimator.model.propeller import (
    PROPULSIVE_EFFICIENCY,
    from_engine,
    full_throttle_thrust,
    static_thrust,
)

ENGINE = [
    "propulsion.prop_area_m2=0",
    "propulsion.prop_coefficient=0",
    "propulsion.motor_constant_mps=0",
    "propulsion.engine=piston",
    "propulsion.prop_diameter_m=0.56",
    "propulsion.max_power_w=2200",
]
"""A 22 in propeller on a 2.2 kW (3 hp) piston engine, at sea level (rho 1.225)."""


def test_the_static_thrust_is_the_discs_and_the_cruise_thrust_the_power_over_the_speed() -> None:
    c = from_engine(0.56, 2200.0, 1.225)
    t0 = static_thrust(2200.0, math.pi * 0.56**2 / 4, 1.225)
    assert c.engine and c.coefficient == pytest.approx(PROPULSIVE_EFFICIENCY * 2200.0)
    assert full_throttle_thrust(c, 1.225) == pytest.approx(t0, rel=1e-12)
    model = build_model(load_config("noc_uav", ENGINE))
    assert model.k[eq.PROP_KIND] == eq.PROP_ENGINE and eq.throttle_driven(model.k)
    assert eq.thrust(0.0, 1.0, 1.225, model.k)[0] == pytest.approx(t0, rel=1e-12)
    # Far above V_s the thrust power is the throttle's share of ETA P, at any throttle:
    # the electric model's quadratic would have no thrust left at 60 % throttle here.
    for throttle in (0.4, 0.6, 1.0):
        fe, _ = eq.thrust(10.0 * c.zero_thrust_mps, throttle, 1.225, model.k)
        assert fe * 10.0 * c.zero_thrust_mps == pytest.approx(throttle * c.coefficient, rel=0.006)


def test_the_jacobian_of_the_engines_thrust_is_its_derivative() -> None:
    model = build_model(load_config("noc_uav", ENGINE))
    for v in (0.0, 5.0, 23.0, 40.0):
        for throttle in (0.2, 0.7):
            _, dv = eq.thrust(v, throttle, 1.225, model.k)
            h = 1e-4
            up = eq.thrust(v + h, throttle, 1.225, model.k)[0]
            down = eq.thrust(v - h, throttle, 1.225, model.k)[0]
            assert dv == pytest.approx((up - down) / (2 * h), rel=1e-6, abs=1e-9)


def test_the_engine_trims_at_a_part_throttle() -> None:
    """The NOC UAV with the engine trims level at its trim airspeed with the throttle
    between 0 and 1, the thrust there equal to the drag."""
    config = load_config("noc_uav", ENGINE)
    model = build_model(config)
    assert config.truth is not None
    at = trim(model, np.asarray(config.truth, float))
    assert 0.0 < at.inputs[1] < 1.0 and at.residual < 1e-6


def test_the_exact_keys_are_an_electric_motors() -> None:
    with pytest.raises(ConfigError, match="engine"):
        load_config("noc_uav", ["propulsion.engine=piston"])
