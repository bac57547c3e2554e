"""An ArduPilot DataFlash log (.bin) of the simulated flight, as ArduPlane writes one.

Every message's format, labels, units and multipliers are ArduPilot's own (quoted from
LogStructure.h of AP_Logger, AP_InertialSensor, AP_AHRS, AP_Baro, AP_GPS, AP_NavEKF3 and
ArduPlane/Log.cpp). Rates are ArduPlane's with the default LOG_BITMASK (ArduPlane.cpp
scheduler): IMU every loop (FAST_TASK ahrs_update: MASK_LOG_IMU), ATT and XKF* with it
at 25 Hz (update_logging25: MASK_LOG_ATTITUDE_FAST; every loop with
MASK_LOG_ATTITUDE_FULLRATE), CTUN, RCOU and AETR at 25 Hz (update_logging25), AOA at
10 Hz (update_logging10), ARSP and BARO at 10 Hz (their update tasks), GPS at 5 Hz (a
fix every GPS_RATE_MS = 200 ms). Scaled integer types as ArduPilot stores them: c/C/e
are value * 100 (centidegrees, centimetres), L is degrees * 1e7.

Record: 0xA3 0x95 <type> <fields packed little-endian>; FMT (type 128) defines each type.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sim.formats import GAS_CONSTANT_AIR, GRAVITY_MSS, FlightRecord, body_vector, every
from sim.formats.ardupilot import MAG_NED_MGAUSS, Param, servo_params
from sim.formats.records import Block, filled, interleave

HEAD = (0xA3, 0x95)
FMT_TYPE = 128

_TYPES = {
    "b": "i1", "B": "u1", "h": "<i2", "H": "<u2", "i": "<i4", "I": "<u4", "f": "<f4",
    "d": "<f8", "n": "S4", "N": "S16", "Z": "S64", "c": "<i2", "C": "<u2", "e": "<i4",
    "E": "<u4", "L": "<i4", "M": "u1", "q": "<i8", "Q": "<u8",
}  # fmt: skip
"""LogStructure.h "Format characters" as numpy types."""
_SCALE = {"c": 100.0, "C": 100.0, "e": 100.0, "E": 100.0, "L": 1e7}
"""What a physical value is multiplied by to be stored in each scaled type."""

UNITS = {
    "-": "", "#": "instance", "d": "deg", "h": "degheading", "D": "deglatitude",
    "U": "deglongitude", "E": "rad/s", "m": "m", "n": "m/s", "o": "m/s/s", "O": "degC",
    "P": "Pa", "s": "s", "S": "satellites", "Y": "us", "z": "Hz", "G": "Gauss", "r": "rad",
}  # fmt: skip
"""log_Units[] of LogStructure.h, the ones these messages use."""
MULTS = {
    "-": 0.0, "?": 1.0, "0": 1.0, "A": 1e-1, "B": 1e-2, "C": 1e-3, "F": 1e-6, "G": 1e-7,
}  # fmt: skip
"""log_Multipliers[] of LogStructure.h, the ones these messages use."""


@dataclass(frozen=True)
class Format:
    name: str
    type: int
    fmt: str
    labels: str
    units: str
    mults: str

    @property
    def dtype(self) -> np.dtype:
        fields = [("head1", "u1"), ("head2", "u1"), ("msgid", "u1")]
        fields += [
            (name, _TYPES[c]) for c, name in zip(self.fmt, self.labels.split(","), strict=True)
        ]
        return np.dtype(fields)

    def records(self, n: int, time_us: np.ndarray | None, **values: object) -> np.ndarray:
        """n records of this type, each field from a physical value (scaled as stored)."""
        cols = dict(zip(self.labels.split(","), self.fmt, strict=True))
        scaled = {
            k: np.asarray(v) * _SCALE[cols[k]] if cols[k] in _SCALE else v
            for k, v in values.items()
        }
        if time_us is not None:
            scaled["TimeUS"] = time_us
        return filled(self.dtype, n, head1=HEAD[0], head2=HEAD[1], msgid=self.type, **scaled)


FORMATS = {
    f.name: f
    for f in (
        # AP_Logger/LogStructure.h LOG_COMMON_STRUCTURES
        Format("FMT", FMT_TYPE, "BBnNZ", "Type,Length,Name,Format,Columns", "-b---", "-----"),
        Format("UNIT", 177, "QbZ", "TimeUS,Id,Label", "s--", "F--"),
        Format("FMTU", 176, "QBNN", "TimeUS,FmtType,UnitIds,MultIds", "s---", "F---"),
        Format("MULT", 178, "Qbd", "TimeUS,Id,Mult", "s--", "F--"),
        Format("PARM", 32, "QNff", "TimeUS,Name,Value,Default", "s---", "F---"),
        Format("MSG", 35, "QZ", "TimeUS,Message", "s-", "F-"),
        Format("MODE", 179, "QMBB", "TimeUS,Mode,ModeNum,Rsn", "s---", "F---"),
        Format(
            "RCOU", 38, "QHHHHHHHHHHHHHH",
            "TimeUS,C1,C2,C3,C4,C5,C6,C7,C8,C9,C10,C11,C12,C13,C14",
            "sYYYYYYYYYYYYYY", "F--------------",
        ),
        Format(
            "ARSP", 172, "QBffcffBBffB",
            "TimeUS,I,Airspeed,DiffPress,Temp,RawPress,Offset,U,H,Hp,TR,Pri",
            "s#nPOPP-----", "F-00B00-----",
        ),
        # AP_InertialSensor/LogStructure.h
        Format(
            "IMU", 131, "QBffffffIIfBBHH",
            "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz",
            "s#EEEooo--O--zz", "F-000000-----00",
        ),
        # AP_AHRS/LogStructure.h
        Format("AOA", 41, "Qff", "TimeUS,AOA,SSA", "sdd", "F00"),
        Format(
            "ATT", 42, "QccccCCCCB",
            "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw,AEKF",
            "sddddhhdh-", "FBBBBBBBB-",
        ),
        # AP_Baro/LogStructure.h
        Format(
            "BARO", 39, "QBffcfIffB",
            "TimeUS,I,Alt,Press,Temp,CRt,SMS,Offset,GndTemp,Health",
            "s#mPOnsmO-", "F-00B0C?0-",
        ),
        # AP_GPS/LogStructure.h
        Format(
            "GPS", 50, "QBBIHBcLLeffffB",
            "TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,Yaw,U",
            "s#-s-S-DUmnhnh-", "F--C-0BGGB000--",
        ),
        # AP_NavEKF3/LogStructure.h
        Format(
            "XKF2", 34, "QBccccchhhhhhfff",
            "TimeUS,C,AX,AY,AZ,VWN,VWE,MN,ME,MD,MX,MY,MZ,IDX,IDY,IS",
            "s#---nnGGGGGGoor", "F----BBCCCCCC000",
        ),
        # ArduPlane/Log.cpp
        Format(
            "CTUN", 1, "Qccccffffffi",
            "TimeUS,NavRoll,Roll,NavPitch,Pitch,ThO,RdrOut,ThD,As,SAs,E2T,GU",
            "sdddd---nn-n", "FBBBB---00-B",
        ),
        Format("AETR", 13, "Qffffff", "TimeUS,Ail,Elev,Thr,Rudd,Flap,SS", "s------", "F------"),
    )
}  # fmt: skip

LOG_BITMASK_DEFAULT = 65535
"""ArduPlane's default LOG_BITMASK (ATTITUDE_FAST, GPS, CTUN, NTUN, MODE, IMU, RC, ...)."""
MASK_LOG_ATTITUDE_FULLRATE = 1 << 20
LOG_25HZ_S, LOG_10HZ_S, GPS_S = 1 / 25, 1 / 10, 0.2
SCALING_SPEED = 15.0
"""ArduPlane's default SCALING_SPEED [m/s]: AETR.SS = SCALING_SPEED / airspeed."""
MODE_MANUAL, REASON_GCS = 0, 2
GPS_WEEK, GPS_WEEK_MS0 = 2300, 345_600_000


