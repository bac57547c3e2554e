"""The International Standard Atmosphere (ISO 2533) up to 20 km, and air density from
what flight data carry: static pressure, pressure altitude, outside air temperature.

Air density changes over a flight (a transport's phugoid alone moves it by a few per
cent), and the model's forces scale with it; the estimator takes it per sample where the
data have it (docs/model.md, "Air density").
"""

from __future__ import annotations

import numpy as np

from gcs_estimator.arrays import FloatArray

R_AIR = 287.05287
"""Specific gas constant of dry air [J/(kg K)]."""
G0 = 9.80665
T0, P0 = 288.15, 101325.0
"""Sea-level standard temperature [K] and pressure [Pa]."""
LAPSE = 0.0065
"""Temperature lapse rate of the troposphere [K/m]."""
H_TROPOPAUSE = 11000.0
T_TROPOPAUSE = T0 - LAPSE * H_TROPOPAUSE
P_TROPOPAUSE = P0 * (T_TROPOPAUSE / T0) ** (G0 / (LAPSE * R_AIR))


def pressure(altitude_m: FloatArray | float) -> FloatArray:
    """Static pressure [Pa] at a pressure altitude [m] (geopotential)."""
    h = np.asarray(altitude_m, float)
    tropo = P0 * (1.0 - LAPSE * h / T0) ** (G0 / (LAPSE * R_AIR))
    strato = P_TROPOPAUSE * np.exp(-G0 * (h - H_TROPOPAUSE) / (R_AIR * T_TROPOPAUSE))
    return np.asarray(np.where(h <= H_TROPOPAUSE, tropo, strato))


def temperature(pressure_pa: FloatArray | float) -> FloatArray:
    """Standard temperature [K] at a static pressure [Pa]."""
    p = np.asarray(pressure_pa, float)
    tropo = T0 * (p / P0) ** (LAPSE * R_AIR / G0)
    return np.asarray(np.where(p >= P_TROPOPAUSE, tropo, T_TROPOPAUSE))


def density(
    pressure_pa: FloatArray | float, temperature_k: FloatArray | float | None = None
) -> FloatArray:
    """Air density [kg/m^3] from static pressure [Pa] and outside air temperature [K]; the
    standard temperature at that pressure where the temperature is not known (NaN)."""
    p = np.asarray(pressure_pa, float)
    t = temperature(p) if temperature_k is None else np.asarray(temperature_k, float)
    t = np.where(np.isfinite(t), t, temperature(p))
    return np.asarray(p / (R_AIR * t))
