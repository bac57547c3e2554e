"""Configuration: one TOML file per airframe, read once into frozen dataclasses.

Every key is declared once, below, on its dataclass field (gcs_estimator.schema): default,
unit, bounds and allowed values. `gcs-estimator keys` lists them all; configs/noc_uav.toml
sets every one. The file may also hold a [simulation] table for the simulator, which
declares and reads it itself (sim/scenario.py, `gcs-sim --keys`). Configs ship with the
package and are found by name (``--config hfb320``) or by path. A file may start from
another (``extends = "hfb320"``, a shipped name or a path relative to the file) and set
only what differs.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import Any, Literal

from gcs_estimator import units
from gcs_estimator.model import propeller
from gcs_estimator.model import turbulence as gusts
from gcs_estimator.model.channels import FLIGHT_STATES, OBS_NAMES
from gcs_estimator.model.propeller import PropellerConstants
from gcs_estimator.schema import (
    ConfigError,
    Invalid,
    Spec,
    Where,
    apply_overrides,
    build,
    merge_tables,
    read_toml,
    reference,
    setting,
    table,
)

__all__ = ["AircraftConfig", "ConfigError", "load_config", "load_reference", "load_truths"]

REGRESSORS: tuple[str, ...] = ("1", "alpha", "qhat", "elevator", "V/V0", "adhat")
"""Regressors a coefficient may have, in kernel order (see model.equations)."""
REGRESSOR_SUFFIX: dict[str, str] = {
    "1": "0",
    "alpha": "a",
    "qhat": "q",
    "elevator": "de",
    "V/V0": "V",
    "adhat": "adot",
}
"""Naming rule: CL with regressor alpha is "CLa", Cm with elevator is "Cmde", and so on."""
AXES: tuple[str, ...] = ("CD", "CL", "Cm")
ANGLES: tuple[str, ...] = ("alpha", "theta", "q", "qdot")
"""Channels that may be given in degrees (KEY_deg)."""
STREAMED_MESSAGES: tuple[str, ...] = (
    "HIGHRES_IMU",
    "ATTITUDE",
    "AOA_SSA",
    "VFR_HUD",
    "SERVO_OUTPUT_RAW",
    "NAMED_VALUE_FLOAT",
)
VIEW_OUTPUTS: tuple[str, ...] = ("auto", "save", "serve", "spawn", "connect", "off")
NOC_SENSOR_SIGMA: tuple[float, ...] = (
    0.3,
    math.radians(0.3),
    math.radians(0.2),
    math.radians(0.1),
    0.05,
    0.2,
    0.2,
    0.3,
)
"""The simulated sensors' noise, and the filters' measurement sigma unless set (h_dot:
a GPS vertical speed's, with the vertical air motion the model does not carry where
turbulence is white process noise: decision 0049)."""

PropulsionKind = Literal["propeller", "measured"]
PowerInput = Literal["throttle", "thrust"]
POWER_COLUMNS: dict[str, str] = {"throttle": "throttle", "thrust": "thrust_n"}
"""Column name of the second input in CSV files and histories."""
COEFFICIENT = "coefficient"
"""Context key of the coefficient names: known once [coefficients] is read."""


@dataclass(frozen=True)
class Airframe:
    """Rigid-body and air-data constants of the aircraft (longitudinal plane)."""

    mass_kg: float = setting(gt=0, unit="kg")
    wing_area_m2: float = setting(gt=0, unit="m^2")
    mean_chord_m: float = setting(gt=0, unit="m")
    inertia_yy_kgm2: float = setting(gt=0, unit="kg m^2")
    air_density_kgpm3: float = setting(gt=0, unit="kg/m^3")
    trim_airspeed_mps: float = setting(
        gt=0, unit="m/s", doc="V0: reference of qhat = q*cbar/(2*V0) and V/V0"
    )
    name: str = setting("aircraft")
    thrust_inclination_rad: float = setting(0.0, unit="rad", doc="sigma_T: thrust line to body x")
    thrust_moment_arm_m: float = setting(0.0, unit="m", doc="l_x*sin(sigma_T) + l_z*cos(sigma_T)")
    wing_span_m: float = setting(
        0.0,
        ge=0,
        unit="m",
        doc="b: the pitch gust's scale (MIL-F-8785C), which the simulator flies and the "
        "filters model (docs/decisions/0016); 0: no pitch gust",
    )
    inertia_xx_kgm2: float = setting(
        0.0,
        ge=0,
        unit="kg m^2",
        doc="roll inertia: with inertia_zz_kgm2, q-dot's inertial coupling in turns "
        "((Izz-Ixx) p r + Ixz (r^2-p^2))/Iy (docs/decisions/0048); 0: left out",
    )
    inertia_zz_kgm2: float = setting(0.0, ge=0, unit="kg m^2", doc="yaw inertia (as Ixx)")
    inertia_xz_kgm2: float = setting(0.0, unit="kg m^2", doc="product of inertia Ixz")
    elevator_travel_deg: float = setting(
        0.0,
        ge=0,
        unit="deg",
        doc="the elevator's deflection at full output (a log's normalised or PWM-end "
        "command, a CSV's -1..1 column); the one thing about the controls a log cannot "
        "say; 0: not given",
    )


@dataclass(frozen=True)
class SensorPlacement:
    """Where the sensors sit relative to the CG (body axes: x forward, z down), and which
    channels carry a constant bias the filters estimate with the coefficients."""

    vane_x_m: float = setting(0.0, unit="m", doc="angle-of-attack vane, ahead of the CG")
    vane_z_m: float = setting(0.0, unit="m", doc="angle-of-attack vane, below the CG")
    accel_x_m: float = setting(0.0, unit="m", doc="accelerometers, ahead of the CG")
    accel_z_m: float = setting(0.0, unit="m", doc="accelerometers, below the CG")
    bias_states: tuple[str, ...] = setting(
        (), choices=OBS_NAMES, unique=True, doc='channels whose bias is estimated, e.g. ["q"]'
    )

    @property
    def bias_channels(self) -> tuple[int, ...]:
        return tuple(OBS_NAMES.index(c) for c in self.bias_states)


@dataclass(frozen=True)
class Propulsion:
    """Thrust: Fe = 0.5*rho*S_prop*C_prop*((k_motor*throttle)^2 - V^2), or measured Fe.

    The propeller model's constants come exactly from prop_area_m2, prop_coefficient and
    motor_constant_mps where all three are set (a static thrust test), else from the spec
    sheet's keys (model.propeller: the derivation and its tolerances; decision 0054)."""

    model: str = setting(choices=("propeller", "measured"))
    prop_diameter_m: float = setting(
        0.0, ge=0, unit="m", doc="the propeller's diameter (spec sheet: 14 in = 0.3556 m)"
    )
    prop_pitch_m: float = setting(
        0.0, ge=0, unit="m", doc="its pitch (14x7: 7 in = 0.1778 m); 0: not given"
    )
    max_power_w: float = setting(
        0.0, ge=0, unit="W", doc="the engine's or motor's maximum (shaft) power at full throttle"
    )
    max_rpm: float = setting(
        0.0,
        ge=0,
        unit="rpm",
        doc="the propeller's rpm at full throttle (electric: about 0.8 x kv x battery volts); "
        "0: not given",
    )
    engine: str = setting(
        "electric",
        choices=("electric", "piston", "turboprop"),
        doc="what turns the propeller: an electric motor (the throttle sets its speed) "
        "or an engine whose throttle sets its power (piston, turboprop); spec sheet only",
    )
    thrust_tolerance: float | None = setting(
        None,
        gt=0,
        doc="relative 1-sigma of the thrust (a factor on it that refine fits and the "
        "structure check moves); not set: the spec sheet derivation's (0.15), exact with "
        "the three exact keys",
    )
    prop_area_m2: float = setting(
        0.0, ge=0, unit="m^2", doc="exact (a static thrust test): all three or none; they win"
    )
    prop_coefficient: float = setting(
        0.0, ge=0, doc="exact (a static thrust test): all three or none; they win"
    )
    motor_constant_mps: float = setting(
        0.0, ge=0, unit="m/s", doc="exact (a static thrust test): all three or none; they win"
    )
    thrust_scale: float = setting(1.0, internal=True)
    """A factor on the thrust (the structure check's replays move it)."""
    speed_scale: float = setting(1.0, internal=True)
    """A factor on the zero-thrust airspeed (the structure check's replays move it)."""

    def check(self) -> None:
        if self.model != "propeller":
            return
        if self.exact:
            if self.engine != "electric":
                raise Invalid(
                    "engine",
                    f"the exact keys ({', '.join(EXACT_PROPELLER_KEYS)}) describe an "
                    'electric motor\'s propeller: leave engine = "electric", or give the '
                    "spec sheet's keys instead of the exact ones",
                )
            return
        exact = [k for k in EXACT_PROPELLER_KEYS if getattr(self, k) > 0]
        if exact:
            missing = [k for k in EXACT_PROPELLER_KEYS if k not in exact]
            raise Invalid(
                missing[0],
                f"set all of {', '.join(EXACT_PROPELLER_KEYS)} (a static thrust test's "
                f"values), or none and the spec sheet's {', '.join(SPEC_SHEET_KEYS)}",
            )
        for key in SPEC_SHEET_KEYS:
            if getattr(self, key) <= 0:
                raise Invalid(
                    key,
                    'a number > 0 is needed with model = "propeller": the propeller\'s '
                    "diameter [m] and the engine's maximum power [W] from their spec "
                    "sheets (with prop_pitch_m and max_rpm where known)",
                )

    @property
    def exact(self) -> bool:
        """Whether the three exact keys are all set (they win over the spec sheet's)."""
        return all(getattr(self, k) > 0 for k in EXACT_PROPELLER_KEYS)

    def constants(self, rho: float) -> PropellerConstants:
        """The propeller model's constants at air density rho and their priors: exact
        (no prior but thrust_tolerance) or from the spec sheet (model.propeller)."""
        if self.exact:
            c = PropellerConstants(
                self.prop_area_m2, self.prop_coefficient, self.motor_constant_mps, 0.0, 0.0
            )
        elif self.engine != "electric":
            c = propeller.from_engine(self.prop_diameter_m, self.max_power_w, rho)
        else:
            c = propeller.from_spec_sheet(
                self.prop_diameter_m, self.max_power_w, rho, self.prop_pitch_m, self.max_rpm
            )
        if self.thrust_tolerance is not None:
            c = c._replace(scale_sigma=self.thrust_tolerance)
        return c

    @property
    def input_name(self) -> PowerInput:
        """What the second input is: the throttle (propeller model) or measured thrust."""
        return "thrust" if self.model == "measured" else "throttle"


