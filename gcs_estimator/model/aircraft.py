"""The configured aircraft as arrays the equations and kernels take, plus trimming."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import AXES, REGRESSORS, AircraftConfig
from gcs_estimator.model import equations as eq
from gcs_estimator.model.channels import FLIGHT_STATES, N_INPUTS, REQUIRED_INPUTS
from gcs_estimator.model.equations import ModelArrays
from gcs_estimator.model.state import StateLayout

STANDARD_GRAVITY_MPS2 = 9.80665
"""g [m/s^2] (ISO 80000-3): the aircraft of this tool fly low enough for it to hold."""

FLIGHT, GUSTS, COEFFICIENTS, BIASES = "flight", "gusts", "coefficients", "biases"
"""Names of the augmented state's blocks."""
GUST_STATES = ("u_g", "w_g")
"""The gust states' names (filter.turbulence.model = "states")."""
PITCH_GUST_STATE = "p_g"
"""The pitch gust's state, where the airframe gives a wing span: after the gust states
(equations.pitch_gust_rows), or alone where turbulence is white process noise
(equations.white_pitch_gust_rows)."""


@dataclass(frozen=True)
class Model:
    """One aircraft: its augmented-state layout and the arrays the equations take."""

    layout: StateLayout
    arrays: ModelArrays
    names: tuple[str, ...]
    """Coefficient names, in state order."""

    @property
    def k(self) -> FloatArray:
        return self.arrays.k

    @property
    def n_coefficients(self) -> int:
        return len(self.names)

    @property
    def n(self) -> int:
        """Augmented state dimension."""
        return self.layout.n

    @property
    def coefficients(self) -> slice:
        """Where the coefficients sit in the augmented state."""
        return self.layout.block(COEFFICIENTS).slice

    @property
    def biases(self) -> slice:
        """Where the estimated sensor biases sit in the augmented state (may be empty)."""
        return self.layout.block(BIASES).slice

    @property
    def bias_names(self) -> tuple[str, ...]:
        return self.layout.block(BIASES).names

    @property
    def gusts(self) -> slice:
        """Where the gust states [u_g, w_g] and the pitch gust's p_g sit ([p_g] alone when
        turbulence is process noise; empty without a wing span then)."""
        for b in self.layout.blocks:
            if b.name == GUSTS:
                return b.slice
        return slice(0, 0)

    @property
    def has_gust_states(self) -> bool:
        return eq.has_gust_states(self.arrays)

    @property
    def flight(self) -> slice:
        """Where the flight states [V, alpha, theta, q] sit in the augmented state."""
        return self.layout.block(FLIGHT).slice

    def f(self, x: FloatArray, u: FloatArray) -> tuple[FloatArray, FloatArray]:
        return eq.dynamics(x, u, self.arrays)

    def h(self, x: FloatArray, u: FloatArray) -> tuple[FloatArray, FloatArray]:
        return eq.observe(x, u, self.arrays)

    def inputs(self, u: FloatArray | Sequence[float]) -> FloatArray:
        """u as the equations take it: [elevator, throttle or thrust, air density, phi, p,
        r], the density being the airframe's wherever u has none (absent, NaN or not
        positive), the bank and the roll and yaw rates 0 (wings level) where absent or NaN.
        (A frame's few values as Python floats: the same values as inputs_of's row, without
        an array operation per part.)"""
        values: list[float] = np.asarray(u, float).reshape(-1).tolist()
        if len(values) < REQUIRED_INPUTS:
            row: FloatArray = self.inputs_of(np.asarray(u, float).reshape(1, -1))[0]
            return row
        rho = values[2] if len(values) > 2 else math.nan
        if not (math.isfinite(rho) and rho > 0.0):
            rho = float(self.k[eq.RHO])
        out = [*values[:REQUIRED_INPUTS], rho]
        out += [v if math.isfinite(v) else 0.0 for v in values[3:N_INPUTS]]
        out += [0.0] * (N_INPUTS - len(out))
        return np.array(out)

    def inputs_of(self, u: FloatArray) -> FloatArray:
        """inputs() of each row of u [N x m], all rows at once: [N x N_INPUTS]."""
        u = np.asarray(u, float)
        out = np.zeros((u.shape[0], N_INPUTS))
        out[:, :REQUIRED_INPUTS] = u[:, :REQUIRED_INPUTS]
        rho = u[:, 2] if u.shape[1] > 2 else np.full(u.shape[0], math.nan)
        ok = np.isfinite(rho) & (rho > 0.0)
        out[:, 2] = np.where(ok, rho, float(self.k[eq.RHO]))
        lateral = u[:, 3:N_INPUTS]
        out[:, 3 : 3 + lateral.shape[1]] = np.where(np.isfinite(lateral), lateral, 0.0)
        return out

    def augment(self, state: FloatArray, beta: FloatArray) -> FloatArray:
        """The augmented state of flight states and coefficients (other blocks at 0)."""
        x = np.zeros(self.n)
        x[self.flight] = state
        x[self.coefficients] = beta
        return x


