"""Per autopilot, which messages or topics give each channel, in which units and axes.

ArduPilot (DataFlash; fields and units as libraries/AP_Logger/LogStructure.h and the
vehicles' Log.cpp define them, read from the log's own FMT/FMTU/UNIT/MULT records):

    q, p, r, a_x, a_z  IMU (first instance) GyrY, GyrX, GyrZ [rad/s], AccX, AccZ [m/s^2,
                       body FRD: level flight reads AccZ = -g]; RATE.P [deg/s] without IMU
    theta, phi, psi    ATT.Pitch, ATT.Roll, ATT.Yaw [deg] (psi unwrapped)
    airspeed           ARSP.Airspeed (first sensor), else CTUN.As: both equivalent airspeed;
                       true = EAS * E2T where CTUN logs the ratio, else EAS * sqrt(rho0/rho)
    alpha              AOA.AOA [deg]: the AHRS's estimate from airspeed, wind and the
                       velocity, not a vane
    elevator           RCOU.Cn of the output whose SERVOn_FUNCTION is 19, normalised with
                       SERVOn_MIN/MAX/TRIM/REVERSED (positive: nose up); else AETR.Elev/4500
    throttle           RCOU.Cn of SERVOn_FUNCTION 70, (pwm - min)/(max - min); else
                       AETR.Thr, CTUN.ThO [%]
    rho                BARO.Press with ARSP.Temp (the probe in the airflow), else the
                       standard temperature at that pressure (BARO.Temp is the board's)
    vz                 GPS.VZ [m/s, down]
    vn, ve, vd         GPS velocity: GPS.Spd [m/s] along GPS.GCrs [deg], GPS.VZ; else the
                       EKF's XKF1.VN, VE, VD (EKF3 core 0; fused with the IMU, so less
                       independent of it)
    wind_n, wind_e     XKF2.VWN, VWE (EKF3 core 0), else NKF2
    airborne           STAT.isFlying; hover: a QuadPlane's Q modes (MODE.ModeNum 17..25)

PX4 (ULog; msg/*.msg):

    theta, phi, psi    vehicle_attitude.q (Hamilton, body FRD to NED; psi unwrapped)
    q, p, r, qdot      vehicle_angular_velocity.xyz[1], [0], [2], xyz_derivative[1]
                       (older logs: vehicle_angular_acceleration.xyz[1])
    a_x, a_z           vehicle_acceleration.xyz[0], [2], else sensor_combined
    airspeed           airspeed_validated.true_airspeed_m_s
    rho                vehicle_air_data.baro_pressure_pa with airspeed.air_temperature_celsius,
                       else the standard temperature at that pressure
    elevator           actuator_servos.control[i] where CA_SV_CSi_TYPE = 3 (elevator), its
                       sign from CA_SV_CSi_TRQ_P; older logs: the fixed-wing pitch command
                       actuator_controls_1 (VTOL) or _0 control[1]
    throttle           actuator_controls_1 (VTOL) or _0 control[3], else actuator_motors
                       control[0] (PX4 1.14 on: the first motor, 0..1), else
                       vehicle_thrust_setpoint.xyz[0]
    vz                 vehicle_local_position.vz; wind: wind or wind_estimate
    vn, ve, vd         vehicle_gps_position (or sensor_gps) vel_n_m_s, vel_e_m_s, vel_d_m_s;
                       else the estimator's vehicle_local_position.vx, vy, vz
    airborne           vehicle_land_detected.landed; hover: vehicle_status (rotary wing)
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from gcs_estimator.arrays import FloatArray
from gcs_estimator.ingest.flightdata import attitude_of_quaternion
from gcs_estimator.ingest.logs.content import LogContent, Signal, Span
from gcs_estimator.ingest.logs.dataflash import DataFlashLog
from gcs_estimator.ingest.logs.ulog import ULogData
from gcs_estimator.model import atmosphere

RHO0 = 1.225
"""Sea-level standard density [kg/m^3]: equivalent airspeed's reference."""
ELEVATOR_FUNCTION = 19
THROTTLE_FUNCTION = 70
Q_MODES = range(17, 26)
"""ArduPlane's QuadPlane modes (QSTABILIZE .. QAUTOTUNE...): the vehicle hovers."""
AETR_FULL = 4500.0
"""AETR's elevator at full output (ArduPlane scales surfaces to +-4500)."""