EXACT_PROPELLER_KEYS = ("prop_area_m2", "prop_coefficient", "motor_constant_mps")
SPEC_SHEET_KEYS = ("prop_diameter_m", "max_power_w")
"""The spec sheet keys the propeller model needs where the exact ones are not set."""


def _regressors() -> Any:
    names = (
        'CL + "alpha" is CLa: suffixes 0, a, q, de, V, adot; adhat = alphadot*cbar/(2*V0) '
        "(usually strongly correlated with qhat: needs varied excitation)"
    )
    return setting(choices=REGRESSORS, unique=True, doc=names)


@dataclass(frozen=True)
class CoefficientStructure:
    """Which regressors each of CD, CL, Cm has; one estimated parameter per pair."""

    CD: tuple[str, ...] = _regressors()
    CL: tuple[str, ...] = _regressors()
    Cm: tuple[str, ...] = _regressors()

    def check(self) -> None:
        if not self.names:
            raise Invalid("CD", "no coefficient to estimate; list at least one regressor")

    @property
    def pairs(self) -> tuple[tuple[str, str], ...]:
        return tuple((axis, r) for axis in AXES for r in getattr(self, axis))

    @property
    def names(self) -> tuple[str, ...]:
        """Parameter names in state order, e.g. ("CD0", "CDa", ..., "Cmde")."""
        return tuple(axis + REGRESSOR_SUFFIX[r] for axis, r in self.pairs)

    @property
    def axes(self) -> tuple[str, ...]:
        """Axis ("CD", "CL" or "Cm") of each parameter, in state order."""
        return tuple(axis for axis, _ in self.pairs)