def write_bin(fr: FlightRecord, path: str | Path, fullrate: bool = False) -> Path:
    """Write the flight as a DataFlash log; fullrate: LOG_BITMASK with
    ATTITUDE_FULLRATE (ATT and XKF2 every loop). Returns the path."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    bitmask = LOG_BITMASK_DEFAULT | (MASK_LOG_ATTITUDE_FULLRATE if fullrate else 0)
    head = _definitions(fr, bitmask)
    data = interleave(_data_blocks(fr, fullrate))
    out.write_bytes(head + data)
    return out


def _definitions(fr: FlightRecord, bitmask: int) -> bytes:
    """FMT of every type, then UNIT, MULT, FMTU, the parameters, the startup messages and
    the mode, as a log begins."""
    t0 = fr.time_us[:1]
    fmt = FORMATS["FMT"]
    parts = [
        fmt.records(
            1, None, Type=f.type, Length=f.dtype.itemsize, Name=f.name.encode(),
            Format=f.fmt.encode(), Columns=f.labels.encode(),
        ).tobytes()
        for f in FORMATS.values()
    ]  # fmt: skip
    for uid, label in UNITS.items():
        parts.append(FORMATS["UNIT"].records(1, t0, Id=ord(uid), Label=label.encode()).tobytes())
    for mid, mult in MULTS.items():
        parts.append(FORMATS["MULT"].records(1, t0, Id=ord(mid), Mult=mult).tobytes())
    for f in FORMATS.values():
        fmtu = FORMATS["FMTU"].records(
            1, t0, FmtType=f.type, UnitIds=f.units.encode(), MultIds=f.mults.encode()
        )
        parts.append(fmtu.tobytes())
    for p in _params(fr, bitmask):
        rec = FORMATS["PARM"].records(1, t0, Name=p.name.encode(), Value=p.value, Default=p.value)
        parts.append(rec.tobytes())
    for text in (
        f"ArduPlane (simulated by gcs-sim: {fr.name} as ArduPlane logs its flight)",
        f"Frame: PLANE, system id {fr.system_id}",
    ):
        parts.append(FORMATS["MSG"].records(1, t0, Message=text.encode()[:64]).tobytes())
    mode = FORMATS["MODE"].records(1, t0, Mode=MODE_MANUAL, ModeNum=MODE_MANUAL, Rsn=REASON_GCS)
    parts.append(mode.tobytes())
    return b"".join(parts)


def _params(fr: FlightRecord, bitmask: int) -> list[Param]:
    return [
        *servo_params(fr),
        Param("SCHED_LOOP_RATE", float(round(fr.sample_rate_hz)), 4),
        Param("LOG_BITMASK", float(bitmask), 6),
        Param("ARSPD_USE", 1.0, 2),
        Param("SCALING_SPEED", SCALING_SPEED, 9),
        Param("SYSID_THISMAV", float(fr.system_id), 4),
    ]


def _data_blocks(fr: FlightRecord, fullrate: bool) -> list[Block]:
    t, us = fr.t_s, fr.time_us
    fast = every(t, 0.0 if fullrate else LOG_25HZ_S)
    rate25, rate10, gps = every(t, LOG_25HZ_S), every(t, LOG_10HZ_S), every(t, GPS_S)
    return [
        Block(_imu(fr), us, 0),
        Block(_att(fr, fast), us[fast], 1),
        Block(_xkf2(fr, fast), us[fast], 2),
        Block(_ctun(fr, rate25), us[rate25], 3),
        Block(_rcou(fr, rate25), us[rate25], 4),
        Block(_aetr(fr, rate25), us[rate25], 5),
        Block(_aoa(fr, rate10), us[rate10], 6),
        Block(_arsp(fr, rate10), us[rate10], 7),
        Block(_baro(fr, rate10), us[rate10], 8),
        Block(_gps(fr, gps), us[gps], 9),
    ]


def _imu(fr: FlightRecord) -> np.ndarray:
    n, hz = len(fr), round(fr.sample_rate_hz)
    return FORMATS["IMU"].records(
        n, fr.time_us, GyrX=fr.roll_rate, GyrY=fr.q, GyrZ=fr.yaw_rate, AccX=fr.a_x,
        AccY=fr.accel_y, AccZ=fr.a_z, T=45.0, GH=1, AH=1, GHz=hz, AHz=hz,
    )  # fmt: skip


def _att(fr: FlightRecord, i: np.ndarray) -> np.ndarray:
    pitch, roll = np.degrees(fr.theta[i]), np.degrees(fr.roll[i])
    return FORMATS["ATT"].records(
        len(i), fr.time_us[i], DesRoll=roll, Roll=roll, DesPitch=pitch, Pitch=pitch,
        DesYaw=fr.heading_deg[i], Yaw=fr.heading_deg[i], AEKF=3,
    )  # fmt: skip


def _xkf2(fr: FlightRecord, i: np.ndarray) -> np.ndarray:
    """The EKF's wind (0 where the flight gives none: the NOC simulator's air is still
    apart from its gusts); the field in NED and body axes [milligauss]."""
    n, e, d = MAG_NED_MGAUSS
    x, y, z = (m[i] for m in body_vector(fr, MAG_NED_MGAUSS))
    return FORMATS["XKF2"].records(
        len(i), fr.time_us[i], VWN=fr.wind_n[i], VWE=fr.wind_e[i], MN=n, ME=e, MD=d, MX=x,
        MY=y, MZ=z,
    )  # fmt: skip


def _ctun(fr: FlightRecord, i: np.ndarray) -> np.ndarray:
    pitch, roll = np.degrees(fr.theta[i]), np.degrees(fr.roll[i])
    throttle = 100.0 * fr.throttle_fraction[i]
    e2t = np.sqrt(1.225 / fr.rho[i])
    return FORMATS["CTUN"].records(
        len(i), fr.time_us[i], NavRoll=roll, Roll=roll, NavPitch=pitch, Pitch=pitch,
        ThO=throttle, ThD=throttle,
        As=fr.eas[i], SAs=np.nan, E2T=e2t,
    )  # fmt: skip


def _servo_outputs(fr: FlightRecord, i: np.ndarray) -> dict[str, np.ndarray]:
    from sim.formats.ardupilot import FUNCTION_AILERON, FUNCTION_RUDDER, servo_functions

    out = {f"C{n}": np.zeros(len(i)) for n in range(1, 15)}
    for n, function in servo_functions(fr.link).items():
        if function in (FUNCTION_AILERON, FUNCTION_RUDDER) and n <= 14:
            out[f"C{n}"] = np.full(len(i), 1500.0)
    out[f"C{fr.link.elevator_servo}"] = fr.elevator_pwm[i]
    if fr.link.throttle_servo:
        out[f"C{fr.link.throttle_servo}"] = fr.throttle_pwm[i]
    return {k: v for k, v in out.items() if k in FORMATS["RCOU"].labels.split(",")}


def _rcou(fr: FlightRecord, i: np.ndarray) -> np.ndarray:
    return FORMATS["RCOU"].records(len(i), fr.time_us[i], **_servo_outputs(fr, i))


def _aetr(fr: FlightRecord, i: np.ndarray) -> np.ndarray:
    """Pre-mixer outputs: the elevator +-4500 positive nose-up, the throttle in percent."""
    return FORMATS["AETR"].records(
        len(i), fr.time_us[i], Elev=4500.0 * fr.elevator_out[i],
        Thr=100.0 * fr.throttle_fraction[i], SS=SCALING_SPEED / np.maximum(fr.eas[i], 1.0),
    )  # fmt: skip


def _aoa(fr: FlightRecord, i: np.ndarray) -> np.ndarray:
    """The simulated vane's alpha [deg] (ArduPlane logs its AHRS estimate here)."""
    return FORMATS["AOA"].records(len(i), fr.time_us[i], AOA=np.degrees(fr.alpha[i]))


