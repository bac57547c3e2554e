"""Signal channels: one numbering for decoding, synchronising and the observation model.

Channels 0..7 are the observations y in the order of h(x) (spec: docs/model.md, eq. 13-14,
and the climb rate of "Alpha without a vane"); 8 on are the inputs. The observation
model's row i is Channel(i).
"""

from __future__ import annotations

import math
from enum import IntEnum

import numpy as np

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
    HDOT = 7
    """Climb rate h-dot [m/s], up positive (GPS or baro vertical speed; docs/model.md,
    "Alpha without a vane")."""
    ELEVATOR = 8
    """Elevator deflection [rad], positive trailing edge down (input)."""
    POWER = 9
    """Throttle [0..1] or thrust [N] (input)."""
    DENSITY = 10
    """Air density [kg/m^3] (input; where the data carry none, the airframe's)."""
    PHI = 11
    """Bank angle [rad], right wing down positive (input; missing: wings level)."""
    ROLL_RATE = 12
    """Body roll rate p [rad/s] (input; missing: 0)."""
    YAW_RATE = 13
    """Body yaw rate r [rad/s] (input; missing: 0)."""


N_INPUTS = 6
"""Inputs per frame: elevator, throttle or thrust, air density, bank angle, roll and yaw
rate (Channel.ELEVATOR .. Channel.YAW_RATE; docs/model.md "Turns")."""
TURN_INPUTS: tuple[str, ...] = ("in_phi_rad", "in_p_radps", "in_r_radps")
"""The history's columns of the turn's inputs (after elevator, power and density)."""
REQUIRED_INPUTS = 2
"""The inputs a frame cannot do without (elevator and power); density falls back."""
N_OBS = 8
"""Observation channels: Channel.V .. Channel.HDOT."""
OBS_NAMES: tuple[str, ...] = ("V", "alpha", "theta", "q", "qdot", "a_x", "a_z", "h_dot")
LEGACY_OBS = 7
"""Observation columns of a record without the climb rate (V .. a_z): such records are
widened with a missing h_dot column (pad_observations)."""
FLIGHT_STATES: tuple[str, ...] = ("V", "alpha", "theta", "q")
"""The flight states, in state order; each is also observed directly (channels 0..3)."""
N_FLIGHT = len(FLIGHT_STATES)

BANK_INPUT = Channel.PHI - Channel.ELEVATOR
"""The bank angle's column in a frame's or a model's inputs."""


def bank_of(inputs: FloatArray) -> float:
    """The bank angle [rad] among a frame's inputs (NaN where they carry none)."""
    return float(inputs[BANK_INPUT]) if len(inputs) > BANK_INPUT else math.nan


def pad_observations(y: FloatArray) -> FloatArray:
    """Observations [.. x k] widened to N_OBS columns with NaN (a record of the seven
    channels before the climb rate); unchanged when already N_OBS wide."""
    y = np.asarray(y, float)
    k = y.shape[-1]
    if k >= N_OBS:
        return y
    out = np.full((*y.shape[:-1], N_OBS), np.nan)
    out[..., :k] = y
    return out
