"""The propeller model's constants from a spec sheet (docs/decisions/0054).

The model (equations.thrust) is Fe = 0.5 rho S C ((k throttle)^2 - V^2): S the disc area,
C a coefficient and k the airspeed at which thrust vanishes at full throttle. A user knows
none of S C and k from a spec sheet, but the propeller's diameter D (and pitch), the
engine's or motor's maximum power P (and its top rpm). At full throttle:

- the disc area S = pi D^2 / 4;
- the static thrust T0 from momentum (actuator-disc) theory: a disc of area S making
  thrust T in still air takes the ideal power T^1.5 / sqrt(2 rho S); a real propeller
  takes more, by its figure of merit FM = ideal / shaft power (FIGURE_OF_MERIT), so
  T0 = (FM P sqrt(2 rho S))^(2/3);
- the zero-thrust airspeed k: the propeller's pitch speed, pitch x rpm / 60, where
  both are given; otherwise from the power: the model's thrust power at full throttle,
  Fe V = (T0 / k^2) (k^2 - V^2) V, peaks at V = k / sqrt(3) at 2 T0 k / (3 sqrt(3)),
  which is the shaft power times the propeller's best efficiency ETA (PROPULSIVE_EFFICIENCY):
  k = 3 sqrt(3) ETA P / (2 T0);
- C = 2 T0 / (rho S k^2), so that Fe(throttle 1, V 0) = T0.

A piston engine or a turboprop ([propulsion] engine): its throttle sets the shaft power,
not the propeller's speed, and at a part throttle the quadratic above would put the
zero-thrust airspeed below the cruise speed. Its model (equations.thrust) is the thrust
power over the airspeed, kept finite at rest: Fe = throttle ETA P / sqrt(V^2 + V_s^2),
with V_s = ETA P / T0 so that the static thrust at full throttle is T0 (the same
actuator-disc T0); PROP_COEF holds ETA P [W] and MOTOR_K V_s, so that the same two
factors (the thrust and the speed) apply.

Each is a guess within a tolerance: the static thrust's (through FM) is the prior sigma
of a thrust scale (a factor on 0.5 rho S C), the zero-thrust airspeed's that of a factor
on k. `refine` fits both with the coefficients, these sigmas its priors; the filters'
structure check replays the run with each moved (uncertainty.weighting).
"""

from __future__ import annotations

import math
from typing import NamedTuple

FIGURE_OF_MERIT = 0.6
"""A small fixed-pitch propeller's static figure of merit (ideal over shaft power):
0.5 to 0.7 for model and small UAV propellers."""
STATIC_THRUST_SIGMA = 0.15
"""The static thrust's relative 1-sigma: FM between 0.45 and 0.75 moves T0 (as FM^(2/3))
by -17 % to +16 %; the spec sheet's power (rated, or input rather than shaft) as much
again is inside it only in part: a user with a static thrust test sets the exact keys."""
PROPULSIVE_EFFICIENCY = 0.75
"""A propeller's best efficiency (thrust power over shaft power) in cruise."""
PITCH_SPEED_SIGMA = 0.15
"""The zero-thrust airspeed's relative 1-sigma where it is the pitch speed (blades'
zero-lift angle puts real propellers' zero thrust 0-30 % above the geometric pitch speed;
the model's quadratic falls off otherwise than a real propeller's thrust)."""
POWER_SPEED_SIGMA = 0.3
"""Its relative 1-sigma where it comes from the power (ETA and T0's both enter)."""
ENGINE_POWER_SIGMA = 0.15
"""An engine's thrust power's relative 1-sigma: ETA between 0.7 and 0.85 in cruise, and
the rated power a new engine's at sea level."""
ENGINE_SPEED_SIGMA = 0.2
"""V_s's relative 1-sigma (ETA P over the actuator-disc T0: both enter)."""


class PropellerConstants(NamedTuple):
    """The model's constants and their priors."""

    area_m2: float
    """S [m^2]."""
    coefficient: float
    """C [-]."""
    zero_thrust_mps: float
    """k [m/s]: the airspeed at which thrust vanishes at full throttle."""
    scale_sigma: float
    """Relative 1-sigma of the thrust (a factor on 0.5 rho S C); 0: exact."""
    speed_sigma: float
    """Relative 1-sigma of k; 0: exact."""
    engine: bool = False
    """The engine model: coefficient is the thrust power ETA P [W] at full throttle and
    zero_thrust_mps its speed scale V_s [m/s] (area unused)."""


def disc_area(diameter_m: float) -> float:
    """pi D^2 / 4 [m^2]."""
    return math.pi * diameter_m * diameter_m / 4.0


def static_thrust(power_w: float, area_m2: float, rho: float) -> float:
    """T0 = (FM P sqrt(2 rho S))^(2/3) [N] (module docstring)."""
    return float((FIGURE_OF_MERIT * power_w * math.sqrt(2.0 * rho * area_m2)) ** (2.0 / 3.0))


def from_spec_sheet(
    diameter_m: float, power_w: float, rho: float, pitch_m: float = 0.0, rpm: float = 0.0
) -> PropellerConstants:
    """S, C and k from the propeller's diameter [m], the maximum power [W] and the air
    density [kg/m^3] (with the pitch [m] and the rpm at full throttle where both are
    given: 0 where not), with their priors (module docstring)."""
    area = disc_area(diameter_m)
    t0 = static_thrust(power_w, area, rho)
    if pitch_m > 0.0 and rpm > 0.0:
        speed, speed_sigma = pitch_m * rpm / 60.0, PITCH_SPEED_SIGMA
    else:
        speed = 3.0 * math.sqrt(3.0) * PROPULSIVE_EFFICIENCY * power_w / (2.0 * t0)
        speed_sigma = POWER_SPEED_SIGMA
    coefficient = 2.0 * t0 / (rho * area * speed * speed)
    return PropellerConstants(area, coefficient, speed, STATIC_THRUST_SIGMA, speed_sigma)


def from_engine(diameter_m: float, power_w: float, rho: float) -> PropellerConstants:
    """A piston engine's or turboprop's constants (module docstring): its propeller's
    diameter [m], the engine's maximum shaft power [W], the air density [kg/m^3]."""
    area = disc_area(diameter_m)
    thrust_power = PROPULSIVE_EFFICIENCY * power_w
    speed = thrust_power / static_thrust(power_w, area, rho)
    return PropellerConstants(
        area, thrust_power, speed, ENGINE_POWER_SIGMA, ENGINE_SPEED_SIGMA, engine=True
    )


def full_throttle_thrust(c: PropellerConstants, rho: float, airspeed_mps: float = 0.0) -> float:
    """The model's thrust [N] at full throttle (equations.thrust)."""
    k = c.zero_thrust_mps
    if c.engine:
        return c.coefficient / math.sqrt(airspeed_mps * airspeed_mps + k * k)
    return 0.5 * rho * c.area_m2 * c.coefficient * (k * k - airspeed_mps * airspeed_mps)
