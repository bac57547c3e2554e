"""A PX4 ULog (.ulg) of the simulated flight, as PX4's logger writes one.

Format (PX4 docs, "ULog File Format", version 1): a 16-byte header ("ULog" 01 12 35, the
version, the start time [us]); then the definitions: flag bits 'B' (first), formats 'F'
("name:type field;..."), info 'I' and parameters 'P' (key "type name", then the value);
then the data: subscriptions 'A' (multi id, msg id, topic), data 'D' (msg id, then the
fields packed little-endian, timestamp first) and logged strings 'L'. Every message has
a 3-byte header: uint16 payload size, uint8 type.

Topics and fields are PX4's uORB messages (msg/*.msg), the ones this tool reads; rates are
the logger's default profile (src/modules/logger/logged_topics.cpp, intervals in ms):
vehicle_attitude 50, vehicle_angular_velocity 20, vehicle_acceleration 20,
airspeed_validated 200, vehicle_air_data 200, vehicle_local_position 100, actuator_servos
100, actuator_motors 100, airspeed (with the probe's air temperature) 1000, wind 1000;
vehicle_status as published (here 1 Hz). The high-rate and system-identification
profiles (SDLOG_PROFILE bits 4 and 3) log attitude, angular velocity and the actuators at
full rate. PX4 logs no angle of attack.

actuator_servos.control is normalised -1..1: the control allocator's output for a
surface of CA_SV_CS0_TYPE = 3 (elevator) with CA_SV_CS0_TRQ_P = 1, positive for a
nose-up pitch torque; PWM_MAIN_REV marks the servo reversed where a higher PWM moves the
trailing edge down (as the simulated link does).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sim.formats import (
    HOME_ALT_M,
    HOME_LAT_DEG,
    HOME_LON_DEG,
    FlightRecord,
    every,
    quaternion,
)
from sim.formats.records import Block, filled, interleave

MAGIC = b"ULog\x01\x12\x35"
VERSION = 1

_TYPES = {
    "int8_t": "i1", "uint8_t": "u1", "int16_t": "<i2", "uint16_t": "<u2", "int32_t": "<i4",
    "uint32_t": "<u4", "int64_t": "<i8", "uint64_t": "<u8", "float": "<f4", "double": "<f8",
    "bool": "u1", "char": "S1",
}  # fmt: skip


@dataclass(frozen=True)
class Topic:
    name: str
    fields: tuple[str, ...]
    """"type name" or "type[n] name", in file order (timestamp first)."""
    interval_ms: int
    fast_ms: int | None = None
    """The interval in the high-rate/system-identification profile (None: unchanged)."""

    def format_text(self) -> str:
        return self.name + ":" + "".join(f"{f};" for f in self.fields)

    def dtype(self) -> np.dtype:
        cols: list[tuple[str, str] | tuple[str, str, tuple[int]]] = [
            ("_size", "<u2"),
            ("_type", "u1"),
            ("_msg_id", "<u2"),
        ]
        for f in self.fields:
            kind, name = f.split(" ")
            if "[" in kind:
                base, n = kind[:-1].split("[")
                cols.append((name, _TYPES[base], (int(n),)))
            else:
                cols.append((name, _TYPES[kind]))
        return np.dtype(cols)


TOPICS = (
    Topic(
        "vehicle_attitude",
        ("uint64_t timestamp", "uint64_t timestamp_sample", "float[4] q",
         "float[4] delta_q_reset", "uint8_t quat_reset_counter"),
        50, 0,
    ),
    Topic(
        "vehicle_angular_velocity",
        ("uint64_t timestamp", "uint64_t timestamp_sample", "float[3] xyz",
         "float[3] xyz_derivative"),
        20, 0,
    ),
    Topic(
        "vehicle_acceleration",
        ("uint64_t timestamp", "uint64_t timestamp_sample", "float[3] xyz"),
        20,
    ),
    Topic(
        "airspeed_validated",
        ("uint64_t timestamp", "float indicated_airspeed_m_s", "float calibrated_airspeed_m_s",
         "float true_airspeed_m_s", "float calibrated_ground_minus_wind_m_s",
         "float true_ground_minus_wind_m_s", "float airspeed_derivative_filtered",
         "float throttle_filtered", "float pitch_filtered",
         "bool airspeed_sensor_measurement_valid", "int8_t selected_airspeed_index"),
        200,
    ),
    Topic(
        "airspeed",
        ("uint64_t timestamp", "uint64_t timestamp_sample", "float indicated_airspeed_m_s",
         "float true_airspeed_m_s", "float air_temperature_celsius", "float confidence"),
        1000,
    ),
    Topic(
        "vehicle_air_data",
        ("uint64_t timestamp", "uint64_t timestamp_sample", "uint32_t baro_device_id",
         "float baro_alt_meter", "float baro_temp_celcius", "float baro_pressure_pa",
         "float rho", "uint8_t calibration_count"),
        200,
    ),
    Topic(
        "vehicle_local_position",
        ("uint64_t timestamp", "uint64_t timestamp_sample", "uint64_t ref_timestamp",
         "double ref_lat", "double ref_lon", "float x", "float y", "float z", "float vx",
         "float vy", "float vz", "float z_deriv", "float ax", "float ay", "float az",
         "float heading", "float ref_alt", "float eph", "float epv", "bool xy_valid",
         "bool z_valid", "bool v_xy_valid", "bool v_z_valid", "bool xy_global",
         "bool z_global"),
        100,
    ),
    Topic(
        "actuator_servos",
        ("uint64_t timestamp", "uint64_t timestamp_sample", "float[8] control"),
        100, 0,
    ),
    Topic(
        "actuator_motors",
        ("uint64_t timestamp", "uint64_t timestamp_sample", "float[12] control",
         "uint16_t reversible_flags"),
        100, 0,
    ),
    Topic(
        "wind",
        ("uint64_t timestamp", "uint64_t timestamp_sample", "float windspeed_north",
         "float windspeed_east", "float variance_north", "float variance_east",
         "float tas_innov", "float tas_innov_var", "float beta_innov", "float beta_innov_var"),
        1000,
    ),
    Topic(
        "vehicle_status",
        ("uint64_t timestamp", "uint64_t armed_time", "uint64_t takeoff_time",
         "uint8_t nav_state", "uint8_t arming_state", "uint8_t vehicle_type", "bool is_vtol",
         "uint8_t system_type", "uint8_t system_id", "uint8_t component_id"),
        1000,
    ),
)  # fmt: skip
VEHICLE_TYPE_FIXED_WING, ARMING_STATE_ARMED, NAVIGATION_STATE_MANUAL = 2, 2, 0
MAV_TYPE_FIXED_WING = 1
CS_TYPE_ELEVATOR = 3
"""CA_SV_CS{n}_TYPE of an elevator (control_allocator module.yaml)."""
SERVO_FUNCTION_1, MOTOR_FUNCTION_1 = 201, 101
"""PWM_MAIN_FUNCn of the first servo and the first motor."""
SDLOG_DEFAULT, SDLOG_SYSID, SDLOG_HIGH_RATE = 1, 1 << 3, 1 << 4


def _message(kind: str, payload: bytes) -> bytes:
    return struct.pack("<HB", len(payload), ord(kind)) + payload


def _key_value(kind: str, key: str, value: bytes) -> bytes:
    k = key.encode()
    return _message(kind, bytes([len(k)]) + k + value)


def _info(key: str, text: str) -> bytes:
    raw = text.encode()
    return _key_value("I", f"char[{len(raw)}] {key}", raw)


def _param(name: str, value: float | int) -> bytes:
    if isinstance(value, int):
        return _key_value("P", f"int32_t {name}", struct.pack("<i", value))
    return _key_value("P", f"float {name}", struct.pack("<f", value))


def px4_params(fr: FlightRecord, fast: bool) -> dict[str, float | int]:
    """The airframe's parameters as a PX4 fixed-wing with one elevator and one motor
    would hold them (the elevator's output is the link's elevator_servo)."""
    link = fr.link
    e, m = link.elevator_servo, link.throttle_servo or (3 if link.elevator_servo != 3 else 4)
    center = int(round(link.elevator_pwm_center_us))
    params: dict[str, float | int] = {
        "SYS_AUTOSTART": 2100,
        "CA_AIRFRAME": 1,
        "CA_ROTOR_COUNT": 1,
        "CA_SV_CS_COUNT": 1,
        "CA_SV_CS0_TYPE": CS_TYPE_ELEVATOR,
        "CA_SV_CS0_TRQ_P": 1.0,
        "CA_SV_CS0_TRQ_R": 0.0,
        "CA_SV_CS0_TRQ_Y": 0.0,
        "CA_SV_CS0_TRIM": 0.0,
        f"PWM_MAIN_FUNC{e}": SERVO_FUNCTION_1,
        f"PWM_MAIN_MIN{e}": center - 500,
        f"PWM_MAIN_MAX{e}": center + 500,
        f"PWM_MAIN_FUNC{m}": MOTOR_FUNCTION_1,
        f"PWM_MAIN_MIN{m}": int(round(link.throttle_pwm_min_us)),
        f"PWM_MAIN_MAX{m}": int(round(link.throttle_pwm_max_us)),
        "PWM_MAIN_REV": (1 << (e - 1)) if link.elevator_us_per_rad > 0 else 0,
        "SDLOG_PROFILE": SDLOG_DEFAULT | (SDLOG_SYSID | SDLOG_HIGH_RATE if fast else 0),
        "MAV_SYS_ID": fr.system_id,
        "MAV_TYPE": MAV_TYPE_FIXED_WING,
    }
    return params


def write_ulg(fr: FlightRecord, path: str | Path, fast: bool = False) -> Path:
    """Write the flight as a ULog; fast: the high-rate and system-identification logging
    profiles. Returns the path."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    t0 = int(fr.time_us[0])
    head = MAGIC + bytes([VERSION]) + struct.pack("<Q", t0)
    flags = _message("B", bytes(16) + struct.pack("<3Q", 0, 0, 0))
    parts = [head, flags]
    parts += [_message("F", t.format_text().encode()) for t in TOPICS]
    parts += [
        _info("sys_name", "PX4"),
        _info("ver_hw", "GCS_SIM"),
        _info("sys_uuid", f"gcs-sim-{fr.system_id}"),
        _key_value("I", "int32_t time_ref_utc", struct.pack("<i", 0)),
    ]
    parts += [_param(k, v) for k, v in px4_params(fr, fast).items()]
    parts += [
        _message("A", struct.pack("<BH", 0, msg_id) + t.name.encode())
        for msg_id, t in enumerate(TOPICS)
    ]
    text = f"gcs-sim: {fr.name} as PX4 logs its flight".encode()
    parts.append(_message("L", struct.pack("<BQ", ord("6"), t0) + text))
    blocks = [_block(fr, msg_id, t, fast) for msg_id, t in enumerate(TOPICS)]
    out.write_bytes(b"".join(parts) + interleave(blocks))
    return out


