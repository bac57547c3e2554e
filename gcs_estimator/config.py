"""Configuration: one TOML file per airframe, read once into frozen dataclasses.

Every value is validated here, so that the rest of the code can trust it. An error names
the file, the key and what is allowed, e.g.::

    configs/my_plane.toml: [airframe] mass_kg: must be a number > 0, got -3
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, TypeVar

if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import NDArray

Num = TypeVar("Num", float, "NDArray[np.float64]")
"""A scalar or an array of them: the link's PWM mapping works on either."""

REGRESSORS: tuple[str, ...] = ("1", "alpha", "qhat", "elevator", "V/V0")
"""Regressors a coefficient may have, in kernel order (see model.equations)."""

REGRESSOR_SUFFIX: dict[str, str] = {
    "1": "0",
    "alpha": "a",
    "qhat": "q",
    "elevator": "de",
    "V/V0": "V",
}
"""Naming rule: CL with regressor alpha is "CLa", Cm with elevator is "Cmde", and so on."""

AXES: tuple[str, ...] = ("CD", "CL", "Cm")
STATE_NAMES: tuple[str, ...] = ("V", "alpha", "theta", "q")
OBS_NAMES: tuple[str, ...] = ("V", "alpha", "theta", "q", "qdot", "a_x", "a_z")

PropulsionKind = Literal["propeller", "measured"]
WarmStartKind = Literal["equation-error", "filter"]


class ConfigError(ValueError):
    """A configuration value is missing or not allowed; the message says where and why."""


@dataclass(frozen=True)
class Airframe:
    """Rigid-body and air-data constants of the aircraft (longitudinal plane)."""

    name: str
    mass_kg: float
    wing_area_m2: float
    mean_chord_m: float
    inertia_yy_kgm2: float
    air_density_kgpm3: float
    gravity_mps2: float
    trim_airspeed_mps: float
    """V0 [m/s]: reference speed of qhat = q*cbar/(2*V0) and of the V/V0 regressor."""
    thrust_inclination_rad: float
    """sigma_T [rad]: thrust line angle to the body x axis."""
    thrust_moment_arm_m: float
    """l_x*sin(sigma_T) + l_z*cos(sigma_T) [m]: pitching moment per newton of thrust."""


PowerInput = Literal["throttle", "thrust"]
POWER_COLUMNS: dict[str, str] = {"throttle": "throttle", "thrust": "thrust_n"}
"""Column name of the second input in CSV files and histories."""


@dataclass(frozen=True)
class Propulsion:
    """Thrust model: Fe = 0.5*rho*S_prop*C_prop*((k_motor*throttle)^2 - V^2), or measured Fe."""

    model: PropulsionKind
    prop_area_m2: float = 0.0
    prop_coefficient: float = 0.0
    motor_constant_mps: float = 0.0

    @property
    def input_name(self) -> PowerInput:
        """What the second input is: the throttle (propeller model) or measured thrust."""
        return "thrust" if self.model == "measured" else "throttle"


@dataclass(frozen=True)
class CoefficientStructure:
    """Which regressors each of CD, CL, Cm has; one estimated parameter per pair."""

    CD: tuple[str, ...]
    CL: tuple[str, ...]
    Cm: tuple[str, ...]

    @property
    def names(self) -> tuple[str, ...]:
        """Parameter names in state order, e.g. ("CD0", "CDa", ..., "Cmde")."""
        return tuple(axis + REGRESSOR_SUFFIX[r] for axis, r in self.pairs)

    @property
    def pairs(self) -> tuple[tuple[str, str], ...]:
        return tuple((axis, r) for axis in AXES for r in getattr(self, axis))

    @property
    def axes(self) -> tuple[str, ...]:
        """Axis ("CD", "CL" or "Cm") of each parameter, in state order."""
        return tuple(axis for axis, _ in self.pairs)


@dataclass(frozen=True)
class Manoeuvre:
    """Elevator excitation around trim: 3-2-1-1 multisteps and pulses (docs/model.md)."""

    duration_s: float = 60.0
    multistep_starts_s: tuple[float, ...] = (2.0, 6.0)
    multistep_unit_s: float = 0.2
    multistep_amplitude_deg: float = 3.0
    pulse_starts_s: tuple[float, ...] = (12.0, 30.0)
    pulse_durations_s: tuple[float, ...] = (2.0, 2.0)
    pulse_amplitudes_deg: tuple[float, ...] = (-3.0, 3.0)


@dataclass(frozen=True)
class Turbulence:
    """Dryden longitudinal gusts (MIL-F-8785C form); intensity 0 turns it off."""

    sigma_u_mps: float = 0.0
    sigma_w_mps: float = 0.0
    length_u_m: float = 200.0
    length_w_m: float = 50.0