def _arsp(fr: FlightRecord, i: np.ndarray) -> np.ndarray:
    eas = fr.eas[i]
    dp = 0.5 * 1.225 * eas**2
    return FORMATS["ARSP"].records(
        len(i), fr.time_us[i], Airspeed=eas, DiffPress=dp, Temp=fr.temperature_c[i],
        RawPress=dp, U=1, H=1, Hp=1.0, Pri=1,
    )  # fmt: skip


def _baro(fr: FlightRecord, i: np.ndarray) -> np.ndarray:
    ms = fr.time_us[i] // 1000
    ground = float(fr.temperature_c[0] + fr.height_m[0] * GRAVITY_MSS / GAS_CONSTANT_AIR)
    return FORMATS["BARO"].records(
        len(i), fr.time_us[i], Alt=fr.height_m[i], Press=fr.pressure_pa[i],
        Temp=fr.temperature_c[i], CRt=-fr.v_down[i], SMS=ms, GndTemp=ground, Health=1,
    )  # fmt: skip


def _gps(fr: FlightRecord, i: np.ndarray) -> np.ndarray:
    week_ms = GPS_WEEK_MS0 + (fr.time_us[i] - fr.time_us[0]) // 1000
    return FORMATS["GPS"].records(
        len(i), fr.time_us[i], Status=3, GMS=week_ms, GWk=GPS_WEEK, NSats=12, HDop=1.21,
        Lat=fr.lat_deg[i], Lng=fr.lon_deg[i], Alt=fr.alt_msl_m[i], Spd=fr.ground_speed[i],
        GCrs=fr.course_deg[i], VZ=fr.v_down[i], U=1,
    )  # fmt: skip