@dataclass(frozen=True)
class Reference:
    """True coefficients (simulation) or accepted reference values, in structure order."""

    values: tuple[float, ...] = setting(keys=COEFFICIENT, inline=True)
    label: str = setting("truth", doc="column heading in the results")


def per_channel(fill: float | tuple[float, ...], **spec: Any) -> Any:
    """A schema field of one number per observation channel (OBS_NAMES), angles also in
    degrees (KEY_deg)."""
    return setting(
        fill if isinstance(fill, tuple) else (fill,) * len(OBS_NAMES),
        keys=OBS_NAMES,
        fill=fill,
        degrees=ANGLES,
        **spec,
    )


@dataclass(frozen=True)
class InitialSigma:
    """1 sigma of the initial belief of the coefficients (the flight states start from
    their first measurement, with filters.core.FLIGHT_PRIOR_SIGMA)."""

    coefficients: tuple[float, ...] = setting(
        (),
        keys=COEFFICIENT,
        fill=10.0,
        gt=0,
        doc="what is known of each coefficient before the flight; wider for the large rate "
        "derivatives (Cmq, CLq)",
    )


@dataclass(frozen=True)
class ProcessNoise:
    """Continuous-time spectral densities: flight states (inline) [unit^2/s] and the
    coefficients' random walk [1/s] (the estimated sensor biases are constant)."""

    states: tuple[float, ...] = setting(
        (1e-8, 1e-9, 1e-10, 1e-9),
        keys=FLIGHT_STATES,
        fill=(1e-8, 1e-9, 1e-10, 1e-9),
        inline=True,
        ge=0,
    )
    coefficients: float = setting(
        1e-12,
        ge=0,
        unit="1/s",
        doc="random walk of every coefficient: how fast they may change in flight",
    )


@dataclass(frozen=True)
class TurbulenceNoise:
    """The filter's model of turbulence, its level a Dryden gust intensity estimated online
    from the innovations: gust states u_g, w_g (first-order Dryden processes with the
    scale lengths below) in the augmented state, or white process noise on V, alpha and
    theta (model.turbulence.gust_densities)."""

    model: str = setting(
        "noise",
        choices=("noise", "states"),
        doc="states: gust states u_g, w_g (coloured, mean-reverting); noise: white process "
        "noise on the flight states",
    )
    adaptive: bool = setting(True, doc="estimate sigma_w^2 online from the V and alpha innovations")
    sigma_w_mps: float = setting(0.0, ge=0, unit="m/s", doc="initial (adaptive) or fixed level")
    sigma_u_ratio: float = setting(1.5, gt=0)
    length_u_m: float = setting(200.0, gt=0, unit="m")
    length_w_m: float = setting(50.0, gt=0, unit="m")
    detection_sigma: float = setting(
        3.0, ge=0, doc="applied only once this many standard errors above zero (calm stays calm)"
    )
    settle_s: float = setting(
        3.0,
        ge=0,
        unit="s",
        doc="until a level is detected only frames where the inputs are still inform it "
        "(model-structure error shows in manoeuvres, turbulence everywhere): this long after "
        "the elevator's last move (0: every frame does; docs/decisions/0015)",
    )

    def unit(self, airspeed_mps: float) -> tuple[float, float, float, float]:
        """Spectral densities of V, alpha, theta, q per unit sigma_w^2."""
        return gusts.gust_densities(
            airspeed_mps, self.sigma_u_ratio, self.length_u_m, self.length_w_m, gusts.THETA_DENSITY
        )


@dataclass(frozen=True)
class FilterTuning:
    """Filter settings: initial belief, noise models, iteration control and restarts."""

    iterations: int = setting(7, ge=1, doc="IEKF update iterations (1 = EKF; the paper: 7)")
    relinearise_sigma: float = setting(
        1.0,
        ge=0,
        doc="keep the iterations only if they move some coefficient this many sigmas",
    )
    restart_frames_per_step: int = setting(
        10,
        ge=0,
        doc="frames of a restart's re-run done at least per new frame (it catches up beside "
        "the live pass, and in idle time); 0: all at once",
    )
    restart_times_s: tuple[float, ...] = setting(
        (5.0, 10.0), ge=0, unit="s", doc="re-run all frames so far from the start at these times"
    )
    measurement_noise: str = setting(
        "auto",
        choices=("auto", "config"),
        doc="where each restart's re-run takes each channel's noise sigma from: auto: the "
        "data's reading (robust fourth differences, gcs_estimator/estimation/noise.py) where it is "
        "clearly below measurement_sigma (the sensor is better than configured), else "
        "measurement_sigma; config: measurement_sigma throughout. Before the first "
        "restart, and for channels with too few samples, measurement_sigma",
    )
    structure_check: str = setting(
        "auto",
        choices=("auto", "on", "off"),
        doc="at the end of a run, replay its final pass once per channel with that channel "
        "trusted half as much, and widen each coefficient's corrected sigma by how far the "
        "estimate moves beyond what the covariance predicts (what the model's structure "
        "misses: gcs_estimator/uncertainty/weighting.py); auto: when the run kept its "
        "history and its frames stay within structure_check_max_frames",
    )
    structure_check_max_frames: int = setting(
        30000,
        ge=0,
        doc="most frames the structure check takes on with structure_check = auto, over "
        "all the vehicles of a run (a vehicle that would go past it is not checked, and its "
        "results say so); the check costs a replay of the final pass per channel, and one "
        "more",
    )
    bank_limit_deg: float = setting(
        45.0,
        gt=0,
        le=90,
        unit="deg",
        doc="frames banked beyond this are predicted through but not used in the update, "
        "and counted (the model's no-sideslip, coordinated turn: docs/decisions/0048)",
    )
    initial_sigma: InitialSigma = table(InitialSigma)
    process_noise: ProcessNoise = table(ProcessNoise)
    measurement_sigma: tuple[float, ...] = per_channel(NOC_SENSOR_SIGMA, gt=0)
    turbulence: TurbulenceNoise = table(TurbulenceNoise)

    def check(self) -> None:
        r = list(self.restart_times_s)
        if r != sorted(set(r)):
            raise Invalid("restart_times_s", f"must be strictly increasing, got {r}")


