"""The simulated flight written as real autopilots write theirs: an ArduPlane MAVLink
stream (ardupilot.py; live and .tlog), an ArduPilot DataFlash .bin (dataflash.py) and a
PX4 .ulg (ulog.py). Each format is filled from one FlightRecord: the simulator's samples
plus what a real vehicle also reports (position, baro, attitude quaternion), derived
here once. Rates, units and their sources: docs/decisions/0040.

Beside each file, its truth side file (truth_path) holds the coefficients the vehicle
flew, as `gcs-sim --truth` writes them (`--truth FILE` reads it).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import FlightAirframe, LinkConfig, truths_text
from gcs_estimator.ingest.flightdata import Recording
from gcs_estimator.ingest.telemetry import pwm
from gcs_estimator.model import atmosphere

GRAVITY_MSS = 9.80665
"""ArduPilot's GRAVITY_MSS (AP_Math/definitions.h), also PX4's CONSTANTS_ONE_G."""
SEA_LEVEL_PA = 101325.0
SEA_LEVEL_DENSITY = 1.225
"""ArduPilot's SSL_AIR_DENSITY: its EAS2TAS = sqrt(1.225 / rho)."""
GAS_CONSTANT_AIR = 287.26
"""ArduPilot's ISA_GAS_CONSTANT [J/(kg K)] (AP_Baro's ground temperature). Not the air's:
the temperature a probe reads is p / (rho R_AIR) with the physical constant
(atmosphere.R_AIR), else a reader's density is 0.07 % off the flown one (decision 0045)."""
HOME_LAT_DEG, HOME_LON_DEG, HOME_ALT_M = 50.8930, -1.3950, 20.0
"""Where the simulated flights start: the National Oceanography Centre, Southampton."""
START_HEIGHT_M = 150.0
"""Height above home when the record starts [m]."""
EARTH_RADIUS_M = 6378137.0
SURFACE_HALF_RANGE_US = 500.0
"""PWM from trim to either end of the elevator servo's range [us] (SERVOn_MIN/MAX)."""


