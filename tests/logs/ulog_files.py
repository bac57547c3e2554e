"""A ULog written byte by byte (PX4's file format: a 16-byte header, then definitions,
then data; each message `uint16 size, uint8 type` and its body), for the PX4 preset."""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tests.logs.dataflash_files import Flight

MAGIC = b"ULog\x01\x12\x35"
TYPES = {"uint64_t": "Q", "float": "f", "bool": "?", "int32_t": "i", "uint8_t": "B"}


@dataclass
class ULogWriter:
    """Topics defined with `topic`, parameters and info given first, then `data`."""

    parts: list[bytes] = field(default_factory=list)
    formats: dict[str, list[tuple[str, str, int]]] = field(default_factory=dict)
    ids: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.parts.append(MAGIC + b"\x01" + struct.pack("<Q", 0))
        self._message(b"B", bytes(16) + struct.pack("<QQQ", 0, 0, 0))

    def _message(self, kind: bytes, body: bytes) -> None:
        self.parts.append(struct.pack("<HB", len(body), kind[0]) + body)

    def info(self, key: str, value: str) -> None:
        k = f"char[{len(value)}] {key}".encode()
        self._message(b"I", bytes([len(k)]) + k + value.encode())

    def param(self, name: str, value: float) -> None:
        if float(value).is_integer() and not name.endswith("_TRQ_P"):
            k, v = f"int32_t {name}".encode(), struct.pack("<i", int(value))
        else:
            k, v = f"float {name}".encode(), struct.pack("<f", value)
        self._message(b"P", bytes([len(k)]) + k + v)

    def topic(self, name: str, fields: list[tuple[str, str, int]]) -> None:
        """fields: (type, name, array length or 0), the first one `uint64_t timestamp`."""
        text = "".join(f"{t}[{n}] {f};" if n else f"{t} {f};" for t, f, n in fields)
        self._message(b"F", f"{name}:{text}".encode())
        self.formats[name] = fields

    def subscribe(self) -> None:
        """The definitions end: each topic logged as instance 0."""
        for i, name in enumerate(self.formats):
            self.ids[name] = i
            self._message(b"A", struct.pack("<BH", 0, i) + name.encode())

    def data(self, name: str, values: dict[str, object]) -> None:
        body = struct.pack("<H", self.ids[name])
        for t, f, n in self.formats[name]:
            code = TYPES[t]
            v = values.get(f, [0] * n if n else 0)
            body += struct.pack(f"<{n}{code}", *v) if n else struct.pack(f"<{code}", v)  # type: ignore[misc]
        self._message(b"D", body)

    def write(self, path: Path) -> Path:
        path.write_bytes(b"".join(self.parts))
        return path


def quaternion(phi: Any, theta: Any, psi: Any = 0.3) -> list[Any]:
    """Hamilton quaternion (w, x, y, z) of the 3-2-1 Euler angles, body FRD to NED, as PX4
    logs vehicle_attitude.q (numbers or arrays of them): written out here, not the
    reader's inverse."""
    cr, sr = np.cos(phi / 2), np.sin(phi / 2)
    cp, sp = np.cos(theta / 2), np.sin(theta / 2)
    cy, sy = np.cos(psi / 2), np.sin(psi / 2)
    return [
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    ]


TRQ_P = -1.0
"""The elevator's pitch torque per unit command in the generated log: negative, so a
positive servo command is nose-down on this airframe."""


def px4_log(path: Path, fl: Flight, mav_type: int = 1) -> Path:
    """A PX4 fixed-wing ULog of the flight (elevator on servo 1 with CA_SV_CS1_TYPE 3)."""
    w = ULogWriter()
    w.info("sys_name", "PX4")
    w.info("ver_sw_branch", "v1.14.0")
    for name, value in {
        "MAV_TYPE": mav_type,
        "CA_SV_CS0_TYPE": 1,
        "CA_SV_CS1_TYPE": 3,
        "CA_SV_CS1_TRQ_P": TRQ_P,
    }.items():
        w.param(name, value)
    ts = ("uint64_t", "timestamp", 0)
    w.topic("vehicle_attitude", [ts, ("float", "q", 4)])
    w.topic("vehicle_angular_velocity", [ts, ("float", "xyz", 3), ("float", "xyz_derivative", 3)])
    w.topic("vehicle_acceleration", [ts, ("float", "xyz", 3)])
    w.topic("airspeed_validated", [ts, ("float", "true_airspeed_m_s", 0)])
    w.topic("vehicle_air_data", [ts, ("float", "baro_pressure_pa", 0), ("float", "rho", 0)])
    w.topic("actuator_servos", [ts, ("float", "control", 8)])
    w.topic("vehicle_thrust_setpoint", [ts, ("float", "xyz", 3)])
    w.topic("vehicle_land_detected", [ts, ("bool", "landed", 0)])
    w.topic("vehicle_local_position", [ts, ("float", "vz", 0)])
    w.topic("wind", [ts, ("float", "windspeed_north", 0), ("float", "windspeed_east", 0)])
    w.subscribe()
    from gcs_estimator.model import atmosphere

    # the pressure whose standard-temperature density is the flight's
    grid = np.linspace(50_000.0, 110_000.0, 20_001)
    press = np.interp(fl.rho, atmosphere.density(grid), grid)
    travel = math.radians(20.0)
    for i, t in enumerate(fl.t_s):
        us = int(round(t * 1e6)) + 1_000_000
        w.data(
            "vehicle_attitude",
            {"timestamp": us, "q": [float(c) for c in quaternion(fl.phi[i], fl.theta[i])]},
        )
        w.data(
            "vehicle_angular_velocity",
            {"timestamp": us, "xyz": [0.01, fl.q[i], 0.0], "xyz_derivative": [0.0, 0.3, 0.0]},
        )
        w.data("vehicle_acceleration", {"timestamp": us, "xyz": [fl.a_x[i], 0.0, fl.a_z[i]]})
        if i % 2 == 0:
            w.data("airspeed_validated", {"timestamp": us, "true_airspeed_m_s": fl.tas[i]})
            w.data("vehicle_air_data", {"timestamp": us, "baro_pressure_pa": press[i]})
            up = -fl.elevator_rad[i] / travel  # nose-up command
            w.data("actuator_servos", {"timestamp": us, "control": [0, up / TRQ_P, *[0] * 6]})
            w.data("vehicle_thrust_setpoint", {"timestamp": us, "xyz": [fl.throttle[i], 0, 0]})
            w.data("vehicle_local_position", {"timestamp": us, "vz": 0.5})
            w.data("wind", {"timestamp": us, "windspeed_north": 3.0, "windspeed_east": -1.5})
        if i % 25 == 0:
            landed = not fl.takeoff_s <= t < fl.landing_s
            w.data("vehicle_land_detected", {"timestamp": us, "landed": landed})
    return w.write(path)
