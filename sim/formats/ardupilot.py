"""The simulated vehicle as ArduPlane speaks MAVLink: its message set, units, stream
groups, stream rates and parameters (gcs-sim --autopilot arduplane).

Sources (ArduPilot master; docs/decisions/0040):
- Stream groups: GCS_Mavlink.cpp of ArduPlane, STREAM_*_msgs[] (AOA_SSA is in EXTRA1,
  WIND and SYSTEM_TIME in EXTRA3); REQUEST_DATA_STREAM of MAV_DATA_STREAM_ALL sets every
  stream but PARAMS.
- RAW_IMU / SCALED_IMU2: GCS_Common.cpp send_raw_imu / send_scaled_imu: accel * 1000 /
  GRAVITY_MSS [milli-g], gyro * 1000 [mrad/s], each converted to int16 by truncation.
- SCALED_PRESSURE: press_abs and press_diff [hPa] (Pa * 0.01), temperature [cdegC].
- SERVO_OUTPUT_RAW: time_usec is AP_HAL::micros() (32 bits: it wraps after 71.6 min).
- Elevator: SRV_Channel::pwm_from_angle, output +-4500 positive nose-up, REVERSED flips.
- The default rate: MAVProxy asks REQUEST_DATA_STREAM(ALL, 4 Hz) on connecting (its
  `streamrate` setting), which the ArduPlane SITL sample telemetry log shows.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as dialect

from gcs_estimator.ingest.telemetry import mavlink
from sim.formats import (
    GRAVITY_MSS,
    SURFACE_HALF_RANGE_US,
    FlightRecord,
    body_vector,
    flight_record,
)
from sim.vehicle import SimulatedVehicle

DEFAULT_STREAM_HZ = 4.0
"""What MAVProxy asks of every stream on connecting (REQUEST_DATA_STREAM, ALL, 4 Hz)."""

STREAM_GROUPS: dict[str, tuple[str, ...]] = {
    "RAW_SENS": ("RAW_IMU", "SCALED_IMU2", "SCALED_PRESSURE"),
    "EXT_STAT": ("SYS_STATUS", "GPS_RAW_INT"),
    "RC_CHAN": ("SERVO_OUTPUT_RAW",),
    "RAW_CTRL": (),
    "POSITION": ("GLOBAL_POSITION_INT", "LOCAL_POSITION_NED"),
    "EXTRA1": ("ATTITUDE", "AOA_SSA"),
    "EXTRA2": ("VFR_HUD",),
    "EXTRA3": ("WIND", "SYSTEM_TIME", "NAMED_VALUE_FLOAT"),
    "PARAMS": (),
    "ADSB": (),
}
"""ArduPlane's SRn_ stream parameters (name after SR0_) and the messages of each that the
simulated vehicle has data for (NAMED_VALUE_FLOAT: a measured thrust, as a script would
send it)."""
STREAM_IDS: dict[int, str] = {
    mavlink.MAV_DATA_STREAM_RAW_SENSORS: "RAW_SENS",
    2: "EXT_STAT",  # MAV_DATA_STREAM_EXTENDED_STATUS
    mavlink.MAV_DATA_STREAM_RC_CHANNELS: "RC_CHAN",
    4: "RAW_CTRL",  # MAV_DATA_STREAM_RAW_CONTROLLER
    6: "POSITION",  # MAV_DATA_STREAM_POSITION
    mavlink.MAV_DATA_STREAM_EXTRA1: "EXTRA1",
    mavlink.MAV_DATA_STREAM_EXTRA2: "EXTRA2",
    mavlink.MAV_DATA_STREAM_EXTRA3: "EXTRA3",
}
"""REQUEST_DATA_STREAM's stream ids and the SR0_ parameter each sets."""
MESSAGES: tuple[str, ...] = tuple(m for group in STREAM_GROUPS.values() for m in group)
STREAM_OF: dict[str, str] = {m: s for s, group in STREAM_GROUPS.items() for m in group}
ASKED: tuple[str, ...] = (
    "ATTITUDE",
    "RAW_IMU",
    "SCALED_IMU2",
    "SCALED_PRESSURE",
    "VFR_HUD",
    "SERVO_OUTPUT_RAW",
    "AOA_SSA",
    "GLOBAL_POSITION_INT",
    "NAMED_VALUE_FLOAT",
)
"""The messages that carry the estimator's channels: what a station asks for at
[link] rate_hz with SET_MESSAGE_INTERVAL (gcs-sim --asked)."""