@dataclass(frozen=True)
class FlightRecord:
    """One vehicle's flight at the sample rate, in SI units, everything a format writes.

    Body axes forward-right-down. flight_record's flight is wings level heading north
    (roll and yaw 0), so the pitch plane is the north-down plane: position and velocity
    come from the measured V, alpha and theta (gamma = theta - alpha, integrated); the
    air is still apart from the simulator's gusts (not reported: wind 0) and of constant
    density, so pressure falls with height as rho g h and the temperature follows
    p / (rho R). A flight that turns (benchmarks/jsbsim_missions.py) gives the lateral
    fields after `boot_s` as well: bank, heading, roll and yaw rate, lateral
    acceleration, east position and velocity, the autopilot's wind estimate; None
    reads as 0 (the lateral properties below).
    """

    t_s: FloatArray
    elevator_rad: FloatArray
    """Positive trailing edge down (the simulator's sign)."""
    elevator_pwm: FloatArray
    """SERVO_OUTPUT_RAW microseconds on the link's elevator servo (whole numbers)."""
    elevator_out: FloatArray
    """Normalised elevator command -1..1, positive nose-up (ArduPlane's and PX4's sign)."""
    power: FloatArray
    """Throttle 0..1 (propeller model) or thrust [N] (measured)."""
    throttle_pwm: FloatArray
    V: FloatArray
    alpha: FloatArray
    theta: FloatArray
    q: FloatArray
    qdot: FloatArray
    a_x: FloatArray
    a_z: FloatArray
    north_m: FloatArray
    height_m: FloatArray
    """Above home [m]."""
    v_north: FloatArray
    v_down: FloatArray
    pressure_pa: FloatArray
    temperature_c: FloatArray
    density: float | FloatArray
    """The air's density [kg/m^3]: one value, or one per sample."""
    link: LinkConfig
    throttle_model: bool
    """power is a throttle setting (else a measured thrust)."""
    system_id: int = 1
    boot_s: float = 5.0
    """Vehicle uptime at the first sample [s]: every format's clock starts here."""
    phi: FloatArray | None = None
    """Bank angle [rad] (None: wings level)."""
    psi: FloatArray | None = None
    """Heading [rad] (None: north)."""
    p: FloatArray | None = None
    r: FloatArray | None = None
    """Roll and yaw rate [rad/s]."""
    a_y: FloatArray | None = None
    """Lateral specific force [m/s^2]."""
    east_m: FloatArray | None = None
    v_east: FloatArray | None = None
    wind_north: FloatArray | None = None
    wind_east: FloatArray | None = None
    """The wind the autopilot's EKF reports, the air's velocity over the ground [m/s]."""
    name: str = "the NOC UAV"
    """What flew, for the logs' text messages."""

    def __len__(self) -> int:
        return len(self.t_s)

    @property
    def time_us(self) -> np.ndarray:
        """Microseconds since the vehicle booted, per sample (uint64)."""
        rel = self.t_s - self.t_s[0] + self.boot_s
        return np.asarray(np.round(rel * 1e6), dtype=np.uint64)

    @property
    def sample_rate_hz(self) -> float:
        return float((len(self.t_s) - 1) / (self.t_s[-1] - self.t_s[0])) if len(self) > 1 else 1.0

    @property
    def elevator_travel_rad(self) -> float:
        """The surface's deflection at full output (SURFACE_HALF_RANGE_US of PWM)."""
        return SURFACE_HALF_RANGE_US / abs(self.link.elevator_us_per_rad)

    @property
    def throttle_fraction(self) -> FloatArray:
        """Throttle 0..1 (0 where the power is a measured thrust)."""
        if not self.throttle_model:
            return np.zeros_like(self.power)
        return np.clip(self.power, 0.0, 1.0)

    def _or_zero(self, values: FloatArray | None) -> FloatArray:
        return np.zeros_like(self.t_s) if values is None else values

    @property
    def roll(self) -> FloatArray:
        return self._or_zero(self.phi)

    @property
    def yaw(self) -> FloatArray:
        return self._or_zero(self.psi)

    @property
    def roll_rate(self) -> FloatArray:
        return self._or_zero(self.p)

    @property
    def yaw_rate(self) -> FloatArray:
        return self._or_zero(self.r)

    @property
    def accel_y(self) -> FloatArray:
        return self._or_zero(self.a_y)

    @property
    def east(self) -> FloatArray:
        return self._or_zero(self.east_m)

    @property
    def vel_east(self) -> FloatArray:
        return self._or_zero(self.v_east)

    @property
    def wind_n(self) -> FloatArray:
        return self._or_zero(self.wind_north)

    @property
    def wind_e(self) -> FloatArray:
        return self._or_zero(self.wind_east)

    @property
    def ground_speed(self) -> FloatArray:
        """Horizontal speed over the ground [m/s]."""
        return np.hypot(self.v_north, self.vel_east)

    @property
    def course_deg(self) -> FloatArray:
        """Course over the ground [deg, 0..360)."""
        return np.degrees(np.arctan2(self.vel_east, self.v_north)) % 360.0

    @property
    def heading_deg(self) -> FloatArray:
        """Heading [deg, 0..360)."""
        return np.degrees(self.yaw) % 360.0

    @property
    def lat_deg(self) -> FloatArray:
        return HOME_LAT_DEG + np.degrees(self.north_m / EARTH_RADIUS_M)

    @property
    def lon_deg(self) -> FloatArray:
        scale = EARTH_RADIUS_M * math.cos(math.radians(HOME_LAT_DEG))
        return HOME_LON_DEG + np.degrees(self.east / scale)

    @property
    def alt_msl_m(self) -> FloatArray:
        return HOME_ALT_M + self.height_m

    @property
    def rho(self) -> FloatArray:
        """The air's density at each sample [kg/m^3]."""
        return np.broadcast_to(np.asarray(self.density, float), self.t_s.shape)

    @property
    def eas(self) -> FloatArray:
        """Equivalent airspeed [m/s] (= true at sea-level density)."""
        return np.asarray(self.V * np.sqrt(self.rho / SEA_LEVEL_DENSITY))


def flight_record(
    rec: Recording,
    link: LinkConfig,
    density: float,
    system_id: int = 1,
    boot_s: float = 5.0,
) -> FlightRecord:
    """The recording with everything the formats derive from it. Missing samples (NaN)
    are held from the last good one: a log has a value in every record."""
    y = _held(np.asarray(rec.measurements, float))
    u = _held(np.asarray(rec.inputs[:, :2], float))
    t = np.asarray(rec.t_s, float)
    V, alpha, theta = y[:, 0], y[:, 1], y[:, 2]
    gamma = theta - alpha
    v_north, v_down = V * np.cos(gamma), -V * np.sin(gamma)
    north = _integral(t, v_north)
    height = START_HEIGHT_M - _integral(t, v_down)
    pressure = SEA_LEVEL_PA - density * GRAVITY_MSS * (HOME_ALT_M + height)
    temperature = pressure / (density * atmosphere.R_AIR) - 273.15
    e_pwm = np.round(pwm.elevator_pwm(link, u[:, 0]))
    throttle_model = rec.power == "throttle"
    t_pwm = (
        np.round(pwm.throttle_pwm(link, np.clip(u[:, 1], 0.0, 1.0)))
        if throttle_model and link.throttle_servo
        else np.zeros(len(t))
    )
    sign = 1.0 if link.elevator_us_per_rad > 0 else -1.0
    return FlightRecord(
        t_s=t,
        elevator_rad=u[:, 0],
        elevator_pwm=e_pwm,
        elevator_out=-sign * (e_pwm - link.elevator_pwm_center_us) / SURFACE_HALF_RANGE_US,
        power=u[:, 1],
        throttle_pwm=t_pwm,
        V=V,
        alpha=alpha,
        theta=theta,
        q=y[:, 3],
        qdot=y[:, 4],
        a_x=y[:, 5],
        a_z=y[:, 6],
        north_m=north,
        height_m=height,
        v_north=v_north,
        v_down=v_down,
        pressure_pa=pressure,
        temperature_c=temperature,
        density=density,
        link=link,
        throttle_model=throttle_model,
        system_id=system_id,
        boot_s=boot_s,
    )


