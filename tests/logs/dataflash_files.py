"""DataFlash logs written byte by byte with struct, as ArduPilot's AP_Logger lays them out
(libraries/AP_Logger/LogStructure.h): FMT records first, then FMTU, UNIT, MULT, PARM and
data records, each `0xA3 0x95 TYPE` and its packed little-endian fields."""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

HEAD = b"\xa3\x95"
STRUCT = {
    "b": "b", "B": "B", "h": "h", "H": "H", "i": "i", "I": "I", "f": "f", "d": "d",
    "n": "4s", "N": "16s", "Z": "64s", "c": "h", "C": "H", "e": "i", "E": "I", "L": "i",
    "M": "B", "q": "q", "Q": "Q",
}  # fmt: skip
SCALE = {"c": 100.0, "C": 100.0, "e": 100.0, "E": 100.0, "L": 1e7}
"""What a value is multiplied by before it is stored as the integer of its format."""


@dataclass(frozen=True)
class MessageType:
    type: int
    name: str
    format: str
    columns: str
    units: str = ""
    mults: str = ""

    @property
    def struct(self) -> struct.Struct:
        return struct.Struct("<" + "".join(STRUCT[c] for c in self.format))

    @property
    def length(self) -> int:
        return 3 + self.struct.size


FMT = MessageType(128, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns")
UNIT = MessageType(177, "UNIT", "QbZ", "TimeUS,Id,Label")
FMTU = MessageType(178, "FMTU", "QBNN", "TimeUS,FmtType,UnitIds,MultIds")
MULT = MessageType(179, "MULT", "Qbd", "TimeUS,Id,Mult")
PARM = MessageType(64, "PARM", "QNff", "TimeUS,Name,Value,Default")
MSG = MessageType(92, "MSG", "QZ", "TimeUS,Message")


@dataclass
class DataFlashWriter:
    """A DataFlash log built in memory: `define` each type, `add` records, `write`."""

    parts: list[bytes] = field(default_factory=list)
    types: dict[str, MessageType] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for t in (FMT, UNIT, FMTU, MULT, PARM, MSG):
            self.define(t, units=False)

    def define(self, t: MessageType, units: bool = True) -> None:
        self.types[t.name] = t
        self.parts.append(
            HEAD
            + bytes([FMT.type])
            + FMT.struct.pack(
                t.type, t.length, t.name.encode(), t.format.encode(), t.columns.encode()
            )
        )
        if units and t.units:
            self.add("FMTU", [0, t.type, t.units, t.mults])

    def add(self, name: str, values: Sequence[object]) -> None:
        t = self.types[name]
        packed = []
        for char, v in zip(t.format, values, strict=True):
            if char in "nNZ":
                packed.append(str(v).encode())
            elif char in "bBhHiIMqQ":
                packed.append(int(v))  # type: ignore[call-overload]
            elif char in SCALE:
                packed.append(round(float(v) * SCALE[char]))  # type: ignore[arg-type]
            else:
                packed.append(float(v))  # type: ignore[arg-type]
        self.parts.append(HEAD + bytes([t.type]) + t.struct.pack(*packed))

    def units(self, ids: dict[str, str], mults: dict[str, float]) -> None:
        for i, label in ids.items():
            self.add("UNIT", [0, ord(i), label])
        for i, m in mults.items():
            self.add("MULT", [0, ord(i), m])

    def params(self, values: dict[str, float]) -> None:
        for name, v in values.items():
            self.add("PARM", [0, name, v, 0.0])

    def junk(self, data: bytes) -> None:
        """Bytes that start no record (a damaged stretch)."""
        self.parts.append(data)

    def write(self, path: Path) -> Path:
        path.write_bytes(b"".join(self.parts))
        return path


ATT = MessageType(
    68,
    "ATT",
    "QccccCCCCB",
    "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw,AEKF",
    "sddddhhdh-",
    "FBBBBBBBB-",
)
IMU = MessageType(
    72,
    "IMU",
    "QBIffffffIIfBBHH",
    "TimeUS,I,GyrMS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz",
    "s#-EEEooo--O--zz",
    "F--000000-----00",
)
ARSP = MessageType(
    74,
    "ARSP",
    "QBffcffBBfB",
    "TimeUS,I,Airspeed,DiffPress,Temp,RawPress,Offset,U,H,Hp,Pri",
    "s#nPOPP----",
    "F-00B00----",
)
BARO = MessageType(
    75,
    "BARO",
    "QBfffcfIffB",
    "TimeUS,I,Alt,AltAMSL,Press,Temp,CRt,SMS,Offset,GndTemp,H",
    "s#mmPOnsmO-",
    "F-000B0C?0-",
)
RCOU = MessageType(
    76,
    "RCOU",
    "QHHHHHHHHHHHHHH",
    "TimeUS,C1,C2,C3,C4,C5,C6,C7,C8,C9,C10,C11,C12,C13,C14",
    "sYYYYYYYYYYYYYY",
    "F--------------",
)
STAT = MessageType(
    77,
    "STAT",
    "QBfBBBBBB",
    "TimeUS,isFlying,isFlyProb,Armed,Safety,Crash,Still,Stage,Hit",
    "s--------",
    "F--------",
)
AOA = MessageType(78, "AOA", "Qff", "TimeUS,AOA,SSA", "sdd", "F00")
GPS = MessageType(
    79,
    "GPS",
    "QBBIHBcLLeffffB",
    "TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,Yaw,U",
    "s#---SmDUmnhnh-",
    "F----0BGGB000--",
)
XKF2 = MessageType(
    80,
    "XKF2",
    "QBccccchhhhhhfff",
    "TimeUS,C,AX,AY,AZ,VWN,VWE,MN,ME,MD,MX,MY,MZ,IDX,IDY,IS",
    "s#---nnGGGGGGoor",
    "F----BBCCCCCC000",
)
VER = MessageType(81, "VER", "QBHBBBBIZH", "TimeUS,BT,BST,Maj,Min,Pat,FWT,GH,FWS,APJ")
MODE = MessageType(82, "MODE", "QMBB", "TimeUS,Mode,ModeNum,Rsn", "s---", "F---")

UNIT_IDS = {
    "s": "s",
    "d": "deg",
    "E": "rad/s",
    "o": "m/s/s",
    "n": "m/s",
    "P": "Pa",
    "O": "degC",
    "Y": "us",
    "m": "m",
}
MULT_IDS = {"F": 1e-6, "B": 1e-2, "0": 1.0, "C": 1e-3, "G": 1e-7}


@dataclass(frozen=True)
class Flight:
    """The signals a generated ArduPlane log holds (SI, the model's elevator convention)."""

    t_s: np.ndarray
    theta: np.ndarray
    phi: np.ndarray
    q: np.ndarray
    a_x: np.ndarray
    a_z: np.ndarray
    tas: np.ndarray
    alpha: np.ndarray
    elevator_rad: np.ndarray
    throttle: np.ndarray
    rho: np.ndarray
    takeoff_s: float
    landing_s: float


SERVO = {"min": 1100.0, "max": 1900.0, "trim": 1520.0}
TRAVEL_DEG = 20.0
RHO0 = 1.225


def flight(duration_s: float = 30.0, rate_hz: float = 50.0) -> Flight:
    t = np.arange(0.0, duration_s, 1.0 / rate_hz)
    w = 2 * math.pi * 0.5
    theta = 0.05 + 0.1 * np.sin(w * t)
    rho = np.full_like(t, 1.10) + 0.001 * np.sin(0.1 * t)
    return Flight(
        t_s=t,
        theta=theta,
        phi=0.2 * np.sin(0.3 * t),
        q=0.1 * w * np.cos(w * t),
        a_x=0.5 + 0.2 * np.sin(w * t),
        a_z=-9.81 + 1.5 * np.sin(w * t + 0.3),
        tas=24.0 + 2.0 * np.sin(0.2 * t),
        alpha=0.04 + 0.02 * np.sin(w * t),
        elevator_rad=np.radians(5.0) * np.sin(1.3 * t),
        throttle=0.4 + 0.2 * np.sin(0.7 * t),
        rho=rho,
        takeoff_s=5.0,
        landing_s=duration_s - 5.0,
    )


def elevator_pwm(de_rad: np.ndarray, reversed_: bool) -> np.ndarray:
    """The PWM ArduPlane outputs for an elevator deflection (positive trailing-edge down)
    with the surface's travel TRAVEL_DEG at full output: its output is positive nose-up."""
    up = -np.degrees(de_rad) / TRAVEL_DEG
    if reversed_:
        up = -up
    return np.asarray(
        np.where(
            up >= 0,
            SERVO["trim"] + up * (SERVO["max"] - SERVO["trim"]),
            SERVO["trim"] + up * (SERVO["trim"] - SERVO["min"]),
        )
    )


def arduplane_log(
    path: Path,
    fl: Flight,
    firmware: str = "ArduPlane V4.5.0 (1234abcd)",
    reversed_: bool = True,
    junk: bytes = b"",
    flying: bool = True,
    hover_mode: int = 0,
) -> Path:
    """An ArduPlane log of the flight: IMU at the flight's rate (two instances), ATT, ARSP,
    BARO, RCOU, AOA at half of it, STAT at 5 Hz; elevator on output 2, throttle on 3.
    hover_mode: a QuadPlane (Q_ENABLE) flying in that mode all along."""
    w = DataFlashWriter()
    w.units(UNIT_IDS, MULT_IDS)
    for t in (VER, ATT, IMU, ARSP, BARO, RCOU, STAT, AOA, GPS, XKF2, MODE):
        w.define(t)
    w.add("MSG", [0, firmware])
    w.add("VER", [0, 10, 5009, 4, 5, 0, 1, 123, firmware, 131])
    if hover_mode:  # a QuadPlane in a Q mode (QHOVER 18, ...) from the start
        w.add("MODE", [0, hover_mode, hover_mode, 1])
    w.params({
        "SERVO2_FUNCTION": 19, "SERVO2_MIN": SERVO["min"], "SERVO2_MAX": SERVO["max"],
        "SERVO2_TRIM": SERVO["trim"], "SERVO2_REVERSED": float(reversed_),
        "SERVO3_FUNCTION": 70, "SERVO3_MIN": 1000, "SERVO3_MAX": 2000, "SERVO3_TRIM": 1000,
        "SERVO3_REVERSED": 0, "Q_ENABLE": float(hover_mode > 0),
    })  # fmt: skip
    pwm = elevator_pwm(fl.elevator_rad, reversed_)
    thr = 1000 + 1000 * fl.throttle
    temp_c = 15.0
    press = fl.rho * 287.05287 * (temp_c + 273.15)
    eas = fl.tas * np.sqrt(fl.rho / RHO0)
    half = 2
    for i, t in enumerate(fl.t_s):
        us = int(round(t * 1e6)) + 1_000_000
        for inst in (0, 1):
            w.add(
                "IMU",
                [
                    us,
                    inst,
                    0,
                    0.01,
                    fl.q[i] + inst * 0.5,
                    -0.02,
                    fl.a_x[i],
                    0.1,
                    fl.a_z[i],
                    0,
                    0,
                    40.0,
                    1,
                    1,
                    400,
                    400,
                ],
            )
        w.add(
            "ATT", [us, 0, math.degrees(fl.phi[i]), 0, math.degrees(fl.theta[i]), 0, 90.0, 0, 0, 3]
        )
        if i % half == 0:
            w.add("ARSP", [us, 0, eas[i], 100.0, temp_c, 100.0, 0.0, 1, 1, 1.0, 0])
            w.add("BARO", [us, 0, 100.0, 100.0, press[i], 35.0, 0.0, us // 1000, 0.0, 20.0, 1])
            w.add("RCOU", [us, 1500, round(pwm[i]), round(thr[i]), 1500, *([0] * 10)])
            w.add("AOA", [us, math.degrees(fl.alpha[i]), 0.0])
            w.add("GPS", [us, 0, 3, 0, 0, 12, 0.8, -35.0, 149.0, 600.0, 20.0, 90.0, 0.5, 0.0, 1])
            w.add("XKF2", [us, 0, 0, 0, 0, 3.0, -1.5, 0, 0, 0, 0, 0, 0, 0.0, 0.0, 0.0])
        if i % 10 == 0:
            air = flying and fl.takeoff_s <= t < fl.landing_s
            w.add("STAT", [us, int(air), float(air), 1, 0, 0, 0, 3, 0])
        if i == len(fl.t_s) // 2 and junk:
            w.junk(junk)
    return w.write(path)


def text_log(
    path: Path, records: list[tuple[str, list[object]]], formats: list[MessageType]
) -> Path:
    """A text DataFlash log (FMT lines, then one line per record)."""
    lines = [f"FMT, {FMT.type}, {FMT.length}, FMT, {FMT.format}, {FMT.columns}"]
    for t in formats:
        lines.append(f"FMT, {t.type}, {t.length}, {t.name}, {t.format}, {t.columns}")
    for name, values in records:
        lines.append(", ".join([name, *(str(v) for v in values)]))
    path.write_text("\n".join(lines) + "\n")
    return path