FUNCTION_AILERON, FUNCTION_ELEVATOR, FUNCTION_RUDDER, FUNCTION_THROTTLE = 4, 19, 21, 70
"""SRV_Channel::Aux_servo_function_t values (SERVOn_FUNCTION)."""
SERVO_OUTPUTS = 16
MAG_NED_MGAUSS = (200.0, 0.0, 420.0)
"""Earth's field where the flights are [milligauss, NED], for the IMU messages' mag."""
SENSORS = 0b1 | 0b10 | 0b100 | 0b1000 | 0b10000 | 0b100000
"""SYS_STATUS present/enabled/healthy: 3D gyro, accel, mag, abs and diff pressure, GPS."""


@dataclass(frozen=True)
class Param:
    name: str
    value: float
    kind: int
    """MAV_PARAM_TYPE (ArduPilot sends every value as a float of the number)."""


INT8, INT16, INT32 = 2, 4, 6
"""MAV_PARAM_TYPE_INT8, _INT16, _INT32."""


def servo_functions(link: Any) -> dict[int, int]:
    """SERVOn_FUNCTION by output: ArduPlane's defaults (1 aileron, 2 elevator, 3
    throttle, 4 rudder) with the elevator and throttle moved to the link's outputs."""
    functions = {
        1: FUNCTION_AILERON,
        2: FUNCTION_ELEVATOR,
        3: FUNCTION_THROTTLE,
        4: FUNCTION_RUDDER,
    }
    wanted = {FUNCTION_ELEVATOR: link.elevator_servo, FUNCTION_THROTTLE: link.throttle_servo}
    for function, output in wanted.items():
        for n, f in list(functions.items()):
            if f == function:
                del functions[n]
        if output:
            functions[output] = function
    return functions


def servo_params(fr: FlightRecord) -> list[Param]:
    """SERVO1..16 _FUNCTION, _MIN, _MAX, _TRIM, _REVERSED as the simulated vehicle has them."""
    link = fr.link
    functions = servo_functions(link)
    out: list[Param] = []
    for n in range(1, SERVO_OUTPUTS + 1):
        function = functions.get(n, 0)
        lo, hi, trim, rev = 1100.0, 1900.0, 1500.0, 0.0
        if function == FUNCTION_ELEVATOR:
            trim = link.elevator_pwm_center_us
            lo, hi = trim - SURFACE_HALF_RANGE_US, trim + SURFACE_HALF_RANGE_US
            # ArduPlane's positive elevator is nose-up (trailing edge up): where a higher
            # PWM moves the trailing edge down, the output is reversed.
            rev = 1.0 if link.elevator_us_per_rad > 0 else 0.0
        elif function == FUNCTION_THROTTLE:
            lo, hi = link.throttle_pwm_min_us, link.throttle_pwm_max_us
            trim = lo
        out += [
            Param(f"SERVO{n}_FUNCTION", float(function), INT16),
            Param(f"SERVO{n}_MIN", float(round(lo)), INT16),
            Param(f"SERVO{n}_MAX", float(round(hi)), INT16),
            Param(f"SERVO{n}_TRIM", float(round(trim)), INT16),
            Param(f"SERVO{n}_REVERSED", rev, INT8),
        ]
    return out


def _cut(values: np.ndarray) -> list[int]:
    """float -> int16 as C converts (truncation toward zero), clamped to the type."""
    return [int(v) for v in np.clip(np.trunc(values), -32768, 32767)]