@dataclass(frozen=True)
class Sensors:
    """Measurement errors of the simulated aircraft, per observation channel (OBS_NAMES)."""

    noise_sigma: tuple[float, ...]
    """White noise 1 sigma in SI units [m/s, rad, rad, rad/s, rad/s^2, m/s^2, m/s^2]."""
    bias: tuple[float, ...] = (0.0,) * 7
    quantum: tuple[float, ...] = (0.0,) * 7
    """Quantisation step per channel in SI units; 0 for none."""


@dataclass(frozen=True)
class Simulation:
    """Truth simulator settings."""

    sample_rate_hz: float = 50.0
    integration_step_s: float = 0.002
    seed: int = 1
    manoeuvre: Manoeuvre = field(default_factory=Manoeuvre)
    sensors: Sensors = field(
        default_factory=lambda: Sensors(
            noise_sigma=(
                0.3,
                math.radians(0.3),
                math.radians(0.2),
                math.radians(0.1),
                0.05,
                0.2,
                0.2,
            )
        )
    )
    turbulence: Turbulence = field(default_factory=Turbulence)


@dataclass(frozen=True)
class TurbulenceNoise:
    """The filter's model of turbulence: white process noise on V, alpha and theta whose
    level follows a Dryden gust intensity, estimated online from the innovations.

    At vertical gust intensity sigma_w [m/s] (sigma_u = ratio * sigma_w) and airspeed V0,
    the air-relative V and alpha are driven by the derivative of the gusts. Its spectral
    density is at most the white (high-frequency) level of the Dryden filters:

        q_V = 2 sigma_u^2 V0 / L_u,    q_alpha = 3 sigma_w^2 / (L_w V0)

    (per unit sigma_w^2 these are the `unit` densities). Theta gets `theta_density`
    per unit sigma_w^2. Theta has no gust term of its own, but without it the filter
    pins theta to the average of thousands of samples while the colour of the gusts moves
    it (measured: theta errors of 80 of its sigma in light turbulence).
    """

    adaptive: bool
    """Estimate sigma_w^2 online by covariance matching of the V and alpha innovations."""
    sigma_w_mps: float
    """Initial (adaptive) or fixed vertical gust intensity [m/s]."""
    sigma_u_ratio: float
    length_u_m: float
    length_w_m: float
    theta_density: float
    """Theta spectral density per unit sigma_w^2 [rad^2/s per (m/s)^2]."""
    adapt_time_s: float
    """Averaging time of the online estimate [s]."""
    detection_sigma: float
    """The estimated level enters the process noise only while it stands at least this
    many of its standard errors above zero (0: whenever it is positive). Below that the
    air is taken as calm: noise the data cannot tell from zero would only discount them."""

    def unit(self, airspeed_mps: float) -> tuple[float, float, float, float]:
        """Spectral densities of V, alpha, theta, q per unit sigma_w^2."""
        v = airspeed_mps
        return (
            2.0 * self.sigma_u_ratio**2 * v / self.length_u_m,
            3.0 / (self.length_w_m * v),
            self.theta_density,
            0.0,
        )


@dataclass(frozen=True)
class FilterTuning:
    """Filter settings: initial belief, noise models and iteration control."""

    initial_coefficients: tuple[float, ...]
    """Initial estimate of each coefficient (default 0, as in the paper)."""
    initial_state_sigma: tuple[float, ...]
    """1 sigma of the initial V [m/s], alpha [rad], theta [rad], q [rad/s]."""
    initial_coefficient_sigma: tuple[float, ...]
    state_process_noise: tuple[float, ...]
    """Continuous-time spectral density of the state noise, per state [unit^2/s]."""
    coefficient_process_noise: tuple[float, ...]
    """Final (steady) spectral density of the coefficient random walk [1/s]."""
    coefficient_process_noise_initial: tuple[float, ...]
    """Spectral density at t = 0; decays to the final value with time constant below."""
    coefficient_noise_decay_s: float
    measurement_sigma: tuple[float, ...]
    """1 sigma per observation channel, SI units, order OBS_NAMES."""
    iterations: int
    """IEKF measurement-update iterations (1 = EKF; the paper uses 7)."""
    iteration_tolerance: float
    """Early stop when the largest state change of an iteration, in prior sigmas, is below."""
    relinearise_sigma: float
    """The IEKF keeps its iterations only when the first re-linearisation moves some
    component by at least this many EKF-posterior sigmas, else it keeps the EKF update;
    0 = always iterate (the paper). See filters.hybrid.iekf_update."""
    max_step_s: float
    """Longest Runge-Kutta step of the prediction [s]."""
    restart_times_s: tuple[float, ...]
    """Times after the first frame [s] at which both filters re-run all frames so far from
    the start, with their original P0 but the estimate so far as the initial mean (a new
    linearisation point; every measurement is still used once). Empty: never."""
    restart_sigma_inflation: float
    """At a restart the coefficient prior sigma is this times the sigma of the estimate
    restarted from (capped at the initial sigma)."""
    warm_start: WarmStartKind
    """Initial mean at the first restart: "equation-error" (least squares on the frames
    so far) or "filter" (the filter's own estimate)."""
    innovation_gate: float
    """Channels whose normalised innovation exceeds this many sigma are rejected; 0 = off."""
    turbulence: TurbulenceNoise
    """Process noise from turbulence, on top of state_process_noise."""