def _block(fr: FlightRecord, msg_id: int, topic: Topic, fast: bool) -> Block:
    interval = topic.fast_ms if fast and topic.fast_ms is not None else topic.interval_ms
    i = every(fr.t_s, interval / 1000.0)
    dtype = topic.dtype()
    values = FILL[topic.name](fr, i)
    us = fr.time_us[i]
    if "timestamp_sample" in dtype.names:  # type: ignore[operator]
        values["timestamp_sample"] = us
    records = filled(
        dtype, len(i), _size=dtype.itemsize - 3, _type=ord("D"), _msg_id=msg_id, timestamp=us,
        **values,
    )  # fmt: skip
    return Block(records, us, msg_id)


Values = dict[str, object]


def _attitude(fr: FlightRecord, i: np.ndarray) -> Values:
    return {"q": quaternion(fr.theta[i], fr.roll[i], fr.yaw[i])}


def _angular_velocity(fr: FlightRecord, i: np.ndarray) -> Values:
    z = np.zeros(len(i))
    return {
        "xyz": np.column_stack([fr.roll_rate[i], fr.q[i], fr.yaw_rate[i]]),
        "xyz_derivative": np.column_stack([z, fr.qdot[i], z]),
    }


def _acceleration(fr: FlightRecord, i: np.ndarray) -> Values:
    return {"xyz": np.column_stack([fr.a_x[i], fr.accel_y[i], fr.a_z[i]])}