class _Tables:
    """The record's values as the messages carry them, computed once for the flight."""

    def __init__(self, fr: FlightRecord) -> None:
        scale = 1000.0 / GRAVITY_MSS
        self.xacc = _cut(fr.a_x * scale)
        self.yacc = _cut(fr.accel_y * scale)
        self.zacc = _cut(fr.a_z * scale)
        self.xgyro = _cut(fr.roll_rate * 1000.0)
        self.ygyro = _cut(fr.q * 1000.0)
        self.zgyro = _cut(fr.yaw_rate * 1000.0)
        self.xmag, self.ymag, self.zmag = (_cut(m) for m in body_vector(fr, MAG_NED_MGAUSS))
        self.roll = fr.roll.tolist()
        self.yaw = np.where(fr.yaw > math.pi, fr.yaw - 2 * math.pi, fr.yaw).tolist()
        self.p = fr.roll_rate.tolist()
        self.r = fr.yaw_rate.tolist()
        self.ve_cm = _cut(np.round(fr.vel_east * 100.0))
        self.east = fr.east.tolist()
        self.ve = fr.vel_east.tolist()
        self.ground_speed = fr.ground_speed.tolist()
        self.gs_cm = [int(v) for v in np.round(fr.ground_speed * 100.0)]
        self.cog_cdeg = [int(v) % 36000 for v in np.round(fr.course_deg * 100.0)]
        self.hdg_cdeg = [int(v) % 36000 for v in np.round(fr.heading_deg * 100.0)]
        self.hdg_deg = [int(v) % 360 for v in np.round(fr.heading_deg)]
        # WIND: the direction the wind comes from [deg], its speed [m/s].
        self.wind_from = (np.degrees(np.arctan2(-fr.wind_e, -fr.wind_n)) % 360.0).tolist()
        self.wind_speed = np.hypot(fr.wind_n, fr.wind_e).tolist()
        self.press_hpa = (fr.pressure_pa * 0.01).tolist()
        self.diff_hpa = (0.5 * fr.rho * fr.V**2 * 0.01).tolist()
        self.temp_cdeg = _cut(fr.temperature_c * 100.0)
        self.lat = [int(v) for v in np.round(fr.lat_deg * 1e7)]
        self.lon = [int(v) for v in np.round(fr.lon_deg * 1e7)]
        self.alt_mm = [int(v) for v in np.round(fr.alt_msl_m * 1000.0)]
        self.rel_mm = [int(v) for v in np.round(fr.height_m * 1000.0)]
        self.vn_cm = _cut(np.round(fr.v_north * 100.0))
        self.vd_cm = _cut(np.round(fr.v_down * 100.0))
        self.e_pwm = [int(v) for v in fr.elevator_pwm]
        self.t_pwm = [int(v) for v in fr.throttle_pwm]
        self.thr_pct = [int(v) for v in np.round(fr.throttle_fraction * 100.0)]
        self.theta = fr.theta.tolist()
        self.q = fr.q.tolist()
        self.alpha_deg = np.degrees(fr.alpha).tolist()
        self.eas = fr.eas.tolist()
        self.vn = fr.v_north.tolist()
        self.vd = fr.v_down.tolist()
        self.north = fr.north_m.tolist()
        self.height = fr.height_m.tolist()
        self.alt_msl = fr.alt_msl_m.tolist()
        self.power = fr.power.tolist()


Builder = Callable[[Any, int, int, int], list[Any]]
"""(vehicle, sample index, time [us since boot], time [ms since boot]) -> messages."""


def _raw_imu(v: ArduPlaneVehicle, i: int, us: int, ms: int) -> list[Any]:
    t = v.tables
    return [
        v.mav.raw_imu_encode(
            us,
            t.xacc[i],
            t.yacc[i],
            t.zacc[i],
            t.xgyro[i],
            t.ygyro[i],
            t.zgyro[i],
            t.xmag[i],
            t.ymag[i],
            t.zmag[i],
            0,
            4500,
        )
    ]


def _scaled_imu2(v: ArduPlaneVehicle, i: int, us: int, ms: int) -> list[Any]:
    t = v.tables
    return [
        v.mav.scaled_imu2_encode(
            ms,
            t.xacc[i],
            t.yacc[i],
            t.zacc[i],
            t.xgyro[i],
            t.ygyro[i],
            t.zgyro[i],
            t.xmag[i],
            t.ymag[i],
            t.zmag[i],
            4500,
        )
    ]


def _scaled_pressure(v: ArduPlaneVehicle, i: int, us: int, ms: int) -> list[Any]:
    t = v.tables
    return [v.mav.scaled_pressure_encode(ms, t.press_hpa[i], t.diff_hpa[i], t.temp_cdeg[i], 0)]


def _sys_status(v: ArduPlaneVehicle, i: int, us: int, ms: int) -> list[Any]:
    return [
        v.mav.sys_status_encode(SENSORS, SENSORS, SENSORS, 250, 12600, 1500, 80, 0, 0, 0, 0, 0, 0)
    ]


def _gps_raw_int(v: ArduPlaneVehicle, i: int, us: int, ms: int) -> list[Any]:
    t = v.tables
    return [
        v.mav.gps_raw_int_encode(
            us, 3, t.lat[i], t.lon[i], t.alt_mm[i], 121, 200, t.gs_cm[i], t.cog_cdeg[i], 12
        )
    ]