STREAMED_MESSAGES: tuple[str, ...] = (
    "HIGHRES_IMU",
    "ATTITUDE",
    "AOA_SSA",
    "VFR_HUD",
    "SERVO_OUTPUT_RAW",
    "NAMED_VALUE_FLOAT",
)


@dataclass(frozen=True)
class LinkConfig:
    """How the aircraft's signals map onto MAVLink, and the rates to ask for."""

    elevator_servo: int = 2
    elevator_pwm_center_us: float = 1500.0
    elevator_us_per_rad: float = 500.0 / math.radians(30.0)
    """PWM microseconds per radian of elevator (positive: trailing edge down)."""
    throttle_servo: int = 3
    """SERVO_OUTPUT_RAW channel of the throttle; 0 when thrust comes as a named value."""
    throttle_pwm_min_us: float = 1000.0
    throttle_pwm_max_us: float = 2000.0
    qdot_name: str = "QDOT"
    thrust_name: str = "THRUST"
    rates_hz: tuple[tuple[str, float], ...] = tuple((m, 50.0) for m in STREAMED_MESSAGES)
    """Stream rate per message, asked of the vehicle with SET_MESSAGE_INTERVAL."""
    frame_window_s: float = 0.005
    """Samples whose vehicle times lie this close belong to the same frame."""
    max_wait_s: float = 0.2
    """A partial frame is processed at the latest this long (receive time) after it opened."""

    def rate(self, message: str) -> float:
        return dict(self.rates_hz).get(message, 0.0)

    # The PWM calibration, both ways: the vehicle encodes with it, the station decodes.
    def elevator_pwm(self, elevator_rad: Num) -> Num:
        """SERVO_OUTPUT_RAW microseconds of an elevator deflection [rad] (unrounded)."""
        return self.elevator_pwm_center_us + elevator_rad * self.elevator_us_per_rad

    def elevator_rad(self, pwm_us: Num) -> Num:
        """Elevator deflection [rad] of a SERVO_OUTPUT_RAW value [us]."""
        return (pwm_us - self.elevator_pwm_center_us) / self.elevator_us_per_rad

    def throttle_pwm(self, throttle: Num) -> Num:
        """SERVO_OUTPUT_RAW microseconds of a throttle setting in [0, 1] (unrounded)."""
        return self.throttle_pwm_min_us + throttle * (
            self.throttle_pwm_max_us - self.throttle_pwm_min_us
        )

    def throttle(self, pwm_us: Num) -> Num:
        """Throttle setting of a SERVO_OUTPUT_RAW value [us]."""
        return (pwm_us - self.throttle_pwm_min_us) / (
            self.throttle_pwm_max_us - self.throttle_pwm_min_us
        )


VIEW_OUTPUTS: tuple[str, ...] = ("auto", "save", "serve", "spawn", "connect", "off")
"""Where the live Rerun view goes; see ViewConfig."""


@dataclass(frozen=True)
class ViewConfig:
    """The live Rerun view: where it goes and how much of it is kept.

    outputs: "save" (an .rrd file), "serve" (host a gRPC server that viewers join at any
    time and receive the history so far), "spawn" (start a local viewer), "connect" (stream
    to a viewer already running at connect_url), "off", or "auto": spawn and save where a
    display exists, else save (and say how to open the file).
    """

    outputs: tuple[str, ...] = ("auto",)
    rrd_path: str = ""
    """The .rrd to save to; empty: a name from the session in the results directory."""
    serve_bind: str = "127.0.0.1"
    """Address the gRPC server binds; "0.0.0.0" lets viewers on other machines join."""
    serve_port: int = 9877
    server_memory_limit: str = "1GiB"
    """History the server keeps for late viewers; the oldest goes first (never static data)."""
    connect_url: str = "rerun+http://127.0.0.1:9876/proxy"
    viewer_port: int = 9876
    """Port of the viewer that "spawn" starts."""
    display_rate_hz: float = 25.0
    """Display-only series (states, inputs, innovations, NIS) are decimated to this rate;
    coefficient estimates and their bands are always logged at every frame."""
    flush_interval_s: float = 1.0
    """Wall-clock seconds between batches sent to the view."""
    results_interval_s: float = 5.0
    """Wall-clock seconds between updates of the live results table."""
    shutdown_timeout_s: float = 3.0
    """At exit, how long a viewer connection may take to drain before it is cut."""


