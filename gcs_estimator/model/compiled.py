"""The model's equations compiled with numba: the one place the compiler meets the model.

model.equations is plain Python (the reference path imports no compiler). Registering its
functions here lets compiled code (the filter kernel, the truth simulator) call them; the
source stays one.
"""

from __future__ import annotations

from numba import njit
from numba.extending import register_jitable

from gcs_estimator.arrays import FloatArray
from gcs_estimator.model import equations as eq
from gcs_estimator.model.equations import ModelArrays

for _fn in (
    eq.density,
    eq.bank,
    eq.inertial_coupling,
    eq.thrust,
    eq.aero_coefficients,
    eq._alpha_rate,
    eq._angles,
    eq.has_alpha_rate,
    eq.coefficients,
    eq.has_gust_states,
    eq.pitch_gust_index,
    eq.has_pitch_gust,
    eq.white_pitch_gust_rows,
    eq.pitch_gust_scale,
    eq.pitch_gust_rows,
    eq._gust_chain,
    eq.still_rows,
    eq.dynamics_rows,
    eq.dynamics,
    eq.sensor_placement,
    eq.turn_placement,
    eq.still_observe,
    eq.climb_rate,
    eq.observe,
    eq.air_relative,
    eq.rk4_step,
    eq.wind_slope,
    eq.observe_in_gust,
    eq.fly_step,
):
    register_jitable(_fn)


@njit(cache=True)
def _dynamics(
    x: FloatArray, u: FloatArray, m: ModelArrays
) -> tuple[FloatArray, FloatArray]:  # pragma: no cover
    return eq.dynamics(x, u, m)


@njit(cache=True)
def _observe(
    x: FloatArray, u: FloatArray, m: ModelArrays
) -> tuple[FloatArray, FloatArray]:  # pragma: no cover
    return eq.observe(x, u, m)


def dynamics(x: FloatArray, u: FloatArray, m: ModelArrays) -> tuple[FloatArray, FloatArray]:
    """Compiled equations.dynamics: f and F."""
    out: tuple[FloatArray, FloatArray] = _dynamics(x, u, m)
    return out


def observe(x: FloatArray, u: FloatArray, m: ModelArrays) -> tuple[FloatArray, FloatArray]:
    """Compiled equations.observe: h and H."""
    out: tuple[FloatArray, FloatArray] = _observe(x, u, m)
    return out