NOT_FIXED_WING = ("ArduCopter", "ArduHeli", "ArduRover", "ArduSub", "Blimp", "AntennaTracker")


def _spans(t: FloatArray, on: NDArray[np.bool_], end: float) -> list[Span]:
    """The intervals in which a sampled flag is true (each sample holds until the next)."""
    out: list[Span] = []
    start: float | None = None
    for ti, flag in zip(t.tolist(), on.tolist(), strict=True):
        if flag and start is None:
            start = ti
        elif not flag and start is not None:
            out.append((start, ti))
            start = None
    if start is not None:
        out.append((start, end))
    return out


def _first_instance(log: DataFlashLog, name: str) -> tuple[NDArray[np.bool_] | None, FloatArray]:
    """Which rows of a message are its first instance (None: all, a message of one), and
    those rows' times; kept on the log, as each message gives several channels."""
    key = ("first instance", name)
    if key not in log.memo:
        column = "C" if name in ("XKF2", "NKF2") else "I"
        t = log.time_s(name)
        keep = None
        if log.has(name, column) and len(t):
            inst = log.values(name, column)
            keep = np.asarray(inst == inst.min(), bool)
            keep = None if keep.all() else keep
        log.memo[key] = (keep, t if keep is None else t[keep])
    found: tuple[NDArray[np.bool_] | None, FloatArray] = log.memo[key]  # type: ignore[assignment]
    return found


def _signal(log: DataFlashLog, name: str, column: str, unit: str, scale: float = 1.0) -> Signal:
    keep, t = _first_instance(log, name)
    v = log.si(name, column, unit)
    v = v if keep is None else v[keep]
    return Signal(t, v * scale if scale != 1.0 else v, f"{name}.{column}")


# ----------------------------------------------------------------------------- ArduPilot


def _firmware(log: DataFlashLog) -> str:
    if log.has("VER", "FWS"):
        fws = [s for s in log.strings("VER", "FWS") if s]
        if fws:
            return fws[0].split(" (")[0]
    for m in log.messages():
        if m.startswith(("Ardu", "Blimp", "AntennaTracker")):
            return m.split(" (")[0]
    return "ArduPilot (firmware not named in the log)"


def _servo_params(
    params: dict[str, float], function: int
) -> tuple[int, float, float, float, bool] | None:
    """(output number, min, max, trim, reversed) of the first output with this function."""
    for n in range(1, 33):
        if params.get(f"SERVO{n}_FUNCTION") == function:
            return (
                n,
                params.get(f"SERVO{n}_MIN", 1100.0),
                params.get(f"SERVO{n}_MAX", 1900.0),
                params.get(f"SERVO{n}_TRIM", 1500.0),
                bool(params.get(f"SERVO{n}_REVERSED", 0.0)),
            )
    return None


def _rcou(log: DataFlashLog, n: int) -> tuple[FloatArray, FloatArray, str] | None:
    for name, first in (("RCOU", 1), ("RCO2", 15), ("RCO3", 19)):
        col = f"C{n}"
        if n >= first and log.has(name, col):
            return log.time_s(name), log.values(name, col), f"{name}.{col}"
    return None


def _ardu_elevator(log: DataFlashLog, params: dict[str, float]) -> Signal | None:
    servo = _servo_params(params, ELEVATOR_FUNCTION)
    if servo is not None and (out := _rcou(log, servo[0])) is not None:
        n, lo, hi, trim, rev = servo
        t, pwm, src = out
        up = np.where(
            pwm >= trim, (pwm - trim) / max(hi - trim, 1.0), (pwm - trim) / max(trim - lo, 1.0)
        )
        up = np.where(pwm > 0, up, np.nan)  # 0: the output was off
        return Signal(
            t,
            -up if rev else up,
            f"{src} (SERVO{n}: {lo:g}..{trim:g}..{hi:g} us{', reversed' if rev else ''})",
        )
    if log.has("AETR", "Elev"):
        return Signal(log.time_s("AETR"), log.values("AETR", "Elev") / AETR_FULL, "AETR.Elev/4500")
    return None