def _airspeed(fr: FlightRecord, i: np.ndarray) -> Values:
    eas = fr.eas[i]
    return {
        "indicated_airspeed_m_s": eas,
        "calibrated_airspeed_m_s": eas,
        "true_airspeed_m_s": fr.V[i],
        "calibrated_ground_minus_wind_m_s": eas,
        "true_ground_minus_wind_m_s": fr.V[i],
        "throttle_filtered": fr.throttle_fraction[i],
        "pitch_filtered": fr.theta[i],
        "airspeed_sensor_measurement_valid": 1,
        "selected_airspeed_index": 1,
    }


def _airspeed_sensor(fr: FlightRecord, i: np.ndarray) -> Values:
    """The differential-pressure sensor's reading with the probe's temperature (the air's,
    which a reader needs with the pressure for the density: decision 0045)."""
    return {
        "indicated_airspeed_m_s": fr.eas[i],
        "true_airspeed_m_s": fr.V[i],
        "air_temperature_celsius": fr.temperature_c[i],
        "confidence": 1.0,
    }


def _air_data(fr: FlightRecord, i: np.ndarray) -> Values:
    return {
        "baro_device_id": 1,
        "baro_alt_meter": fr.alt_msl_m[i],
        "baro_temp_celcius": fr.temperature_c[i],
        "baro_pressure_pa": fr.pressure_pa[i],
        "rho": fr.rho[i],
    }