@dataclass(frozen=True)
class AircraftConfig:
    """Everything one airframe needs: physics, structure, truth (if simulated), tuning."""

    source: str
    airframe: Airframe
    propulsion: Propulsion
    structure: CoefficientStructure
    truth: tuple[float, ...] | None
    """True coefficients (simulation) or accepted reference values, in structure order."""
    truth_label: str
    simulation: Simulation
    filter: FilterTuning
    link: LinkConfig
    view: ViewConfig
    raw: Mapping[str, Any]
    """The parsed TOML, kept to write into results exactly as used."""

    @property
    def coefficient_names(self) -> tuple[str, ...]:
        return self.structure.names

    def with_truth(self, truth: tuple[float, ...], label: str | None = None) -> AircraftConfig:
        """The same aircraft with other true (or reference) coefficients."""
        from dataclasses import replace

        if len(truth) != len(self.coefficient_names):
            raise ConfigError(f"{self.source}: truth needs {len(self.coefficient_names)} values")
        return replace(
            self,
            truth=tuple(float(v) for v in truth),
            truth_label=self.truth_label if label is None else label,
        )


# --------------------------------------------------------------------------- reading


class _Section:
    """A TOML table with the file name and table path, for precise error messages."""

    def __init__(self, source: str, path: str, data: Mapping[str, Any]) -> None:
        self.source = source
        self.path = path
        self.data = data
        self.used: set[str] = set()

    def where(self, key: str) -> str:
        return f"{self.source}: [{self.path}] {key}" if self.path else f"{self.source}: {key}"

    def fail(self, key: str, message: str) -> ConfigError:
        return ConfigError(f"{self.where(key)}: {message}")

    def has(self, key: str) -> bool:
        return key in self.data

    def sub(self, key: str, required: bool = False) -> _Section:
        self.used.add(key)
        value = self.data.get(key)
        if value is None:
            if required:
                raise self.fail(key, "missing table")
            value = {}
        if not isinstance(value, Mapping):
            raise self.fail(key, f"must be a table, got {value!r}")
        path = f"{self.path}.{key}" if self.path else key
        return _Section(self.source, path, value)

    def number(
        self,
        key: str,
        default: float | None = None,
        *,
        positive: bool = False,
        nonnegative: bool = False,
    ) -> float:
        self.used.add(key)
        if key not in self.data:
            if default is None:
                raise self.fail(key, "missing; add it (a number)")
            return default
        value = self.data[key]
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.fail(key, f"must be a number, got {value!r}")
        value = float(value)
        if not math.isfinite(value):
            raise self.fail(key, f"must be finite, got {value!r}")
        if positive and value <= 0:
            raise self.fail(key, f"must be a number > 0, got {value!r}")
        if nonnegative and value < 0:
            raise self.fail(key, f"must be a number >= 0, got {value!r}")
        return value

    def integer(self, key: str, default: int, *, minimum: int = 0) -> int:
        self.used.add(key)
        value = self.data.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.fail(key, f"must be a whole number, got {value!r}")
        if value < minimum:
            raise self.fail(key, f"must be >= {minimum}, got {value!r}")
        return value

    def boolean(self, key: str, default: bool) -> bool:
        self.used.add(key)
        value = self.data.get(key, default)
        if not isinstance(value, bool):
            raise self.fail(key, f"must be true or false, got {value!r}")
        return value

    def string(self, key: str, default: str | None = None, allowed: tuple[str, ...] = ()) -> str:
        self.used.add(key)
        if key not in self.data:
            if default is None:
                raise self.fail(key, "missing; add it (a string)")
            return default
        value = self.data[key]
        if not isinstance(value, str):
            raise self.fail(key, f"must be a string, got {value!r}")
        if allowed and value not in allowed:
            raise self.fail(
                key, f"must be one of {', '.join(repr(a) for a in allowed)}, got {value!r}"
            )
        return value

    def numbers(
        self,
        key: str,
        default: tuple[float, ...] | None = None,
        *,
        length: int | None = None,
        nonnegative: bool = False,
    ) -> tuple[float, ...]:
        self.used.add(key)
        if key not in self.data:
            if default is None:
                raise self.fail(key, "missing; add it (a list of numbers)")
            return default
        value = self.data[key]
        if not isinstance(value, list) or not all(
            isinstance(v, int | float) and not isinstance(v, bool) for v in value
        ):
            raise self.fail(key, f"must be a list of numbers, got {value!r}")
        out = tuple(float(v) for v in value)
        if length is not None and len(out) != length:
            raise self.fail(key, f"must have {length} values, got {len(out)}")
        if not all(math.isfinite(v) for v in out):
            raise self.fail(key, "values must be finite")
        if nonnegative and any(v < 0 for v in out):
            raise self.fail(key, f"values must be >= 0, got {list(out)}")
        return out

    def strings(
        self, key: str, allowed: tuple[str, ...], what: str = "regressor"
    ) -> tuple[str, ...]:
        self.used.add(key)
        if key not in self.data:
            raise self.fail(key, f"missing; add a list drawn from {list(allowed)}")
        value = self.data[key]
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise self.fail(key, f"must be a list of strings, got {value!r}")
        for v in value:
            if v not in allowed:
                raise self.fail(key, f"unknown {what} {v!r}; allowed: {list(allowed)}")
        if len(set(value)) != len(value):
            raise self.fail(key, f"lists a {what} twice: {value!r}")
        return tuple(value)

    def per_name(
        self,
        names: tuple[str, ...],
        default: float | None,
        *,
        nonnegative: bool = False,
        positive: bool = False,
    ) -> tuple[float, ...]:
        """One number per name; a key "default" supplies the missing ones."""
        fallback = (
            self.number("default", default, nonnegative=nonnegative, positive=positive)
            if (self.has("default") or default is not None)
            else None
        )
        out = []
        for name in names:
            if name in self.data:
                out.append(self.number(name, nonnegative=nonnegative, positive=positive))
            elif fallback is not None:
                out.append(fallback)
            else:
                raise self.fail(name, "missing; give a value for it or a 'default'")
        return tuple(out)

    def check_unknown(self, also_allowed: tuple[str, ...] = ()) -> None:
        unknown = sorted(set(self.data) - self.used - set(also_allowed))
        if unknown:
            known = sorted(self.used | set(also_allowed))
            raise self.fail(unknown[0], f"unknown key; known keys here: {known}")