def _held(a: FloatArray) -> FloatArray:
    """NaN entries replaced by the last finite value of their column (0 before any)."""
    out = np.array(a, float)
    for j in range(out.shape[1]):
        col = out[:, j]
        bad = ~np.isfinite(col)
        if bad.any():
            idx = np.where(bad, 0, np.arange(len(col)))
            np.maximum.accumulate(idx, out=idx)
            col[:] = np.where(np.isfinite(col[idx]), col[idx], 0.0)
    return out


def _integral(t: FloatArray, v: FloatArray) -> FloatArray:
    """Trapezoidal running integral of v over t, 0 at the first sample."""
    out = np.zeros_like(v)
    if len(v) > 1:
        out[1:] = np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(t))
    return out


def every(t_s: FloatArray, interval_s: float) -> np.ndarray:
    """Indices of the samples a logger with this minimum interval keeps: the first, then
    each sample at least interval_s after the last kept (0: every sample)."""
    if interval_s <= 0 or len(t_s) == 0:
        return np.arange(len(t_s))
    dt = float(np.median(np.diff(t_s))) if len(t_s) > 1 else interval_s
    step = max(1, math.ceil(interval_s / dt - 1e-6))
    if np.allclose(np.diff(t_s), dt, rtol=1e-6, atol=1e-9):
        return np.arange(0, len(t_s), step)
    kept, last = [], -math.inf
    for i, t in enumerate(t_s):
        if t - last >= interval_s - 1e-9:
            kept.append(i)
            last = t
    return np.array(kept, dtype=int)


def quaternion(
    theta: FloatArray, phi: FloatArray | None = None, psi: FloatArray | None = None
) -> FloatArray:
    """[N x 4] Hamilton quaternion (w, x, y, z) body to NED of the Euler angles (yaw psi,
    pitch theta, roll phi; None: 0)."""
    th = 0.5 * np.asarray(theta, float)
    ph = np.zeros_like(th) if phi is None else 0.5 * np.asarray(phi, float)
    ps = np.zeros_like(th) if psi is None else 0.5 * np.asarray(psi, float)
    cr, sr, cp, sp, cy, sy = np.cos(ph), np.sin(ph), np.cos(th), np.sin(th), np.cos(ps), np.sin(ps)
    return np.column_stack(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ]
    )