def _local_position(fr: FlightRecord, i: np.ndarray) -> Values:
    flags = dict.fromkeys(
        ("xy_valid", "z_valid", "v_xy_valid", "v_z_valid", "xy_global", "z_global"), 1
    )
    return {
        "ref_timestamp": fr.time_us[0],
        "ref_lat": HOME_LAT_DEG,
        "ref_lon": HOME_LON_DEG,
        "ref_alt": HOME_ALT_M,
        "x": fr.north_m[i],
        "y": fr.east[i],
        "z": -fr.height_m[i],
        "vx": fr.v_north[i],
        "vy": fr.vel_east[i],
        "vz": fr.v_down[i],
        "heading": np.where(fr.yaw[i] > np.pi, fr.yaw[i] - 2 * np.pi, fr.yaw[i]),
        "z_deriv": fr.v_down[i],
        "eph": 1.0,
        "epv": 1.5,
        **flags,
    }


def _servos(fr: FlightRecord, i: np.ndarray) -> Values:
    control = np.full((len(i), 8), np.nan)
    control[:, 0] = fr.elevator_out[i]
    return {"control": control}


def _motors(fr: FlightRecord, i: np.ndarray) -> Values:
    control = np.full((len(i), 12), np.nan)
    control[:, 0] = fr.throttle_fraction[i]
    return {"control": control}


def _wind(fr: FlightRecord, i: np.ndarray) -> Values:
    return {
        "windspeed_north": fr.wind_n[i],
        "windspeed_east": fr.wind_e[i],
        "variance_north": 0.1,
        "variance_east": 0.1,
    }


def _status(fr: FlightRecord, i: np.ndarray) -> Values:
    return {
        "armed_time": fr.time_us[0],
        "takeoff_time": fr.time_us[0],
        "nav_state": NAVIGATION_STATE_MANUAL,
        "arming_state": ARMING_STATE_ARMED,
        "vehicle_type": VEHICLE_TYPE_FIXED_WING,
        "system_type": MAV_TYPE_FIXED_WING,
        "system_id": fr.system_id,
        "component_id": 1,
    }


FILL = {
    "vehicle_attitude": _attitude,
    "vehicle_angular_velocity": _angular_velocity,
    "vehicle_acceleration": _acceleration,
    "airspeed_validated": _airspeed,
    "airspeed": _airspeed_sensor,
    "vehicle_air_data": _air_data,
    "vehicle_local_position": _local_position,
    "actuator_servos": _servos,
    "actuator_motors": _motors,
    "wind": _wind,
    "vehicle_status": _status,
}
"""Each topic's values at the logged samples (fields not named stay 0)."""