def _read_toml(path: str | Path) -> dict[str, Any]:
    source = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{source}: cannot read: {exc.strerror}") from exc
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{source}: not valid TOML: {exc}") from exc


def load_reference(path: str | Path, names: tuple[str, ...]) -> tuple[tuple[float, ...], str]:
    """Reference coefficient values (a textbook, a wind tunnel) from a TOML file: a
    [truth] table like the aircraft config's, or the same keys at the top level. Returns
    (values in structure order, label)."""
    data = _read_toml(path)
    top = _Section(str(path), "", data)
    table = top.sub("truth") if top.has("truth") else top
    label = table.string("label", "reference")
    values = tuple(table.number(n) for n in names)
    table.check_unknown()
    if table is not top:
        top.check_unknown()
    return values, label


def load_config(path: str | Path) -> AircraftConfig:
    """Read and validate an aircraft TOML file."""
    return parse_config(_read_toml(path), str(path))


def parse_config(data: Mapping[str, Any], source: str = "<config>") -> AircraftConfig:
    """Validate a parsed TOML mapping (see configs/noc_uav.toml for every key)."""
    top = _Section(source, "", data)
    airframe = _parse_airframe(top.sub("airframe", required=True))
    propulsion = _parse_propulsion(top.sub("propulsion", required=True))
    structure = _parse_structure(top.sub("coefficients", required=True))
    names = structure.names

    truth: tuple[float, ...] | None = None
    truth_label = "truth"
    if top.has("truth"):
        t = top.sub("truth")
        truth_label = t.string("label", "truth")
        truth = tuple(t.number(n) for n in names)
        t.check_unknown()

    simulation = _parse_simulation(top.sub("simulation"))
    tuning = _parse_filter(top.sub("filter"), names)
    link = _parse_link(top.sub("link"), propulsion)
    view = _parse_view(top.sub("view"))
    top.check_unknown()
    return AircraftConfig(
        source=source,
        airframe=airframe,
        propulsion=propulsion,
        structure=structure,
        truth=truth,
        truth_label=truth_label,
        simulation=simulation,
        filter=tuning,
        link=link,
        view=view,
        raw=dict(data),
    )