def body_vector(
    fr: FlightRecord, ned: tuple[float, float, float]
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """A fixed NED vector (Earth's field) in body axes at each sample: (x, y, z)."""
    phi, theta, psi = fr.roll, fr.theta, fr.yaw
    n, e, d = ned
    # Rotate by yaw, then pitch, then roll (NED to body).
    x1 = np.cos(psi) * n + np.sin(psi) * e
    y1 = -np.sin(psi) * n + np.cos(psi) * e
    x = np.cos(theta) * x1 - np.sin(theta) * d
    z2 = np.sin(theta) * x1 + np.cos(theta) * d
    y = np.cos(phi) * y1 + np.sin(phi) * z2
    z = -np.sin(phi) * y1 + np.cos(phi) * z2
    return x, y, z


def truth_path(path: str | Path) -> Path:
    """The truth side file that accompanies a written flight, where the station looks for
    it: the flight's path with the suffix .truth.toml (flight.bin: flight.truth.toml)."""
    return Path(path).with_suffix(".truth.toml")


def write_truth(
    path: str | Path,
    truths: Mapping[int, tuple[float, ...]],
    names: tuple[str, ...],
    airframe: FlightAirframe | None = None,
) -> Path:
    """Write the truth side file of `path` (truths by system id, and the airframe file the
    flight was flown with, so that a replay needs no --config); returns its path."""
    side = truth_path(path)
    side.write_text(truths_text(truths, names, airframe), encoding="utf-8")
    return side


def numbered(path: str | Path, index: int, count: int) -> Path:
    """Vehicle index's file (1-based) of `count`: the path itself for one vehicle, else
    with _INDEX before the suffix (flight.bin -> flight_2.bin)."""
    p = Path(path)
    return p if count == 1 else p.with_name(f"{p.stem}_{index}{p.suffix}")


OUTPUTS_REFERENCE = """
## Outputs

`gcs-sim` streams each vehicle's flight over MAVLink (`--target`) and can write it as a
ground station or an autopilot would (docs/decisions/0040 gives the rates, units and
their sources):

| option | writes |
|---|---|
| `--tlog PREFIX` | each vehicle's own .tlog, `PREFIX_N.tlog` (what a station receives) |
| `--autopilot arduplane` | the stream as ArduPlane sends it (below), live and in the .tlog |
| `--bin FILE` | an ArduPilot DataFlash log at ArduPlane's logging rates, then exits |
| `--ulg FILE` | a PX4 ULog at PX4's default logger rates, then exits |
| `--log-rates fast` | the autopilot's fast logging (below) |

`--log-rates fast` logs ATT every loop in the .bin (LOG_BITMASK ATTITUDE_FULLRATE) and,
in the .ulg, attitude, angular velocity and actuators every sample (SDLOG_PROFILE
high-rate and system identification). With several vehicles, `--bin` and `--ulg` get
`_N` before the suffix. Beside every written file of a simulated flight lies
its truth file (`flight.bin`: `flight.truth.toml`): the airframe file it was flown with
and the coefficients each vehicle flew by system id, which `replay` and `offline` find by
themselves (no `--config` needed).

**ArduPlane stream** (`--autopilot arduplane`): HEARTBEAT (MAV_AUTOPILOT_ARDUPILOTMEGA,
MAV_TYPE_FIXED_WING) at 1 Hz; the SR0 streams at `--stream-rate` (default 4 Hz, what
MAVProxy asks for): RAW_SENSORS (RAW_IMU and SCALED_IMU2 in milli-g and mrad/s,
SCALED_PRESSURE in hPa), EXTENDED_STATUS (SYS_STATUS, GPS_RAW_INT), POSITION
(GLOBAL_POSITION_INT, LOCAL_POSITION_NED), RC_CHANNELS (SERVO_OUTPUT_RAW), EXTRA1
(ATTITUDE, AOA_SSA carrying the simulated vane's alpha in degrees), EXTRA2 (VFR_HUD),
EXTRA3 (WIND, SYSTEM_TIME). `--msg-rate NAME=HZ` sets one message's or one stream's rate
(as SET_MESSAGE_INTERVAL or REQUEST_DATA_STREAM would); `--asked` streams the messages
the estimator reads at `[link] rate_hz`. Live, the vehicle honours SET_MESSAGE_INTERVAL,
REQUEST_DATA_STREAM and the parameter protocol. Its parameters (SERVOn_FUNCTION, _MIN,
_MAX, _TRIM, _REVERSED; SR0_*) are sent once at the start, as a station fetches them on
connecting, so a .tlog carries them. The elevator is on `[link] elevator_servo` with
SERVOn_FUNCTION = 19, trim at `elevator_pwm_center_us`, MIN/MAX 500 us either side, and
REVERSED = 1 where a higher PWM means trailing edge down (ArduPlane's positive elevator
output is nose-up); the surface's travel at full output is then 500 us /
`elevator_us_per_rad` (30 deg for the NOC UAV: `elevator_travel_deg`).

**DataFlash** (`--bin`): FMT, UNIT, MULT, FMTU, PARM (SERVOn_*, SCHED_LOOP_RATE,
LOG_BITMASK), MSG, MODE; IMU at the loop rate (the sample rate), ATT, CTUN, AETR, RCOU and
XKF2 (wind) at 25 Hz, AOA (the vane's alpha), ARSP and BARO at 10 Hz, GPS at 5 Hz.

**ULog** (`--ulg`), at PX4's logger intervals (the first sample at least the interval
after the last logged): vehicle_attitude (q) every 50 ms (every third 50 Hz sample),
vehicle_angular_velocity (xyz, xyz_derivative) and vehicle_acceleration every 20 ms,
vehicle_local_position, actuator_servos (normalised -1..1, positive nose-up;
CA_SV_CS0_TYPE = 3 elevator, CA_SV_CS0_TRQ_P = 1) and actuator_motors (throttle 0..1)
every 100 ms, airspeed_validated and vehicle_air_data every 200 ms, airspeed (with the
probe's air temperature), wind and vehicle_status (fixed wing) every second. PX4 logs
no angle of attack.
"""
"""The outputs section of docs/simulation.md (`gcs-sim --keys`)."""