def _ardu_throttle(log: DataFlashLog, params: dict[str, float]) -> Signal | None:
    servo = _servo_params(params, THROTTLE_FUNCTION)
    if servo is not None and (out := _rcou(log, servo[0])) is not None:
        n, lo, hi, _trim, rev = servo
        t, pwm, src = out
        x = np.clip((pwm - lo) / max(hi - lo, 1.0), 0.0, 1.0)
        return Signal(t, 1.0 - x if rev else x, f"{src} (SERVO{n}: {lo:g}..{hi:g} us)")
    for name, col in (("AETR", "Thr"), ("CTUN", "ThO")):
        if log.has(name, col):
            return Signal(log.time_s(name), log.values(name, col) / 100.0, f"{name}.{col} [%]")
    return None


def _ardu_density(log: DataFlashLog) -> Signal | None:
    if not log.has("BARO", "Press"):
        return None
    base = _signal(log, "BARO", "Press", "Pa")
    if log.has("ARSP", "Temp"):
        temp = _signal(log, "ARSP", "Temp", "degC")
        if len(temp.t_s):
            tk = np.interp(base.t_s, temp.t_s, temp.values)
            return Signal(base.t_s, atmosphere.density(base.values, tk), "BARO.Press, ARSP.Temp")
    return Signal(base.t_s, atmosphere.density(base.values), "BARO.Press at standard temperature")


def _ardu_airspeed(log: DataFlashLog, rho: Signal | None) -> Signal | None:
    if log.has("ARSP", "Airspeed"):
        eas = _signal(log, "ARSP", "Airspeed", "m/s")
    elif log.has("CTUN", "As"):
        eas = _signal(log, "CTUN", "As", "m/s")
        if log.has("CTUN", "E2T"):
            return Signal(
                eas.t_s, eas.values * log.values("CTUN", "E2T"), "CTUN.As*E2T (the AHRS's)"
            )
    else:
        return None
    if rho is None or not len(rho.t_s):
        return Signal(eas.t_s, eas.values, f"{eas.source} (equivalent; no density to make it true)")
    r = np.interp(eas.t_s, rho.t_s, rho.values)
    return Signal(eas.t_s, eas.values * np.sqrt(RHO0 / r), f"{eas.source}*sqrt(rho0/rho)")


def _ardu_hover(log: DataFlashLog, params: dict[str, float], end: float) -> list[Span]:
    if not params.get("Q_ENABLE") or not log.has("MODE", "ModeNum"):
        return []
    mode = log.values("MODE", "ModeNum")
    return _spans(log.time_s("MODE"), np.isin(mode, list(Q_MODES)), end)


def _ardu_vehicle(firmware: str, params: dict[str, float]) -> tuple[str, bool]:
    if firmware.startswith(NOT_FIXED_WING):
        kind = (
            "multirotor" if firmware.startswith(("ArduCopter", "ArduHeli")) else "not an aircraft"
        )
        return kind, False
    if params.get("Q_ENABLE"):
        return "QuadPlane (VTOL)", True
    return "fixed-wing", True


def _ardu_motion(log: DataFlashLog, s: dict[str, Signal]) -> None:
    """The body rates and accelerations (IMU, else RATE), attitude (ATT), alpha (AOA)."""
    if log.has("IMU", "GyrY"):
        for ch, col, unit in (
            ("q", "GyrY", "rad/s"),
            ("p", "GyrX", "rad/s"),
            ("r", "GyrZ", "rad/s"),
            ("a_x", "AccX", "m/s/s"),
            ("a_z", "AccZ", "m/s/s"),
        ):
            s[ch] = _signal(log, "IMU", col, unit)
    elif log.has("RATE", "P"):
        s["q"] = _signal(log, "RATE", "P", "deg/s")
    if log.has("ATT", "Pitch"):
        s["theta"] = _signal(log, "ATT", "Pitch", "deg")
        s["phi"] = _signal(log, "ATT", "Roll", "deg")
        yaw = _signal(log, "ATT", "Yaw", "deg")
        s["psi"] = Signal(yaw.t_s, np.unwrap(yaw.values), "ATT.Yaw (unwrapped)")
    if log.has("AOA", "AOA"):
        a = _signal(log, "AOA", "AOA", "deg")
        s["alpha"] = Signal(a.t_s, a.values, "AOA.AOA (the AHRS's estimate, not a vane)")