def build_model(config: AircraftConfig, gust_states: bool | None = None) -> Model:
    """Pack an aircraft configuration for the equations: the state is the flight block
    (dynamic), the gust states where the filters model turbulence as states
    (`gust_states`; default: as filter.turbulence.model says) and the pitch gust's state
    where the airframe gives a wing span (none with gust_states=False: the still-air
    model the simulators and output error fly), then the coefficients of the configured
    structure and the sensor biases (constant)."""
    a = config.airframe
    p = config.propulsion
    k = np.zeros(eq.N_CONST)
    k[eq.MASS] = a.mass_kg
    k[eq.AREA] = a.wing_area_m2
    k[eq.CHORD] = a.mean_chord_m
    k[eq.IYY] = a.inertia_yy_kgm2
    k[eq.RHO] = a.air_density_kgpm3
    k[eq.GRAV] = STANDARD_GRAVITY_MPS2
    k[eq.V0] = a.trim_airspeed_mps
    k[eq.SIGMA_T] = a.thrust_inclination_rad
    k[eq.ARM] = a.thrust_moment_arm_m
    s = config.sensors
    k[eq.VANE_X], k[eq.VANE_Z] = s.vane_x_m, s.vane_z_m
    k[eq.ACCEL_X], k[eq.ACCEL_Z] = s.accel_x_m, s.accel_z_m
    turbulence = config.filter.turbulence
    k[eq.GUST_LU], k[eq.GUST_LW] = turbulence.length_u_m, turbulence.length_w_m
    k[eq.SPAN] = a.wing_span_m
    k[eq.IXX], k[eq.IZZ], k[eq.IXZ] = a.inertia_xx_kgm2, a.inertia_zz_kgm2, a.inertia_xz_kgm2
    if p.model == "propeller":
        c = p.constants(a.air_density_kgpm3)
        k[eq.PROP_KIND] = eq.PROP_ENGINE if c.engine else eq.PROP_PROPELLER
        k[eq.PROP_AREA] = c.area_m2
        k[eq.PROP_COEF] = c.coefficient * p.thrust_scale
        k[eq.MOTOR_K] = c.zero_thrust_mps * p.speed_scale
    else:
        k[eq.PROP_KIND] = eq.PROP_MEASURED
    pairs = config.structure.pairs
    axis = np.array([AXES.index(ax) for ax, _ in pairs], dtype=np.int64)
    regressor = np.array([REGRESSORS.index(r) for _, r in pairs], dtype=np.int64)
    names = config.structure.names
    biases = tuple(f"{c}_bias" for c in s.bias_states)
    gusts = turbulence.model == "states" if gust_states is None else gust_states
    # The pitch gust's state with a wing span, but never in the
    # still-air model the simulators and output error fly (gust_states=False).
    pitch = a.wing_span_m > 0.0 and gust_states is not False
    gust_names = (GUST_STATES if gusts else ()) + ((PITCH_GUST_STATE,) if pitch else ())
    layout = StateLayout.assemble(
        [(FLIGHT, FLIGHT_STATES, True)]
        + ([(GUSTS, gust_names, True)] if gust_names else [])
        + [(COEFFICIENTS, names, False), (BIASES, biases, False)]
    )
    arrays = ModelArrays(
        k=k,
        axis=axis,
        regressor=regressor,
        coef_start=layout.block(COEFFICIENTS).start,
        n_dynamic=layout.n_dynamic,
        bias_channel=np.array(s.bias_channels, dtype=np.int64),
        bias_start=layout.block(BIASES).start,
    )
    return Model(layout=layout, arrays=arrays, names=names)


@dataclass(frozen=True)
class Trim:
    """Steady level flight: state [V, alpha, theta, q] and inputs [de, throttle_or_thrust]."""

    state: FloatArray
    inputs: FloatArray
    residual: float
    """Largest |state derivative| left at the solution [SI]."""


def steady_residual(
    model: Model, beta: FloatArray, state: FloatArray, inputs: FloatArray
) -> FloatArray:
    """[Vdot, alphadot * V, qdot] of straight flight (q = 0) at state [V, alpha, theta]
    and inputs: zero in steady flight. Scaled so that each equation weighs alike
    (m/s^2, rad/s, rad/s^2)."""
    x = model.augment(np.array([state[0], state[1], state[2], 0.0]), beta)
    fx, _ = model.f(x, inputs)
    return np.array([fx[0], fx[1] * state[0], fx[3]])


def trim(model: Model, beta: FloatArray, airspeed_mps: float | None = None) -> Trim:
    """Trim for level flight (theta = alpha, q = 0) at the given airspeed.

    Solves Vdot = alphadot = qdot = 0 for alpha, elevator and throttle (or thrust).
    """
    V = float(model.k[eq.V0]) if airspeed_mps is None else airspeed_mps
    propeller = eq.throttle_driven(model.k)

    def residual(z: FloatArray) -> FloatArray:
        alpha, de, power = z
        return steady_residual(model, beta, np.array([V, alpha, alpha]), np.array([de, power]))

    weight = model.k[eq.MASS] * model.k[eq.GRAV]
    guess = np.array([0.05, 0.0, 0.3 if propeller else 0.1 * weight])
    lower = np.array([-0.5, -0.6, 0.0 if propeller else -math.inf])
    upper = np.array([0.5, 0.6, 1.0 if propeller else math.inf])
    sol = least_squares(residual, guess, bounds=(lower, upper), xtol=1e-15, ftol=1e-15, gtol=1e-15)
    alpha, de, power = sol.x
    return Trim(
        state=np.array([V, alpha, alpha, 0.0]),
        inputs=np.array([de, power]),
        residual=float(np.max(np.abs(residual(sol.x)))),
    )