REFINE_METHODS: tuple[str, ...] = ("auto", "output-error", "filter-error")
"""Whole-record fits (gcs_estimator.refine): chosen from the filters' turbulence level
(refine.choose_method), output error, or with process noise."""

QUANTITY_KINDS: dict[str, str] = {
    "time": "time",
    "airspeed": "speed",
    "alpha": "angle",
    "theta": "angle",
    "q": "rate",
    "qdot": "acceleration_angular",
    "a_x": "acceleration",
    "a_z": "acceleration",
    "elevator": "angle",
    "throttle": "fraction",
    "thrust": "force",
    "air_density": "density",
    "static_pressure": "pressure",
    "pressure_altitude": "length",
    "air_temperature": "temperature",
    "climb_rate": "speed",
    "phi": "angle",
    "p": "rate",
    "r": "rate",
}
"""The quantities of a flight-data file and the kind of unit each takes (units.UNITS)."""
LATERAL_QUANTITIES: tuple[str, ...] = ("phi", "p", "r")
"""Optional columns of the turns (decision 0048): the bank angle, the roll and yaw rates,
the model's measured inputs."""
QUATERNION_QUANTITIES: tuple[str, ...] = ("quat_w", "quat_x", "quat_y", "quat_z")
"""Optional columns of the attitude as a unit quaternion (body to north-east-down, scalar
first, as PX4's vehicle_attitude.q): the pitch and bank angles where the file has no
column of their own."""
ATMOSPHERE_QUANTITIES: tuple[str, ...] = (
    "air_density",
    "static_pressure",
    "pressure_altitude",
    "air_temperature",
)
"""Optional columns the air density per sample comes from (first that the file has):
air_density itself, else static_pressure or pressure_altitude with air_temperature
(the standard temperature where that column is absent or empty)."""


def _column(default: str, optional: bool = False, observed: bool = False) -> Any:
    doc = "the file's column name" + (" (optional: air density per sample)" if optional else "")
    if observed:
        doc += ' ("": the data have none, and the filters go without this channel)'
    return setting(default, doc=doc)


NORMALISED = "normalised"
"""The elevator's unit when its column is the command as a fraction of full travel
(-1..1, as PX4 and ROS exports write it): [airframe] elevator_travel_deg turns it into a
deflection."""


def _unit(quantity: str) -> Any:
    kind = QUANTITY_KINDS[quantity]
    if quantity == "elevator":
        return setting(
            units.choices(kind)[0],
            choices=(*units.choices(kind), NORMALISED),
            doc=f'"{NORMALISED}": a command -1..1, times [airframe] elevator_travel_deg',
        )
    return setting(units.choices(kind)[0], choices=units.choices(kind))


@dataclass(frozen=True)
class Columns:
    """Which CSV column holds each quantity (the defaults are the project's own layout)."""

    time: str = _column("time_s")
    airspeed: str = _column("airspeed_mps", observed=True)
    alpha: str = _column("alpha_rad", observed=True)
    theta: str = _column("theta_rad", observed=True)
    q: str = _column("q_radps", observed=True)
    qdot: str = _column("qdot_radps2", observed=True)
    a_x: str = _column("ax_mps2", observed=True)
    a_z: str = _column("az_mps2", observed=True)
    elevator: str = _column("elevator_rad")
    throttle: str = _column("throttle")
    thrust: str = _column("thrust_n")
    air_density: str = _column("air_density_kgpm3", optional=True)
    static_pressure: str = _column("static_pressure_pa", optional=True)
    pressure_altitude: str = _column("pressure_altitude_m", optional=True)
    air_temperature: str = _column("air_temperature_k", optional=True)
    climb_rate: str = setting(
        "climb_rate_mps",
        doc="the file's column name (optional: the climb rate h_dot, up positive; "
        "without it the filters go without that channel; a down-positive vertical speed "
        "with [data.scale] climb_rate = -1)",
    )
    phi: str = setting(
        "phi_rad",
        doc="the file's column name (optional: the bank angle, right wing down positive; "
        "with it the model flies the turns, decision 0048; without it and without the "
        "quaternion, wings level)",
    )
    p: str = setting("p_radps", doc="the file's column name (optional: the roll rate)")
    r: str = setting("r_radps", doc="the file's column name (optional: the yaw rate)")
    quat_w: str = setting(
        "quat_w",
        doc="the file's column name (optional, with quat_x, quat_y, quat_z: the attitude "
        "quaternion, body to north-east-down, scalar first; the pitch and bank angles come "
        "from it where the file has no theta or phi column)",
    )
    quat_x: str = setting("quat_x", doc="the file's column name (see quat_w)")
    quat_y: str = setting("quat_y", doc="the file's column name (see quat_w)")
    quat_z: str = setting("quat_z", doc="the file's column name (see quat_w)")