def _parse_link(s: _Section, propulsion: Propulsion) -> LinkConfig:
    d = LinkConfig()
    rates = s.sub("rates_hz")
    rate_values = tuple(
        (m, rates.number(m, dict(d.rates_hz)[m], nonnegative=True)) for m in STREAMED_MESSAGES
    )
    rates.check_unknown()
    link = LinkConfig(
        elevator_servo=s.integer("elevator_servo", d.elevator_servo, minimum=1),
        elevator_pwm_center_us=s.number("elevator_pwm_center_us", d.elevator_pwm_center_us),
        elevator_us_per_rad=s.number("elevator_us_per_rad", d.elevator_us_per_rad),
        throttle_servo=s.integer(
            "throttle_servo", 0 if propulsion.model == "measured" else d.throttle_servo
        ),
        throttle_pwm_min_us=s.number("throttle_pwm_min_us", d.throttle_pwm_min_us),
        throttle_pwm_max_us=s.number("throttle_pwm_max_us", d.throttle_pwm_max_us),
        qdot_name=s.string("qdot_name", d.qdot_name),
        thrust_name=s.string("thrust_name", d.thrust_name),
        rates_hz=rate_values,
        frame_window_s=s.number("frame_window_s", d.frame_window_s, positive=True),
        max_wait_s=s.number("max_wait_s", d.max_wait_s, positive=True),
    )
    if link.elevator_us_per_rad == 0:
        raise s.fail("elevator_us_per_rad", "must not be 0")
    if link.throttle_servo > 16 or link.elevator_servo > 16:
        raise s.fail("throttle_servo", "SERVO_OUTPUT_RAW has channels 1..16")
    if link.throttle_servo and link.throttle_pwm_max_us <= link.throttle_pwm_min_us:
        raise s.fail("throttle_pwm_max_us", "must be greater than throttle_pwm_min_us")
    for key in (link.qdot_name, link.thrust_name):
        if not 0 < len(key) <= 10:
            raise s.fail("qdot_name", f"NAMED_VALUE_FLOAT names are 1..10 characters, got {key!r}")
    s.check_unknown()
    return link


def _parse_view(s: _Section) -> ViewConfig:
    d = ViewConfig()
    outputs = d.outputs
    if s.has("outputs"):
        outputs = s.strings("outputs", VIEW_OUTPUTS, what="output")
    view = ViewConfig(
        outputs=outputs,
        rrd_path=s.string("rrd_path", d.rrd_path),
        serve_bind=s.string("serve_bind", d.serve_bind),
        serve_port=s.integer("serve_port", d.serve_port, minimum=1),
        server_memory_limit=s.string("server_memory_limit", d.server_memory_limit),
        connect_url=s.string("connect_url", d.connect_url),
        viewer_port=s.integer("viewer_port", d.viewer_port, minimum=1),
        display_rate_hz=s.number("display_rate_hz", d.display_rate_hz, positive=True),
        flush_interval_s=s.number("flush_interval_s", d.flush_interval_s, positive=True),
        results_interval_s=s.number("results_interval_s", d.results_interval_s, positive=True),
        shutdown_timeout_s=s.number("shutdown_timeout_s", d.shutdown_timeout_s, positive=True),
    )
    if view.serve_port > 65535 or view.viewer_port > 65535:
        raise s.fail("serve_port", "ports are 1..65535")
    if not view.connect_url.startswith(("rerun://", "rerun+http://", "rerun+https://")):
        raise s.fail(
            "connect_url",
            f"must look like rerun+http://HOST:PORT/proxy, got {view.connect_url!r}",
        )
    s.check_unknown()
    return view


def _parse_airframe(s: _Section) -> Airframe:
    airframe = Airframe(
        name=s.string("name", "aircraft"),
        mass_kg=s.number("mass_kg", positive=True),
        wing_area_m2=s.number("wing_area_m2", positive=True),
        mean_chord_m=s.number("mean_chord_m", positive=True),
        inertia_yy_kgm2=s.number("inertia_yy_kgm2", positive=True),
        air_density_kgpm3=s.number("air_density_kgpm3", positive=True),
        gravity_mps2=s.number("gravity_mps2", 9.80665, positive=True),
        trim_airspeed_mps=s.number("trim_airspeed_mps", positive=True),
        thrust_inclination_rad=s.number("thrust_inclination_rad", 0.0),
        thrust_moment_arm_m=s.number("thrust_moment_arm_m", 0.0),
    )
    s.check_unknown()
    return airframe


def _parse_propulsion(s: _Section) -> Propulsion:
    kind = s.string("model", allowed=("propeller", "measured"))
    if kind == "propeller":
        prop = Propulsion(
            model="propeller",
            prop_area_m2=s.number("prop_area_m2", positive=True),
            prop_coefficient=s.number("prop_coefficient", positive=True),
            motor_constant_mps=s.number("motor_constant_mps", positive=True),
        )
    else:
        prop = Propulsion(model="measured")
    s.check_unknown()
    return prop