def _global_position_int(v: ArduPlaneVehicle, i: int, us: int, ms: int) -> list[Any]:
    t = v.tables
    return [
        v.mav.global_position_int_encode(
            ms,
            t.lat[i],
            t.lon[i],
            t.alt_mm[i],
            t.rel_mm[i],
            t.vn_cm[i],
            t.ve_cm[i],
            t.vd_cm[i],
            t.hdg_cdeg[i],
        )
    ]


def _local_position_ned(v: ArduPlaneVehicle, i: int, us: int, ms: int) -> list[Any]:
    t = v.tables
    return [
        v.mav.local_position_ned_encode(
            ms, t.north[i], t.east[i], -t.height[i], t.vn[i], t.ve[i], t.vd[i]
        )
    ]


def _servo_output_raw(v: ArduPlaneVehicle, i: int, us: int, ms: int) -> list[Any]:
    servos = list(v.servo_idle)
    link = v.record.link
    servos[link.elevator_servo - 1] = v.tables.e_pwm[i]
    if link.throttle_servo:
        servos[link.throttle_servo - 1] = v.tables.t_pwm[i]
    return [v.mav.servo_output_raw_encode(us & 0xFFFFFFFF, 0, *servos)]


def _attitude(v: ArduPlaneVehicle, i: int, us: int, ms: int) -> list[Any]:
    t = v.tables
    return [v.mav.attitude_encode(ms, t.roll[i], t.theta[i], t.yaw[i], t.p[i], t.q[i], t.r[i])]


def _aoa_ssa(v: ArduPlaneVehicle, i: int, us: int, ms: int) -> list[Any]:
    return [v.mav.aoa_ssa_encode(us, v.tables.alpha_deg[i], 0.0)]


def _vfr_hud(v: ArduPlaneVehicle, i: int, us: int, ms: int) -> list[Any]:
    t = v.tables
    return [
        v.mav.vfr_hud_encode(
            t.eas[i], t.ground_speed[i], t.hdg_deg[i], t.thr_pct[i], t.alt_msl[i], -t.vd[i]
        )
    ]


def _wind(v: ArduPlaneVehicle, i: int, us: int, ms: int) -> list[Any]:
    t = v.tables
    return [v.mav.wind_encode(t.wind_from[i], t.wind_speed[i], 0.0)]


def _system_time(v: ArduPlaneVehicle, i: int, us: int, ms: int) -> list[Any]:
    return [v.mav.system_time_encode(v.clock_us(), ms)]


def _named_value_float(v: ArduPlaneVehicle, i: int, us: int, ms: int) -> list[Any]:
    if v.record.throttle_model:
        return []
    return [
        v.mav.named_value_float_encode(ms, v.record.link.thrust_name.encode(), v.tables.power[i])
    ]


BUILDERS: dict[str, Builder] = {
    "SERVO_OUTPUT_RAW": _servo_output_raw,
    "NAMED_VALUE_FLOAT": _named_value_float,
    "RAW_IMU": _raw_imu,
    "SCALED_IMU2": _scaled_imu2,
    "SCALED_PRESSURE": _scaled_pressure,
    "SYS_STATUS": _sys_status,
    "GPS_RAW_INT": _gps_raw_int,
    "GLOBAL_POSITION_INT": _global_position_int,
    "LOCAL_POSITION_NED": _local_position_ned,
    "AOA_SSA": _aoa_ssa,
    "VFR_HUD": _vfr_hud,
    "WIND": _wind,
    "SYSTEM_TIME": _system_time,
    "ATTITUDE": _attitude,
}
"""Each message's builder, in the order a sample's messages are sent: inputs first,
ATTITUDE last (a frame is complete when its last observation arrives)."""


def _message_name(message_id: int) -> str | None:
    """The name of a MAVLink message id (ardupilotmega dialect), None if unknown."""
    kind = dialect.mavlink_map.get(message_id)
    return None if kind is None else str(kind.msgname)


def check_rates(autopilot: str, items: list[str], link_rate_hz: float, asked: bool) -> None:
    """Refuse (ValueError) rate options the chosen stream cannot honour."""
    if autopilot != "arduplane" and (items or asked):
        raise ValueError("--msg-rate and --asked set ArduPlane's rates: add --autopilot arduplane")
    parse_rates(items, link_rate_hz, asked)