@dataclass(frozen=True)
class Units:
    """The unit of each CSV column (the defaults: SI, throttle 0..1)."""

    time: str = _unit("time")
    airspeed: str = _unit("airspeed")
    alpha: str = _unit("alpha")
    theta: str = _unit("theta")
    q: str = _unit("q")
    qdot: str = _unit("qdot")
    a_x: str = _unit("a_x")
    a_z: str = _unit("a_z")
    elevator: str = _unit("elevator")
    throttle: str = _unit("throttle")
    thrust: str = _unit("thrust")
    air_density: str = _unit("air_density")
    static_pressure: str = _unit("static_pressure")
    pressure_altitude: str = _unit("pressure_altitude")
    air_temperature: str = _unit("air_temperature")
    climb_rate: str = _unit("climb_rate")
    phi: str = _unit("phi")
    p: str = _unit("p")
    r: str = _unit("r")

    def factor(self, quantity: str) -> float:
        """Multiplier from this file's unit of `quantity` to SI (a normalised elevator:
        1, its travel is the airframe's)."""
        unit = getattr(self, quantity)
        return 1.0 if unit == NORMALISED else units.factor(QUANTITY_KINDS[quantity], unit)

    def offset(self, quantity: str) -> float:
        """Added after the factor (temperatures in degC or degF)."""
        return units.offset(getattr(self, quantity))


def _scale() -> Any:
    return setting(1.0, doc="multiplies the column after its unit; -1 flips its sign")


@dataclass(frozen=True)
class Scale:
    """A factor per CSV column after its unit: -1 flips an axis (a ROS export's body axes
    are x forward, y left, z up: q and a_z are -1 in the estimator's x forward, z down),
    another number rescales (a sensor's gain, a command's sign)."""

    airspeed: float = _scale()
    alpha: float = _scale()
    theta: float = _scale()
    q: float = _scale()
    qdot: float = _scale()
    a_x: float = _scale()
    a_z: float = _scale()
    elevator: float = _scale()
    throttle: float = _scale()
    thrust: float = _scale()
    climb_rate: float = _scale()
    phi: float = _scale()
    p: float = _scale()
    r: float = _scale()

    def check(self) -> None:
        for key, value in vars(self).items():
            if value == 0 or not math.isfinite(value):
                raise Invalid(key, f"a factor must be a finite number other than 0, got {value}")

    def of(self, quantity: str) -> float:
        """The factor of a quantity (1 for those without one: time, the atmosphere's)."""
        return float(getattr(self, quantity, 1.0))


PLAUSIBLE_QUANTITIES: tuple[str, ...] = (
    "airspeed",
    "alpha",
    "theta",
    "q",
    "qdot",
    "a_x",
    "a_z",
    "elevator",
)
PLAUSIBLE_MAX: tuple[float, ...] = (300.0, 0.8, 1.6, 5.0, 50.0, 100.0, 100.0, 0.8)
"""Largest magnitudes a fixed-wing aircraft's signals reach [SI: m/s, rad (46 deg for
alpha and the elevator, 92 deg for theta), rad/s, rad/s^2, m/s^2]: beyond them a link's
value is dropped and counted, a file refused with the unit it is likely in."""


@dataclass(frozen=True)
class DataConfig:
    """What the flight data are, whatever carries them (a link, a log, a file)."""

    input_hold: str = setting(
        "linear",
        choices=("linear", "previous"),
        doc="the commands (elevator, throttle) between samples: linear (first-order hold) "
        "or held at the earlier sample (the bank and its rates go linearly either way); "
        "a CSV's empty input cells are filled the same way",
    )
    input_delay_s: float = setting(
        0.0,
        ge=0.0,
        le=0.5,
        unit="s",
        doc="the surfaces and engine respond this late after the logged inputs: the "
        "filters take each input this much later (refine estimates what remains; "
        "decision 0044)",
    )
    estimate_input_delay: bool = setting(
        True,
        doc="refine fits the inputs' delay with the coefficients (false: the timing as "
        "logged plus input_delay_s, as a textbook fit assumes)",
    )
    compatibility_check: str = setting(
        "report",
        choices=("correct", "report", "off"),
        doc="a log's or data file's channels checked against the kinematics before "
        "estimation (each one's bias, scale factor and time shift; decision 0056): "
        "correct those beyond the noise, report them only, or skip the check",
    )
    columns: Columns = table(Columns)
    units: Units = table(Units)
    scale: Scale = table(Scale)

    @staticmethod
    def plausible(quantity: str) -> float:
        """The largest magnitude the signal can have (PLAUSIBLE_MAX) [SI]."""
        return PLAUSIBLE_MAX[PLAUSIBLE_QUANTITIES.index(quantity)]


@dataclass(frozen=True)
class LinkConfig:
    """How the aircraft's signals map onto MAVLink (telemetry.pwm), and the rate to ask for."""

    elevator_servo: int = setting(2, ge=1, le=16, doc="SERVO_OUTPUT_RAW channel")
    elevator_pwm_center_us: float = setting(1500.0, unit="us")
    elevator_us_per_rad: float = setting(954.93, unit="us/rad", doc="500 us for 30 deg")
    throttle_servo: int = setting(3, ge=0, le=16, doc="0: thrust comes as NAMED_VALUE_FLOAT")
    throttle_pwm_min_us: float = setting(1000.0, unit="us")
    throttle_pwm_max_us: float = setting(2000.0, unit="us")
    qdot_name: str = setting("QDOT", doc="NAMED_VALUE_FLOAT name, 1..10 characters")
    thrust_name: str = setting("THRUST", doc="NAMED_VALUE_FLOAT name, 1..10 characters")
    density_from_pressure: bool = setting(
        False,
        doc="air density per sample from SCALED_PRESSURE.press_abs at the standard "
        "temperature (its temperature field is the sensor's own); false: the airframe's",
    )
    max_vehicles: int = setting(
        16, ge=1, doc="system ids estimated per session; packets of more are counted only"
    )
    allowed_system_ids: tuple[int, ...] = setting(
        (),
        ge=1,
        le=255,
        doc="the only system ids estimated and sent to (empty: any); packets of others are "
        "counted only",
    )
    aoa_ssa: str = setting(
        "ahrs",
        choices=("ahrs", "vane"),
        doc='what AOA_SSA carries: "ahrs", ArduPilot\'s estimate from its velocity and wind '
        "estimates, not a measurement (alpha weighed with a sigma of at least 3 deg); "
        '"vane", a measured angle (alpha weighed with [filter] measurement_sigma; the '
        "simulator's)",
    )
    rate_hz: float = setting(
        50.0,
        ge=0,
        unit="Hz",
        doc="asked of the vehicle (SET_MESSAGE_INTERVAL) for each message the estimator "
        "reads; the data's rate, for a replayed or simulated record",
    )
    signing_key_file: str = setting(
        "",
        doc="MAVLink 2 signing: a file holding the 32-byte key as 64 hex digits, or a "
        "passphrase (its SHA-256 is the key, as in MAVProxy); a path relative to the working "
        "directory. Set: only correctly signed packets are taken, and the station signs "
        "what it sends. Empty: no signing",
    )

    def check(self) -> None:
        if self.elevator_us_per_rad == 0:
            raise Invalid("elevator_us_per_rad", "must not be 0")
        if self.throttle_servo and self.throttle_pwm_max_us <= self.throttle_pwm_min_us:
            raise Invalid("throttle_pwm_max_us", "must be greater than throttle_pwm_min_us")
        for key in ("qdot_name", "thrust_name"):
            name = getattr(self, key)
            if not 0 < len(name) <= 10:
                raise Invalid(key, f"NAMED_VALUE_FLOAT names are 1..10 characters, got {name!r}")

    def rate(self, message: str) -> float:
        """The rate asked for a message [Hz] (0 for one the estimator does not read)."""
        return self.rate_hz if message in STREAMED_MESSAGES else 0.0


