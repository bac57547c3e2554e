"""Units a data file may use, and their factors to SI (value_SI = value * factor + offset)."""

from __future__ import annotations

import math

KNOT = 1852.0 / 3600.0
FOOT = 0.3048
G0 = 9.80665
POUND_FORCE = 4.4482216152605
SLUG = 14.593902937
INHG = 3386.389
PSF = POUND_FORCE / FOOT**2

UNITS: dict[str, dict[str, float]] = {
    "time": {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9},
    "speed": {"m/s": 1.0, "kt": KNOT, "km/h": 1.0 / 3.6, "ft/s": FOOT},
    "angle": {"rad": 1.0, "deg": math.pi / 180.0},
    "rate": {"rad/s": 1.0, "deg/s": math.pi / 180.0},
    "acceleration_angular": {"rad/s^2": 1.0, "deg/s^2": math.pi / 180.0},
    "acceleration": {"m/s^2": 1.0, "g": G0, "ft/s^2": FOOT},
    "fraction": {"1": 1.0, "%": 0.01},
    "force": {"N": 1.0, "kN": 1e3, "lbf": POUND_FORCE},
    "density": {"kg/m^3": 1.0, "slug/ft^3": SLUG / FOOT**3},
    "pressure": {"Pa": 1.0, "hPa": 100.0, "kPa": 1e3, "inHg": INHG, "psf": PSF},
    "temperature": {"K": 1.0, "degC": 1.0, "degF": 5.0 / 9.0},
    "length": {"m": 1.0, "ft": FOOT},
}
"""Unit name -> factor to SI, per kind of quantity."""
OFFSETS: dict[str, float] = {"degC": 273.15, "degF": 273.15 - 32.0 * 5.0 / 9.0}
"""Units whose zero is not SI's: value_SI = value * factor + offset."""


def choices(kind: str) -> tuple[str, ...]:
    return tuple(UNITS[kind])


def factor(kind: str, unit: str) -> float:
    return UNITS[kind][unit]


def offset(unit: str) -> float:
    """What to add after the factor (temperatures in degC or degF), else 0."""
    return OFFSETS.get(unit, 0.0)