def _ardu_gps_velocity(log: DataFlashLog, s: dict[str, Signal]) -> None:
    """GPS velocity north, east, down (GPS.Spd along GCrs, VZ), else the EKF's (XKF1)."""
    if log.has("GPS", "Spd") and log.has("GPS", "GCrs") and log.has("GPS", "VZ"):
        spd = _signal(log, "GPS", "Spd", "m/s")
        crs = _signal(log, "GPS", "GCrs", "deg")
        if len(spd.t_s) == len(crs.t_s):
            s["vn"] = Signal(spd.t_s, spd.values * np.cos(crs.values), "GPS.Spd*cos(GCrs)")
            s["ve"] = Signal(spd.t_s, spd.values * np.sin(crs.values), "GPS.Spd*sin(GCrs)")
            s["vd"] = _signal(log, "GPS", "VZ", "m/s")
            return
    if log.has("XKF1", "VN"):
        for ch, col in (("vn", "VN"), ("ve", "VE"), ("vd", "VD")):
            s[ch] = _signal(log, "XKF1", col, "m/s")


def _ardu_aux(log: DataFlashLog, s: dict[str, Signal]) -> None:
    """Vertical speed and velocity (GPS) and the EKF's wind (XKF2, or EKF2's NKF2)."""
    if log.has("GPS", "VZ"):
        s["vz"] = _signal(log, "GPS", "VZ", "m/s")
    _ardu_gps_velocity(log, s)
    for ekf in ("XKF2", "NKF2"):
        if log.has(ekf, "VWN"):
            s["wind_n"] = _signal(log, ekf, "VWN", "m/s")
            s["wind_e"] = _signal(log, ekf, "VWE", "m/s")
            break


def arduplane(log: DataFlashLog) -> LogContent:
    """A DataFlash log read as ArduPlane logs its flight."""
    params = log.params()
    firmware = _firmware(log)
    vehicle, fixed_wing = _ardu_vehicle(firmware, params)
    times = [log.time_s(n) for n in ("ATT", "IMU", "GPS", "BARO") if log.has(n)]
    times = [t for t in times if len(t)]
    span = (
        (min(float(t[0]) for t in times), max(float(t[-1]) for t in times)) if times else (0.0, 0.0)
    )
    airborne = None
    if log.has("STAT", "isFlying"):
        airborne = _spans(log.time_s("STAT"), log.values("STAT", "isFlying") > 0, span[1])
    out = LogContent(firmware, vehicle, fixed_wing, span, airborne, "STAT.isFlying")
    out.hover = _ardu_hover(log, params, span[1])
    _ardu_motion(log, out.signals)
    rho = _ardu_density(log)
    for ch, sig in (
        ("rho", rho),
        ("airspeed", _ardu_airspeed(log, rho)),
        ("elevator", _ardu_elevator(log, params)),
        ("throttle", _ardu_throttle(log, params)),
    ):
        if sig is not None:
            out.signals[ch] = sig
    _ardu_aux(log, out.signals)
    if log.skipped_bytes:
        out.notes.append(f"{log.path}: {log.skipped_bytes} byte(s) that start no record skipped")
    if log.truncated_bytes:
        out.notes.append(
            f"{log.path}: the last record is cut by the end of the file ({log.truncated_bytes} "
            "byte(s)): not read"
        )
    for name, why in log.bad.items():
        out.notes.append(f"{log.path}: message type {name} not read: {why}")
    return out


# ----------------------------------------------------------------------------------- PX4

PX4_TOPICS = (
    "vehicle_attitude",
    "vehicle_angular_velocity",
    "vehicle_angular_acceleration",
    "vehicle_acceleration",
    "sensor_combined",
    "airspeed_validated",
    "airspeed",
    "vehicle_air_data",
    "vehicle_local_position",
    "vehicle_gps_position",
    "sensor_gps",
    "actuator_servos",
    "actuator_motors",
    "actuator_controls_0",
    "actuator_controls_1",
    "vehicle_thrust_setpoint",
    "wind",
    "wind_estimate",
    "vehicle_land_detected",
    "vehicle_status",
    "vtol_vehicle_status",
)
"""The topics the PX4 preset reads (pyulog parses only these)."""