def _is_host(text: str) -> bool:
    """An IP address (v4 or v6) or a host name (RFC 1123 labels)."""
    import ipaddress
    import re

    try:
        ipaddress.ip_address(text)
        return True
    except ValueError:
        label = r"(?!-)[A-Za-z0-9-]{1,63}(?<!-)"
        return len(text) <= 253 and re.fullmatch(rf"{label}(\.{label})*", text) is not None


@dataclass(frozen=True)
class ViewConfig:
    """The live Rerun view: where it goes (save an .rrd, serve over gRPC, spawn a viewer,
    connect to one, off; auto: spawn and save with a display, else save) and what is kept."""

    outputs: tuple[str, ...] = setting(("auto",), choices=VIEW_OUTPUTS, unique=True)
    rrd_path: str = setting("", internal=True)
    """The .rrd to save (the command line's --rrd; empty: one in the run's folder)."""
    serve_bind: str = setting("127.0.0.1", doc='"0.0.0.0" lets viewers on other machines join')
    serve_port: int = setting(9877, ge=1, le=65535)
    serve_linger_s: float = setting(
        30.0,
        ge=0,
        unit="s",
        doc="a served view stays up this long after the run, for viewers to catch up "
        "(Ctrl-C ends it sooner)",
    )
    connect_url: str = setting("rerun+http://127.0.0.1:9876/proxy")
    viewer_port: int = setting(9876, ge=1, le=65535, doc="port of a spawned viewer")

    def check(self) -> None:
        if not _is_host(self.serve_bind):
            raise Invalid(
                "serve_bind",
                f"{self.serve_bind!r} is no address to listen on: an IP address such as "
                '"127.0.0.1" (this machine only) or "0.0.0.0" (every interface), or a host name',
            )
        if not self.connect_url.startswith(("rerun://", "rerun+http://", "rerun+https://")):
            raise Invalid(
                "connect_url",
                f"must look like rerun+http://HOST:PORT/proxy, got {self.connect_url!r}",
            )


@dataclass(frozen=True)
class AircraftConfig:
    """Everything one airframe needs: physics, structure, truth (if simulated), tuning."""

    airframe: Airframe = table(Airframe, required=True)
    propulsion: Propulsion = table(Propulsion, required=True)
    structure: CoefficientStructure = table(
        CoefficientStructure, required=True, toml="coefficients"
    )
    sensors: SensorPlacement = table(SensorPlacement)
    reference: Reference | None = table(Reference, optional=True, toml="truth")
    filter: FilterTuning = table(FilterTuning)
    data: DataConfig = table(DataConfig)
    link: LinkConfig = table(LinkConfig)
    view: ViewConfig = table(ViewConfig)
    source: str = setting("<config>", internal=True)
    raw: Mapping[str, Any] = field(default_factory=dict, metadata={"spec": Spec(internal=True)})
    """The parsed TOML, kept to write into results exactly as used."""

    def link_problem(self) -> str | None:
        """Why this config cannot read a MAVLink link's power input (None: it can): the
        measured-thrust model reads thrust as NAMED_VALUE_FLOAT, so no throttle servo; the
        propeller model a throttle servo. A data file's columns need neither."""
        measured = self.propulsion.model == "measured"
        if measured == (self.link.throttle_servo == 0):
            return None
        need = "0 (thrust comes as NAMED_VALUE_FLOAT thrust_name)" if measured else "1..16"
        return (
            f"{self.source}: [link] throttle_servo: must be {need} with [propulsion] model = "
            f'"{self.propulsion.model}" for a MAVLink link or log'
        )

    @property
    def coefficient_names(self) -> tuple[str, ...]:
        return self.structure.names

    @property
    def truth(self) -> tuple[float, ...] | None:
        return None if self.reference is None else self.reference.values

    @property
    def truth_label(self) -> str:
        return "truth" if self.reference is None else self.reference.label

    def with_truth(self, truth: tuple[float, ...], label: str | None = None) -> AircraftConfig:
        """The same aircraft with other true (or reference) coefficients."""
        if len(truth) != len(self.coefficient_names):
            raise ConfigError(f"{self.source}: truth needs {len(self.coefficient_names)} values")
        values = tuple(float(v) for v in truth)
        return replace(
            self, reference=Reference(values, self.truth_label if label is None else label)
        )


