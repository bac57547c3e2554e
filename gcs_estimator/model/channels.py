"""Signal channels: one numbering for decoding, synchronising and the observation model.

Channels 0..6 are the observations y in the order of h(x) (spec: docs/model.md, eq. 13-14);
7 on are the inputs. The observation model's row i is Channel(i).
"""

from __future__ import annotations

import math
from enum import IntEnum

from gcs_estimator.arrays import FloatArray


class Channel(IntEnum):
    V = 0
    """True airspeed [m/s]."""
    ALPHA = 1
    """Angle of attack [rad]."""
    THETA = 2
    """Pitch angle [rad]."""
    Q = 3
    """Pitch rate [rad/s]."""
    QDOT = 4
    """Pitch acceleration [rad/s^2]."""
    AX = 5
    """Body-axis specific force, forward [m/s^2]."""
    AZ = 6
    """Body-axis specific force, down [m/s^2]."""
    ELEVATOR = 7
    """Elevator deflection [rad], positive trailing edge down (input)."""
    POWER = 8
    """Throttle [0..1] or thrust [N] (input)."""
    DENSITY = 9
    """Air density [kg/m^3] (input; where the data carry none, the airframe's)."""
    PHI = 10
    """Bank angle [rad], right wing down positive (input; missing: wings level)."""
    ROLL_RATE = 11
    """Body roll rate p [rad/s] (input; missing: 0)."""
    YAW_RATE = 12
    """Body yaw rate r [rad/s] (input; missing: 0)."""


N_INPUTS = 6
"""Inputs per frame: elevator, throttle or thrust, air density, bank angle, roll and yaw
rate (Channel.ELEVATOR .. Channel.YAW_RATE; docs/model.md "Turns")."""
TURN_INPUTS: tuple[str, ...] = ("in_phi_rad", "in_p_radps", "in_r_radps")
"""The history's columns of the turn's inputs (after elevator, power and density)."""
REQUIRED_INPUTS = 2
"""The inputs a frame cannot do without (elevator and power); density falls back."""
N_OBS = 7
"""Observation channels: Channel.V .. Channel.AZ."""
OBS_NAMES: tuple[str, ...] = ("V", "alpha", "theta", "q", "qdot", "a_x", "a_z")
FLIGHT_STATES: tuple[str, ...] = ("V", "alpha", "theta", "q")
"""The flight states, in state order; each is also observed directly (channels 0..3)."""
N_FLIGHT = len(FLIGHT_STATES)

BANK_INPUT = Channel.PHI - Channel.ELEVATOR
"""The bank angle's column in a frame's or a model's inputs."""


def bank_of(inputs: FloatArray) -> float:
    """The bank angle [rad] among a frame's inputs (NaN where they carry none)."""
    return float(inputs[BANK_INPUT]) if len(inputs) > BANK_INPUT else math.nan