PX4_ELEVATOR_TYPE = 3
"""CA_SV_CSn_TYPE of an elevator."""
MAV_TYPES = {
    1: "fixed-wing",
    2: "multirotor",
    3: "multirotor",
    4: "helicopter",
    13: "multirotor",
    14: "multirotor",
    15: "multirotor",
}
VTOL_TYPES = range(19, 26)


def _px4_time(topic: dict[str, np.ndarray]) -> FloatArray:
    return np.asarray(topic["timestamp"], float) * 1e-6


def _px4_signal(
    u: ULogData, name: str, column: str, label: str = "", scale: float = 1.0
) -> Signal | None:
    t = u.topic(name)
    if t is None or column not in t:
        return None
    return Signal(_px4_time(t), np.asarray(t[column], float) * scale, label or f"{name}.{column}")


def _px4_attitude(u: ULogData) -> tuple[Signal, Signal, Signal] | None:
    t = u.topic("vehicle_attitude")
    if t is None or "q[0]" not in t:
        return None
    phi, theta, psi = attitude_of_quaternion(*(np.asarray(t[f"q[{i}]"], float) for i in range(4)))
    psi = np.unwrap(psi)
    time = _px4_time(t)
    return (
        Signal(time, theta, "vehicle_attitude.q"),
        Signal(time, phi, "vehicle_attitude.q"),
        Signal(time, psi, "vehicle_attitude.q (unwrapped)"),
    )


def _px4_elevator(u: ULogData) -> Signal | None:
    servos = u.topic("actuator_servos")
    if servos is not None:
        for i in range(8):
            if u.params.get(f"CA_SV_CS{i}_TYPE") == PX4_ELEVATOR_TYPE and f"control[{i}]" in servos:
                sign = math.copysign(1.0, u.params.get(f"CA_SV_CS{i}_TRQ_P", 1.0) or 1.0)
                return Signal(
                    _px4_time(servos),
                    np.asarray(servos[f"control[{i}]"], float) * sign,
                    f"actuator_servos.control[{i}] (CA_SV_CS{i}_TYPE elevator)",
                )
    for name in ("actuator_controls_1", "actuator_controls_0"):
        sig = _px4_signal(u, name, "control[1]", f"{name}.control[1] (the pitch command)")
        if sig is not None and len(sig.t_s) and np.any(sig.values != 0):
            return sig
    return None


def _px4_throttle(u: ULogData) -> Signal | None:
    for name, col in (
        ("actuator_controls_1", "control[3]"),
        ("actuator_controls_0", "control[3]"),
        ("actuator_motors", "control[0]"),
        ("vehicle_thrust_setpoint", "xyz[0]"),
    ):
        sig = _px4_signal(u, name, col)
        if sig is not None and len(sig.t_s) and np.any(sig.values != 0):
            return Signal(sig.t_s, np.clip(sig.values, 0.0, 1.0), sig.source)
    return None


def _px4_density(u: ULogData) -> Signal | None:
    p = _px4_signal(u, "vehicle_air_data", "baro_pressure_pa")
    if p is None:
        return None
    temp = _px4_signal(u, "airspeed", "air_temperature_celsius")
    if temp is not None and len(temp.t_s) and np.all(np.isfinite(temp.values)):
        tk = np.interp(p.t_s, temp.t_s, temp.values) + 273.15
        return Signal(
            p.t_s,
            atmosphere.density(p.values, tk),
            "vehicle_air_data.baro_pressure_pa, airspeed.air_temperature_celsius",
        )
    return Signal(
        p.t_s,
        atmosphere.density(p.values),
        "vehicle_air_data.baro_pressure_pa at standard temperature",
    )


def _px4_vehicle(u: ULogData) -> tuple[str, bool]:
    mav = int(u.params.get("MAV_TYPE", 0))
    if mav in VTOL_TYPES:
        return f"VTOL (MAV_TYPE {mav})", True
    kind = MAV_TYPES.get(mav, f"MAV_TYPE {mav}" if mav else "unknown type")
    return kind, mav in (0, 1)