SIMULATOR_TABLE = "simulation"
"""The table an airframe file may hold for the simulator, which reads and checks it
(sim.scenario); the estimator does not look at it."""


def parse_config(data: Mapping[str, Any], source: str = "<config>") -> AircraftConfig:
    """Validate a parsed TOML mapping (configs/noc_uav.toml sets every key), all but the
    simulator's table (kept in `raw` for it)."""
    where = Where(source)
    coefficients = data.get("coefficients")
    if not isinstance(coefficients, Mapping):
        raise where.error(
            "coefficients", "missing table; add it" if coefficients is None else "must be a table"
        )
    names = build(CoefficientStructure, coefficients, where.sub("coefficients")).names
    tables = {k: v for k, v in data.items() if k != SIMULATOR_TABLE}
    return build(AircraftConfig, tables, where, {COEFFICIENT: names}, source=source, raw=dict(data))


def config_path(name: str | Path) -> Path:
    """A config file by path, or by the name of one shipped with the package ("hfb320")."""
    path = Path(name)
    if path.exists() or path.suffix == ".toml" or len(path.parts) > 1:
        return path
    shipped = shipped_configs()
    if str(name) in shipped:
        return shipped[str(name)]
    raise ConfigError(f"{name}: no such file, nor a shipped config; shipped: {sorted(shipped)}")


def shipped_configs() -> dict[str, Path]:
    """The configs that ship with the package, by name."""
    root = resources.files("gcs_estimator.configs")
    return {
        p.name.removesuffix(".toml"): Path(str(p))
        for p in root.iterdir()
        if p.name.endswith(".toml")
    }


def load_config(path: str | Path, overrides: list[str] | None = None) -> AircraftConfig:
    """Read and validate an aircraft TOML file (a path or a shipped name), with command-line
    overrides "table.key=value" applied before the one validation (schema.apply_overrides)."""
    file = config_path(path)
    data, source = read_extended(file)
    if overrides:
        data = apply_overrides(data, overrides, source)
        source = f"{file} with --set {' '.join(overrides)}"
    return parse_config(data, source)


def read_extended(file: Path, within: tuple[Path, ...] = ()) -> tuple[dict[str, Any], str]:
    """A config file's tables, on top of those of the file it `extends` (a shipped
    config's name, or a path relative to the file), and a source that names both."""
    data = read_toml(file)
    base = data.pop("extends", None)
    if base is None:
        return data, str(file)
    where = Where(str(file))
    if not isinstance(base, str) or not base:
        raise where.error("extends", "must be a shipped config's name or a path, as a string")
    beside = file.parent / base
    shipped = shipped_configs()
    if beside.is_file():
        base_file = beside
    elif base in shipped:
        base_file = shipped[base]
    else:
        raise where.error(
            "extends",
            f"{base!r} is neither a file beside this one nor a shipped config "
            f"({', '.join(sorted(shipped))})",
        )
    chain = (*within, file.resolve())
    if base_file.resolve() in chain:
        raise where.error("extends", f"{base!r} leads back to this file; remove the loop")
    base_data, base_source = read_extended(base_file, chain)
    return merge_tables(base_data, data), f"{file} (extends {base_source})"


def config_reference(names: tuple[str, ...]) -> str:
    """Every key of an airframe file (Markdown), per-coefficient tables for these names."""
    head = (
        "# Configuration keys\n\n"
        "Generated by `gcs-estimator keys` from the schema in gcs_estimator/config.py; "
        "configs/noc_uav.toml is a complete example. Per-coefficient tables list the names "
        f"of that file's structure ({', '.join(names)}); a `default` key sets the rest.\n\n"
        'A file may start from another and set only what differs: `extends = "NAME"` at '
        "the top, NAME a shipped config (`hfb320`) or a path relative to the file; its "
        "tables merge key by key over the other's (configs/hfb320_book_noise.toml).\n\n"
    )
    return head + reference(AircraftConfig, {COEFFICIENT: names})


def load_reference(path: str | Path, names: tuple[str, ...]) -> tuple[tuple[float, ...], str]:
    """Reference coefficient values (a textbook, a wind tunnel) from a TOML file: a [truth]
    table like the aircraft config's, or the same keys at the top level."""
    data = read_toml(path)
    where = Where(str(path))
    if "truth" in data:
        if set(data) != {"truth"}:
            raise where.error(
                sorted(set(data) - {"truth"})[0], "unknown key; known keys here: ['truth']"
            )
        data, where = data["truth"], where.sub("truth")
        if not isinstance(data, Mapping):
            raise Where(str(path)).error("truth", "must be a table")
    ref = build(Reference, data, where, {COEFFICIENT: names})
    return ref.values, ref.label


FLIGHT_KEYS = ("airframe", "set", "airframe_truth")
"""What a truth file may say besides its [vehicle.N] tables: the airframe file the
flight was flown or estimated with (a shipped name, or a path relative to the truth
file), its --set overrides, and whether that file's [truth] is the flight's own (a
simulated flight of it)."""


@dataclass(frozen=True)
class FlightAirframe:
    """The airframe a truth file names (see FLIGHT_KEYS)."""

    config: str
    overrides: tuple[str, ...]
    own_truth: bool


def flight_airframe(path: str | Path) -> FlightAirframe | None:
    """The airframe a truth file names (None: it names none)."""
    data = read_toml(path)
    where = Where(str(path))
    name = data.get("airframe")
    if name is None:
        return None
    overrides = data.get("set", [])
    if not isinstance(name, str) or not name:
        raise where.error("airframe", "must be a shipped config's name or a path, as a string")
    if not isinstance(overrides, list) or not all(isinstance(o, str) for o in overrides):
        raise where.error("set", 'must be a list of "table.key=value" strings')
    own = data.get("airframe_truth", False)
    if not isinstance(own, bool):
        raise where.error("airframe_truth", "must be true or false")
    beside = Path(path).parent / name
    if name not in shipped_configs() and not Path(name).is_absolute():
        name = str(beside)
    return FlightAirframe(name, tuple(overrides), own)