def _parse_structure(s: _Section) -> CoefficientStructure:
    structure = CoefficientStructure(
        CD=s.strings("CD", REGRESSORS),
        CL=s.strings("CL", REGRESSORS),
        Cm=s.strings("Cm", REGRESSORS),
    )
    s.check_unknown()
    if not structure.names:
        raise s.fail("CD", "no coefficient to estimate; list at least one regressor")
    return structure


def _parse_simulation(s: _Section) -> Simulation:
    defaults = Simulation()
    m = s.sub("manoeuvre")
    dm = defaults.manoeuvre
    pulse_starts = m.numbers("pulse_starts_s", dm.pulse_starts_s, nonnegative=True)
    manoeuvre = Manoeuvre(
        duration_s=m.number("duration_s", dm.duration_s, positive=True),
        multistep_starts_s=m.numbers("multistep_starts_s", dm.multistep_starts_s, nonnegative=True),
        multistep_unit_s=m.number("multistep_unit_s", dm.multistep_unit_s, positive=True),
        multistep_amplitude_deg=m.number("multistep_amplitude_deg", dm.multistep_amplitude_deg),
        pulse_starts_s=pulse_starts,
        pulse_durations_s=m.numbers(
            "pulse_durations_s", dm.pulse_durations_s, length=len(pulse_starts), nonnegative=True
        ),
        pulse_amplitudes_deg=m.numbers(
            "pulse_amplitudes_deg", dm.pulse_amplitudes_deg, length=len(pulse_starts)
        ),
    )
    m.check_unknown()

    se = s.sub("sensors")
    ds = defaults.sensors
    sensors = Sensors(
        noise_sigma=_channels(se.sub("noise_sigma"), ds.noise_sigma, nonnegative=True),
        bias=_channels(se.sub("bias"), ds.bias),
        quantum=_channels(se.sub("quantum"), ds.quantum, nonnegative=True),
    )
    se.check_unknown()

    tu = s.sub("turbulence")
    preset = tu.string("preset", "none", allowed=("none", "light", "moderate", "custom"))
    # MIL-F-8785C low altitude: sigma_w = 0.1*W20, W20 = 15 kt (light) or 30 kt (moderate).
    w20 = {"none": 0.0, "light": 7.72, "moderate": 15.43, "custom": 0.0}[preset]
    sigma_w = 0.1 * w20
    turbulence = Turbulence(
        sigma_w_mps=tu.number("sigma_w_mps", sigma_w, nonnegative=True),
        sigma_u_mps=tu.number("sigma_u_mps", sigma_w * 1.5, nonnegative=True),
        length_u_m=tu.number("length_u_m", 200.0, positive=True),
        length_w_m=tu.number("length_w_m", 50.0, positive=True),
    )
    tu.check_unknown()

    sim = Simulation(
        sample_rate_hz=s.number("sample_rate_hz", defaults.sample_rate_hz, positive=True),
        integration_step_s=s.number(
            "integration_step_s", defaults.integration_step_s, positive=True
        ),
        seed=s.integer("seed", defaults.seed),
        manoeuvre=manoeuvre,
        sensors=sensors,
        turbulence=turbulence,
    )
    s.check_unknown()
    return sim


def _channels(
    s: _Section, default: tuple[float, ...], *, nonnegative: bool = False
) -> tuple[float, ...]:
    """Per-observation-channel values; angles may be given in degrees with a _deg key."""
    out = list(default)
    for i, name in enumerate(OBS_NAMES):
        if s.has(name):
            out[i] = s.number(name, nonnegative=nonnegative)
        elif s.has(name + "_deg"):
            out[i] = math.radians(s.number(name + "_deg", nonnegative=nonnegative))
    s.check_unknown()
    return tuple(out)


