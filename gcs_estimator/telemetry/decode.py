"""Decode at the edge: MAVLink messages -> SI samples stamped with both clocks.

Channels 0..6 are the observations (V, alpha, theta, q, qdot, a_x, a_z); 7 is the
elevator [rad] and 8 the throttle [0..1] or thrust [N]. Downstream code never sees a
MAVLink object.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from gcs_estimator.config import LinkConfig
from gcs_estimator.telemetry.mavlink import MAVLinkMessage

V, ALPHA, THETA, Q, QDOT, AX, AZ, ELEVATOR, POWER = range(9)
N_CHANNELS = 9

PLAUSIBLE: dict[int, tuple[float, float]] = {
    V: (0.5, 400.0),
    ALPHA: (-math.pi / 2, math.pi / 2),
    THETA: (-math.pi / 2, math.pi / 2),
    Q: (-10.0, 10.0),
    QDOT: (-100.0, 100.0),
    AX: (-200.0, 200.0),
    AZ: (-200.0, 200.0),
    ELEVATOR: (-1.0, 1.0),
    POWER: (-1e7, 1e7),
}
"""Physically possible ranges [SI]; a value outside is absurd and dropped (and counted)."""


@dataclass(frozen=True)
class Sample:
    """Channel values from one message, in SI units, with both clocks."""

    system_id: int
    message: str
    t_vehicle_s: float | None
    """Vehicle clock [s since boot]; None for messages without a timestamp (VFR_HUD)."""
    t_recv_s: float
    """Ground receive time [s since the Unix epoch]."""
    values: tuple[tuple[int, float], ...]


@dataclass
class DecodeStats:
    invalid_values: int = 0
    """NaN, infinite or physically absurd fields dropped."""
    ignored_messages: int = 0
    """Messages that carry nothing the estimator uses (known, or unknown to the dialect)."""


def decode_message(
    msg: MAVLinkMessage, t_recv_s: float, link: LinkConfig, stats: DecodeStats
) -> Sample | None:
    """The sample a message carries, or None if it carries none."""
    kind = msg.get_type()
    sysid = int(msg.get_srcSystem())
    t: float | None
    vals: list[tuple[int, float]]
    if kind == "HIGHRES_IMU":
        t = msg.time_usec * 1e-6
        vals = [(AX, msg.xacc), (AZ, msg.zacc), (Q, msg.ygyro)]
    elif kind == "ATTITUDE":
        t = msg.time_boot_ms * 1e-3
        vals = [(THETA, msg.pitch)]
    elif kind == "AOA_SSA":
        t = msg.time_usec * 1e-6
        vals = [(ALPHA, math.radians(msg.AOA))]
    elif kind == "VFR_HUD":
        t = None
        vals = [(V, msg.airspeed)]
    elif kind == "SERVO_OUTPUT_RAW":
        t = msg.time_usec * 1e-6
        elev_us = getattr(msg, f"servo{link.elevator_servo}_raw")
        vals = [(ELEVATOR, link.elevator_rad(float(elev_us)))]
        if link.throttle_servo > 0:
            thr_us = getattr(msg, f"servo{link.throttle_servo}_raw")
            vals.append((POWER, link.throttle(float(thr_us))))
    elif kind == "NAMED_VALUE_FLOAT":
        t = msg.time_boot_ms * 1e-3
        name = (
            msg.name.rstrip("\x00")
            if isinstance(msg.name, str)
            else msg.name.decode("ascii", "replace").rstrip("\x00")
        )
        if name == link.qdot_name:
            vals = [(QDOT, msg.value)]
        elif name == link.thrust_name:
            vals = [(POWER, msg.value)]
        else:
            stats.ignored_messages += 1
            return None
    else:
        stats.ignored_messages += 1
        return None
    good: list[tuple[int, float]] = []
    for ch, v in vals:
        lo, hi = PLAUSIBLE[ch]
        fv = float(v)
        if math.isfinite(fv) and lo <= fv <= hi:
            good.append((ch, fv))
        else:
            stats.invalid_values += 1
    if not good:
        return None
    return Sample(sysid, kind, t, t_recv_s, tuple(good))