def load_truths(path: str | Path, names: tuple[str, ...]) -> dict[int, tuple[float, ...]]:
    """Each vehicle's true coefficients, by system id, from a truth file (as
    `gcs-sim --truth` writes): a [vehicle.N] table per system id N, each like the aircraft
    config's [truth]. A file that names its airframe (FLIGHT_KEYS) may have none."""
    data = read_toml(path)
    where = Where(str(path))
    unknown = sorted(set(data) - {"vehicle", *FLIGHT_KEYS})
    if unknown:
        known = ["vehicle", *FLIGHT_KEYS]
        raise where.error(unknown[0], f"unknown key; known keys here: {known}")
    vehicles = data.get("vehicle")
    if vehicles is None and "airframe" in data:
        return {}
    if not isinstance(vehicles, Mapping) or not vehicles:
        raise where.error("vehicle", "missing: add a [vehicle.N] table per system id N")
    out: dict[int, tuple[float, ...]] = {}
    for key, values in vehicles.items():
        if not (key.isdigit() and 1 <= int(key) <= 255):
            raise where.sub("vehicle").error(key, "a system id 1..255 is expected here")
        if not isinstance(values, Mapping):
            raise where.sub("vehicle").error(key, "must be a table of coefficients")
        out[int(key)] = build(
            Reference, values, where.sub(f"vehicle.{key}"), {COEFFICIENT: names}
        ).values
    return out


def truths_text(
    truths: Mapping[int, tuple[float, ...]],
    names: tuple[str, ...],
    airframe: FlightAirframe | None = None,
) -> str:
    """A truth file (load_truths reads it back exactly: floats written by repr), naming
    the flight's airframe when given (flight_airframe reads it back)."""
    lines = ["# True coefficients each vehicle flies, by system id (gcs-sim --truth)."]
    if airframe is not None:
        lines = [
            "# What flew: the airframe file this flight was flown or estimated with (a replay",
            "# without --config reads it), and each vehicle's true coefficients, if known.",
            f"airframe = {json.dumps(airframe.config)}",
            f"set = {json.dumps(list(airframe.overrides))}",
            f"airframe_truth = {'true' if airframe.own_truth else 'false'}",
        ]
    for sid, values in sorted(truths.items()):
        lines.append(f"\n[vehicle.{sid}]")
        lines += [f"{n} = {float(v)!r}" for n, v in zip(names, values, strict=True)]
    return "\n".join(lines) + "\n"


STARTER_AIRFRAME = """\
# My aircraft's airframe file for gcs-estimator: fill in every value marked FILL IN (0
# until you do; the estimator refuses a 0 there and names the key), then give the file
# with --config. Every other key has a default: `gcs-estimator keys` lists them all.

[airframe]
name = "my plane"
# The weight as flown, with battery, fuel and payload [kg]: weigh it.
mass_kg = 0.0                 # FILL IN
# Wing area [m^2], from the spec sheet (sq in x 0.000645; sq ft x 0.0929).
wing_area_m2 = 0.0            # FILL IN
# Mean aerodynamic chord [m]; for a rectangular wing, area / span.
mean_chord_m = 0.0            # FILL IN
# Pitch moment of inertia [kg m^2]: rarely on a spec sheet. From a CAD model, or a
# swing (bifilar pendulum) test. The moment coefficients scale with it.
inertia_yy_kgm2 = 0.0         # FILL IN
# Air density at the flying site [kg/m^3] (1.225 at sea level, 15 degC), used wherever
# the data carry none.
air_density_kgpm3 = 1.225
# A typical cruise airspeed [m/s]: V0, the scale of the qhat and V/V0 coefficients.
trim_airspeed_mps = 0.0       # FILL IN
# Wing span [m]: with it the filters model turbulence's pitch gust (0: not given).
wing_span_m = 0.0
# The elevator's deflection at full output [deg] (a log's normalised or PWM-end
# command needs it): measure it on the aircraft at full stick (0: not given).
elevator_travel_deg = 0.0
# The thrust line: leave at 0 if it runs along the body axis through the CG.
thrust_inclination_rad = 0.0
thrust_moment_arm_m = 0.0

[propulsion]
# "propeller" when the data carry the throttle (0..1), "measured" when they carry thrust
# in newtons (or none: a glide).
model = "propeller"
# From the spec sheets, in SI units; the thrust model's constants are derived from
# them (docs/model.md, "Thrust from the spec sheet"), and `refine` fits the thrust with
# the coefficients where the flight tells it from drag (throttle steps, a glide).
# The propeller's diameter [m] (inches x 0.0254: a 14x7 propeller is 0.3556 m).
prop_diameter_m = 0.0         # FILL IN
# Its pitch [m] (the second number: 14x7 is 7 in, 0.1778 m); 0: not known.
prop_pitch_m = 0.0
# The engine's or motor's maximum power [W] (hp x 745.7).
max_power_w = 0.0             # FILL IN
# The propeller's rpm at full throttle (an electric motor: about 0.8 x kv x battery
# volts); 0: not known. With the pitch it gives the airspeed where thrust vanishes.
max_rpm = 0.0
# A static thrust test instead: set all three of prop_area_m2, prop_coefficient and
# motor_constant_mps (`gcs-estimator keys`); they win over the keys above.

# Which regressors CD, CL and Cm have, from "1", "alpha", "qhat", "elevator", "V/V0",
# "adhat": each pair is one coefficient (CL with "alpha" is CLa). This is the usual set.
[coefficients]
CD = ["1", "alpha", "elevator"]
CL = ["1", "alpha", "qhat", "elevator"]
Cm = ["1", "alpha", "qhat", "elevator"]

# A log's or CSV's layout: [link] (MAVLink servo outputs), [data.columns], [data.units],
# [data.scale]; see docs/guide.md.
"""
"""What `gcs-estimator airframe FILE` writes: the keys a spec sheet gives, with what each
means and where to find it."""