def parse_rates(items: list[str], link_rate_hz: float, asked: bool) -> dict[str, float]:
    """--msg-rate NAME=HZ items (a message or an SR0_ stream name) and --asked, as the
    per-message and per-stream rates they set; raises ValueError naming a bad item."""
    rates: dict[str, float] = dict.fromkeys(ASKED, link_rate_hz) if asked else {}
    for item in items:
        name, sep, value = item.partition("=")
        name = name.strip().upper().removeprefix("SR0_")
        try:
            hz = float(value)
        except ValueError:
            hz = -1.0
        if not sep or hz < 0 or not math.isfinite(hz):
            raise ValueError(f"--msg-rate {item!r}: give NAME=HZ with HZ >= 0")
        if name not in STREAM_OF and name not in STREAM_GROUPS:
            known = ", ".join([*MESSAGES, *STREAM_GROUPS])
            raise ValueError(f"--msg-rate {item!r}: {name} is none of {known}")
        rates[name] = hz
    return rates


@dataclass
class ArduPlaneVehicle(SimulatedVehicle):
    """The simulated vehicle speaking as ArduPlane: stream groups at SR0_ rates (default:
    what MAVProxy asks), per-message intervals, the parameter protocol."""

    density: float = 1.225
    stream_hz: float = DEFAULT_STREAM_HZ
    asked_rates: Mapping[str, float] = field(default_factory=dict)
    """Per-message or per-stream rates set before the flight (--msg-rate, --asked)."""
    loop_hz: float = 50.0
    flight: FlightRecord | None = None
    """The flight as the formats take it, where the caller built it (a flight that
    turns: benchmarks/jsbsim_missions.py); None: from the recording (wings level)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        self.record = self.flight or flight_record(
            self.recording, self.link, self.density, self.system_id, self.boot_s
        )
        self.tables = _Tables(self.record)
        self.loop_hz = self.record.sample_rate_hz
        self.stream_rates = {
            s: (0.0 if s in ("PARAMS", "ADSB") else self.stream_hz) for s in STREAM_GROUPS
        }
        self.intervals: dict[str, float] = {}
        """Per-message rates [Hz] set by SET_MESSAGE_INTERVAL (0: stopped)."""
        for name, hz in self.asked_rates.items():
            if name in STREAM_GROUPS:
                self.stream_rates[name] = hz
            else:
                self.intervals[name] = hz
        self.servo_idle = [0] * SERVO_OUTPUTS
        for n, function in servo_functions(self.link).items():
            if function in (FUNCTION_AILERON, FUNCTION_RUDDER):
                self.servo_idle[n - 1] = 1500
        self.fixed = {p.name: p for p in servo_params(self.record)}
        self._epoch_us = int(time.time() * 1e6)
        self._t_rel = 0.0

    # -- rates -------------------------------------------------------------------------

    def message_rate(self, name: str) -> float:
        """The rate [Hz] a message goes out at: its own interval, else its stream's,
        at most the loop rate."""
        hz = self.intervals.get(name, self.stream_rates[STREAM_OF[name]])
        return min(hz, self.loop_hz)

    def params(self) -> list[Param]:
        """Every parameter the vehicle answers for, in index order."""
        streams = [Param(f"SR0_{s}", float(self.stream_rates[s]), INT16) for s in STREAM_GROUPS]
        other = [
            Param("SYSID_THISMAV", float(self.system_id), INT16),
            Param("SCHED_LOOP_RATE", float(round(self.loop_hz)), INT16),
            Param("ARSPD_USE", 1.0, INT8),
        ]
        return [*self.fixed.values(), *streams, *other]

    # -- the ground's requests -----------------------------------------------------------

    def _answer(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind in ("PARAM_REQUEST_LIST", "PARAM_REQUEST_READ", "PARAM_SET") and int(
            msg.target_system
        ) not in (0, self.system_id):
            return
        if kind == "PARAM_REQUEST_LIST":
            self.send_params()
        elif kind == "PARAM_REQUEST_READ":
            self._param_read(msg.param_id, int(msg.param_index))
        elif kind == "PARAM_SET":
            self._param_set(msg.param_id, float(msg.param_value))
        else:
            super()._answer(msg)

    def send_params(self) -> None:
        params = self.params()
        for index in range(len(params)):
            self._send_param(params, index)

    def _send_param(self, params: list[Param], index: int) -> None:
        p = params[index]
        self._send(
            self.mav.param_value_encode(p.name.encode(), p.value, p.kind, len(params), index)
        )

    def _param_read(self, param_id: str | bytes, index: int) -> None:
        params = self.params()
        name = param_id.decode() if isinstance(param_id, bytes) else param_id
        names = [p.name for p in params]
        if index < 0 and name in names:
            index = names.index(name)
        if 0 <= index < len(params):
            self._send_param(params, index)

    def _param_set(self, param_id: str | bytes, value: float) -> None:
        """PARAM_SET: a stream rate is applied; the others are fixed by the airframe
        (answered with the value held, as ArduPilot answers a refused set)."""
        name = param_id.decode() if isinstance(param_id, bytes) else param_id
        stream = name.removeprefix("SR0_")
        if name.startswith("SR0_") and stream in STREAM_GROUPS and value >= 0:
            self.stream_rates[stream] = value
            self.stats.rate_changes += 1
        self._param_read(name, -1)

    def _set_interval(self, message_id: int, interval_us: float) -> int:
        """SET_MESSAGE_INTERVAL for any message this vehicle sends (-1 stop, 0 its
        stream's rate)."""
        name = _message_name(message_id)
        if name not in STREAM_OF:
            return int(mavlink.MAV_RESULT_DENIED)
        if interval_us == 0:
            self.intervals.pop(str(name), None)
        else:
            self.intervals[str(name)] = 0.0 if interval_us < 0 else 1e6 / interval_us
        self.stats.rate_changes += 1
        return int(mavlink.MAV_RESULT_ACCEPTED)

    def _request_message(self, message_id: int) -> int:
        if message_id == mavlink.MSG_ID["HEARTBEAT"]:
            self._send_packet(self.codec.heartbeat(mavlink.MAV_TYPE_FIXED_WING))
            return int(mavlink.MAV_RESULT_ACCEPTED)
        name = _message_name(message_id)
        if name not in STREAM_OF:
            return int(mavlink.MAV_RESULT_DENIED)
        self.requested.add(str(name))
        return int(mavlink.MAV_RESULT_ACCEPTED)

    def _data_stream(self, stream_id: int, rate_hz: float, start: int) -> None:
        """REQUEST_DATA_STREAM: one stream (or ALL but PARAMS) at rate_hz, or off."""
        hz = float(rate_hz) if start else 0.0
        if stream_id == mavlink.MAV_DATA_STREAM_ALL:
            names = [s for s in STREAM_GROUPS if s != "PARAMS"]
        else:
            names = [STREAM_IDS[stream_id]] if stream_id in STREAM_IDS else []
        for s in names:
            self.stream_rates[s] = hz
            self.stats.rate_changes += 1

    # -- the flight ----------------------------------------------------------------------

    def clock_us(self) -> int:
        """Unix time [us]: real time when paced, else the start plus flight time (a
        record written as fast as possible still reads as a flight of its length)."""
        if self.speed > 0:
            return int(time.time() * 1e6)
        return self._epoch_us + int(round(self._t_rel * 1e6))

    def _send_packet(self, buf: bytes) -> None:
        self.port.send(buf)
        self.stats.sent += 1
        if self._tlog is not None:
            self._tlog.write(self.clock_us(), buf)

    def run(self, stop_after_s: float | None = None) -> Any:
        """Stream the flight: the parameters first (as a station fetches them on
        connecting), then each sample's due messages at the vehicle's rates."""
        t = self.record.t_s
        start_wall = time.time()
        next_due = dict.fromkeys(BUILDERS, float(t[0]))
        next_hb = float(t[0])
        self.send_params()
        for i in range(len(t)):
            self._t_rel = float(t[i] - t[0])
            if stop_after_s is not None and self._t_rel > stop_after_s:
                break
            self._pace(self._t_rel, start_wall)
            self._serve()
            vt = self._t_rel + self.boot_s
            us, ms = int(round(vt * 1e6)), int(round(vt * 1e3)) & 0xFFFFFFFF
            if t[i] >= next_hb - 1e-9:
                next_hb += 1.0
                self._send_packet(self.codec.heartbeat(mavlink.MAV_TYPE_FIXED_WING))
            due = self._due_messages(float(t[i]), next_due) | self.requested
            self.requested = set()
            for name, build in BUILDERS.items():
                if name in due:
                    for msg in build(self, i, us, ms):
                        self._send(msg)
        self._serve()
        self.close()
        return self.stats

    def _due_messages(self, t: float, next_due: dict[str, float]) -> set[str]:
        due = set()
        for name in BUILDERS:
            hz = self.message_rate(name)
            if hz > 0 and t >= next_due[name] - 1e-6:
                due.add(name)
                next_due[name] = max(next_due[name] + 1.0 / hz, t + 0.5 / hz)
        return due