def _parse_filter(s: _Section, names: tuple[str, ...]) -> FilterTuning:
    p = len(names)
    init = s.sub("initial_coefficients")
    initial = init.per_name(names, 0.0)
    init.check_unknown(("default",))

    isig = s.sub("initial_sigma")
    state_sigma = tuple(
        isig.number(n, d, positive=True)
        for n, d in zip(STATE_NAMES, (1.0, 0.02, 0.02, 0.02), strict=True)
    )
    coeff_sigma_sec = isig.sub("coefficients")
    coeff_sigma = coeff_sigma_sec.per_name(names, 10.0, positive=True)
    coeff_sigma_sec.check_unknown(("default",))
    isig.check_unknown()

    qn = s.sub("process_noise")
    state_q = tuple(
        qn.number(n, d, nonnegative=True)
        for n, d in zip(STATE_NAMES, (0.05, 1e-4, 1e-6, 1e-3), strict=True)
    )
    cq = qn.sub("coefficients")
    coeff_q = cq.per_name(names, 1e-8, nonnegative=True)
    cq.check_unknown(("default",))
    cq0 = qn.sub("coefficients_initial")
    coeff_q0 = cq0.per_name(names, None, nonnegative=True) if cq0.data else coeff_q
    cq0.check_unknown(("default",))
    decay = qn.number("coefficient_decay_s", 5.0, positive=True)
    qn.check_unknown()

    ms = s.sub("measurement_sigma")
    meas = _channels(ms, Simulation().sensors.noise_sigma, nonnegative=True)
    if any(v <= 0 for v in meas):
        bad = OBS_NAMES[[v <= 0 for v in meas].index(True)]
        raise ms.fail(bad, "must be > 0 (a channel with no noise makes the update singular)")

    tn = s.sub("turbulence")
    turbulence = TurbulenceNoise(
        adaptive=tn.boolean("adaptive", True),
        sigma_w_mps=tn.number("sigma_w_mps", 0.0, nonnegative=True),
        sigma_u_ratio=tn.number("sigma_u_ratio", 1.5, positive=True),
        length_u_m=tn.number("length_u_m", 200.0, positive=True),
        length_w_m=tn.number("length_w_m", 50.0, positive=True),
        theta_density=tn.number("theta_density", 1.7e-6, nonnegative=True),
        adapt_time_s=tn.number("adapt_time_s", 2.0, positive=True),
        detection_sigma=tn.number("detection_sigma", 3.0, nonnegative=True),
    )
    tn.check_unknown()

    restarts = s.numbers("restart_times_s", (), nonnegative=True)
    if list(restarts) != sorted(set(restarts)):
        raise s.fail("restart_times_s", f"must be strictly increasing, got {list(restarts)}")
    warm = s.string("warm_start", "equation-error", allowed=("equation-error", "filter"))
    tuning = FilterTuning(
        initial_coefficients=initial,
        initial_state_sigma=state_sigma,
        initial_coefficient_sigma=coeff_sigma,
        state_process_noise=state_q,
        coefficient_process_noise=coeff_q,
        coefficient_process_noise_initial=coeff_q0,
        coefficient_noise_decay_s=decay,
        measurement_sigma=meas,
        iterations=s.integer("iterations", 7, minimum=1),
        iteration_tolerance=s.number("iteration_tolerance", 0.0, nonnegative=True),
        relinearise_sigma=s.number("relinearise_sigma", 1.0, nonnegative=True),
        max_step_s=s.number("max_step_s", 0.02, positive=True),
        restart_times_s=restarts,
        warm_start="filter" if warm == "filter" else "equation-error",
        restart_sigma_inflation=s.number("restart_sigma_inflation", 10.0, positive=True),
        innovation_gate=s.number("innovation_gate", 0.0, nonnegative=True),
        turbulence=turbulence,
    )
    s.check_unknown()
    assert len(tuning.initial_coefficients) == p
    return tuning


def apply_overrides(data: Mapping[str, Any], overrides: list[str], source: str) -> dict[str, Any]:
    """Apply command-line overrides "table.key=value" (value in TOML syntax) to parsed TOML.

    Example: ``filter.iterations=3``, ``filter.restart_times_s=[4.0]``,
    ``simulation.turbulence.preset="light"`` (a bare word is taken as a string).
    """
    out: dict[str, Any] = _deep_copy(data)
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE, e.g. filter.iterations=3")
        key, text = item.split("=", 1)
        parts = key.strip().split(".")
        try:
            value = tomllib.loads(f"v = {text.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            value = text.strip()
        node = out
        for part in parts[:-1]:
            nxt = node.setdefault(part, {})
            if not isinstance(nxt, dict):
                raise ConfigError(f"{source}: --set {key}: {part!r} is not a table")
            node = nxt
        node[parts[-1]] = value
    return out


def _deep_copy(data: Mapping[str, Any]) -> dict[str, Any]:
    return {k: _deep_copy(v) if isinstance(v, Mapping) else v for k, v in data.items()}


def load_config_with(path: str | Path, overrides: list[str] | None = None) -> AircraftConfig:
    """load_config plus command-line overrides (see apply_overrides)."""
    if not overrides:
        return load_config(path)
    base = load_config(path)
    return parse_config(apply_overrides(base.raw, overrides, str(path)), str(path))
