"""Decode at the edge: MAVLink packets -> SI samples stamped with both clocks, or link events.

Channels are model.channels.Channel: the observations 0..6 in the order of the model's
h(x), then the elevator [rad], the throttle [0..1] or thrust [N] and, where asked for
(link.density_from_pressure), the air density [kg/m^3]. Downstream code never
sees a MAVLink object.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import NamedTuple

from gcs_estimator import atmosphere
from gcs_estimator.config import DataConfig, LinkConfig
from gcs_estimator.model.channels import Channel
from gcs_estimator.telemetry import pwm
from gcs_estimator.telemetry.mavlink import (
    MAV_TYPE_FIXED_WING,
    MAV_TYPE_GCS,
    Decoder,
    MAVLinkMessage,
    header,
)

Ranges = Mapping[Channel, tuple[float, float]]


def ranges_of(data: DataConfig) -> dict[Channel, tuple[float, float]]:
    """The values a fixed-wing aircraft's signals can take [SI] (data.plausible_max); a
    value outside is absurd and dropped (and counted)."""
    out = {
        ch: (-data.plausible(q), data.plausible(q))
        for ch, q in (
            (Channel.ALPHA, "alpha"),
            (Channel.THETA, "theta"),
            (Channel.Q, "q"),
            (Channel.QDOT, "qdot"),
            (Channel.AX, "a_x"),
            (Channel.AZ, "a_z"),
            (Channel.ELEVATOR, "elevator"),
        )
    }
    out[Channel.V] = (0.5, data.plausible("airspeed"))
    out[Channel.POWER] = (-1e7, 1e7)
    out[Channel.DENSITY] = (0.01, 2.0)
    return out


PLAUSIBLE = ranges_of(DataConfig())
"""The default ranges."""


class Sample(NamedTuple):
    """Channel values from one message, in SI units, with both clocks. (A named tuple:
    immutable, and built once per packet at a third of a frozen dataclass's cost.)"""

    system_id: int
    message: str
    t_vehicle_s: float | None
    """Vehicle clock [s since boot]; None for messages without a timestamp (VFR_HUD)."""
    t_recv_s: float
    """Ground receive time [s since the Unix epoch]."""
    values: tuple[tuple[Channel, float], ...]
    wrap_s: float | None = None
    """Where the time field wraps [s] (a 32-bit field), None for 64-bit ones."""


@dataclass(frozen=True)
class Heartbeat:
    """A HEARTBEAT: presence of a vehicle (or of another ground station)."""

    ground_station: bool
    mav_type: int = MAV_TYPE_FIXED_WING
    """What the sender says it is (MAV_TYPE)."""


@dataclass(frozen=True)
class CommandAck:
    command: int
    result: int
    target_system: int = 0
    """Whom it answers (0: everyone)."""


@dataclass(frozen=True)
class Unknown:
    """A message the dialect does not know."""

    name: str


@dataclass(frozen=True)
class Ignored:
    """A valid message that carries nothing the estimator uses."""


Event = Sample | Heartbeat | CommandAck | Unknown | Ignored


class Decoded(NamedTuple):
    """One packet that passed its CRC: its header and what it means."""

    system_id: int
    component_id: int
    seq: int
    event: Event


@dataclass
class DecodeStats:
    invalid_values: int = 0
    """NaN, infinite or physically absurd fields dropped."""
    ignored_messages: int = 0
    """Messages that carry nothing the estimator uses (known, or unknown to the dialect)."""


def decode_packet(
    decoder: Decoder,
    packet: bytes,
    t_recv_s: float,
    link: LinkConfig,
    stats: DecodeStats,
    ranges: Ranges = PLAUSIBLE,
) -> Decoded | None:
    """What one packet means; None if it fails its CRC or framing."""
    msg = decoder.decode(packet)
    if msg is None:
        return None
    return decoded_message(msg, packet, t_recv_s, link, stats, ranges)


def decoded_message(
    msg: MAVLinkMessage,
    packet: bytes,
    t_recv_s: float,
    link: LinkConfig,
    stats: DecodeStats,
    ranges: Ranges = PLAUSIBLE,
) -> Decoded:
    """What a packet that decoded means."""
    kind = msg.get_type()
    event: Event
    extract = _EXTRACT.get(kind)
    if extract is not None:
        sample = _sample(msg, kind, extract(msg, link), t_recv_s, stats, ranges)
        event = Ignored() if sample is None else sample
    elif kind == "HEARTBEAT":
        event = Heartbeat(int(msg.type) == MAV_TYPE_GCS, int(msg.type))
    elif kind == "COMMAND_ACK":
        event = CommandAck(int(msg.command), int(msg.result), int(msg.target_system))
    elif kind.startswith("UNKNOWN"):
        # pymavlink gives an unknown message no header; the packet has one.
        seq, sysid, compid = header(packet)
        return Decoded(sysid, compid, seq, Unknown(kind))
    else:
        stats.ignored_messages += 1
        event = Ignored()
    return Decoded(int(msg.get_srcSystem()), int(msg.get_srcComponent()), int(msg.get_seq()), event)


WRAP_US32_S = 2**32 * 1e-6
"""A 32-bit time_usec wraps after 71.6 minutes [s]."""
WRAP_MS32_S = 2**32 * 1e-3
"""A 32-bit time_boot_ms wraps after 49.7 days [s]."""
TIME_WRAP_S: dict[str, float] = {
    "SERVO_OUTPUT_RAW": WRAP_US32_S,
    "ATTITUDE": WRAP_MS32_S,
    "SCALED_PRESSURE": WRAP_MS32_S,
    "NAMED_VALUE_FLOAT": WRAP_MS32_S,
}
"""Messages whose vehicle time is a 32-bit field (HIGHRES_IMU and AOA_SSA have 64 bits)."""


Found = tuple[float | None, list[tuple[Channel, float]]] | None
"""(vehicle time [s] or None, channel values) of a message, None if it carries none."""


def _highres_imu(msg: MAVLinkMessage, link: LinkConfig) -> Found:
    return msg.time_usec * 1e-6, [
        (Channel.AX, msg.xacc),
        (Channel.AZ, msg.zacc),
        (Channel.Q, msg.ygyro),
    ]


def _attitude(msg: MAVLinkMessage, link: LinkConfig) -> Found:
    return msg.time_boot_ms * 1e-3, [(Channel.THETA, msg.pitch)]


def _aoa_ssa(msg: MAVLinkMessage, link: LinkConfig) -> Found:
    return msg.time_usec * 1e-6, [(Channel.ALPHA, math.radians(msg.AOA))]


def _vfr_hud(msg: MAVLinkMessage, link: LinkConfig) -> Found:
    return None, [(Channel.V, msg.airspeed)]


def _servo_output_raw(msg: MAVLinkMessage, link: LinkConfig) -> Found:
    elev_us = getattr(msg, f"servo{link.elevator_servo}_raw")
    vals = [(Channel.ELEVATOR, pwm.elevator_rad(link, float(elev_us)))]
    if link.throttle_servo > 0:
        thr_us = getattr(msg, f"servo{link.throttle_servo}_raw")
        vals.append((Channel.POWER, pwm.throttle(link, float(thr_us))))
    return msg.time_usec * 1e-6, vals


def _scaled_pressure(msg: MAVLinkMessage, link: LinkConfig) -> Found:
    if not link.density_from_pressure:
        return None
    rho = float(atmosphere.density(100.0 * float(msg.press_abs)))
    return msg.time_boot_ms * 1e-3, [(Channel.DENSITY, rho)]


def _named_value_float(msg: MAVLinkMessage, link: LinkConfig) -> Found:
    name = msg.name if isinstance(msg.name, str) else msg.name.decode("ascii", "replace")
    channel = {link.qdot_name: Channel.QDOT, link.thrust_name: Channel.POWER}.get(
        name.rstrip("\x00")
    )
    return None if channel is None else (msg.time_boot_ms * 1e-3, [(channel, msg.value)])


_EXTRACT: dict[str, Callable[[MAVLinkMessage, LinkConfig], Found]] = {
    "HIGHRES_IMU": _highres_imu,
    "ATTITUDE": _attitude,
    "AOA_SSA": _aoa_ssa,
    "VFR_HUD": _vfr_hud,
    "SERVO_OUTPUT_RAW": _servo_output_raw,
    "SCALED_PRESSURE": _scaled_pressure,
    "NAMED_VALUE_FLOAT": _named_value_float,
}
"""The messages that carry channels, each with what reads them."""


def decode_message(
    msg: MAVLinkMessage,
    t_recv_s: float,
    link: LinkConfig,
    stats: DecodeStats,
    ranges: Ranges = PLAUSIBLE,
) -> Sample | None:
    """The sample a message carries, or None if it carries none."""
    kind = msg.get_type()
    extract = _EXTRACT.get(kind)
    if extract is None:
        stats.ignored_messages += 1
        return None
    return _sample(msg, kind, extract(msg, link), t_recv_s, stats, ranges)


def _sample(
    msg: MAVLinkMessage,
    kind: str,
    found: Found,
    t_recv_s: float,
    stats: DecodeStats,
    ranges: Ranges,
) -> Sample | None:
    """The sample of a message's channel values that are finite and in range."""
    if found is None:
        stats.ignored_messages += 1
        return None
    t, vals = found
    good: list[tuple[Channel, float]] = []
    for ch, v in vals:
        lo, hi = ranges[ch]
        fv = float(v)
        if math.isfinite(fv) and lo <= fv <= hi:
            good.append((ch, fv))
        else:
            stats.invalid_values += 1
    if not good:
        return None
    return Sample(int(msg.get_srcSystem()), kind, t, t_recv_s, tuple(good), TIME_WRAP_S.get(kind))