def _px4_hover(u: ULogData, end: float) -> list[Span]:
    status = u.topic("vehicle_status")
    if status is not None and "is_rotary_wing" in status:
        return _spans(_px4_time(status), np.asarray(status["is_rotary_wing"], float) > 0, end)
    if status is not None and "vehicle_type" in status:
        return _spans(_px4_time(status), np.asarray(status["vehicle_type"], float) == 1, end)
    vtol = u.topic("vtol_vehicle_status")
    if vtol is not None and "vtol_in_rw_mode" in vtol:
        return _spans(_px4_time(vtol), np.asarray(vtol["vtol_in_rw_mode"], float) > 0, end)
    return []


def _px4_first(u: ULogData, topics: tuple[str, ...], column: str) -> Signal | None:
    """The column from the first of the topics the log has it in."""
    for name in topics:
        sig = _px4_signal(u, name, column)
        if sig is not None:
            return sig
    return None


def _px4_motion(u: ULogData, s: dict[str, Signal]) -> None:
    """Attitude, body rates, pitch acceleration and the accelerometers."""
    att = _px4_attitude(u)
    if att is not None:
        s["theta"], s["phi"], s["psi"] = att
    for ch, i in (("p", 0), ("q", 1), ("r", 2)):
        sig = _px4_signal(u, "vehicle_angular_velocity", f"xyz[{i}]")
        if sig is not None:
            s[ch] = sig
    qdot = _px4_signal(u, "vehicle_angular_velocity", "xyz_derivative[1]") or _px4_signal(
        u, "vehicle_angular_acceleration", "xyz[1]"
    )
    if qdot is not None:
        s["qdot"] = qdot
    for ch, i in (("a_x", 0), ("a_z", 2)):
        sig = _px4_signal(u, "vehicle_acceleration", f"xyz[{i}]") or _px4_signal(
            u, "sensor_combined", f"accelerometer_m_s2[{i}]"
        )
        if sig is not None:
            s[ch] = sig


def _px4_gps_velocity(u: ULogData) -> list[tuple[str, Signal | None]]:
    """GPS velocity north, east, down: the receiver's, else the estimator's."""
    for name in ("vehicle_gps_position", "sensor_gps"):
        sigs = [_px4_signal(u, name, f"vel_{a}_m_s") for a in "ned"]
        if all(sig is not None for sig in sigs):
            return list(zip(("vn", "ve", "vd"), sigs, strict=True))
    return [
        (ch, _px4_signal(u, "vehicle_local_position", col))
        for ch, col in (("vn", "vx"), ("ve", "vy"), ("vd", "vz"))
    ]


def px4(u: ULogData) -> LogContent:
    """A ULog read as PX4 logs its flight."""
    sw = u.info.get("ver_sw_branch") or u.info.get("ver_sw") or ""
    firmware = f"PX4 {sw}".strip()
    start, last = (float(str(u.extra.get(k) or 0)) * 1e-6 for k in ("start_us", "last_us"))
    vehicle, fixed_wing = _px4_vehicle(u)
    land = u.topic("vehicle_land_detected")
    airborne = None
    if land is not None and "landed" in land:
        airborne = _spans(_px4_time(land), np.asarray(land["landed"], float) == 0, last)
    out = LogContent(
        firmware, vehicle, fixed_wing, (start, last), airborne, "vehicle_land_detected.landed"
    )
    if vehicle.startswith("VTOL"):
        out.hover = _px4_hover(u, last)
    _px4_motion(u, out.signals)
    for ch, sig in (
        ("airspeed", _px4_signal(u, "airspeed_validated", "true_airspeed_m_s")),
        ("rho", _px4_density(u)),
        ("elevator", _px4_elevator(u)),
        ("throttle", _px4_throttle(u)),
        ("vz", _px4_signal(u, "vehicle_local_position", "vz")),
        *_px4_gps_velocity(u),
        ("wind_n", _px4_first(u, ("wind", "wind_estimate"), "windspeed_north")),
        ("wind_e", _px4_first(u, ("wind", "wind_estimate"), "windspeed_east")),
    ):
        if sig is not None:
            out.signals[ch] = sig
    if u.dropouts:
        out.notes.append(f"{u.path}: {u.dropouts} logging dropout(s) (samples missing there)")
    return out
