"""Decode at the edge: MAVLink packets -> SI samples stamped with both clocks, or link events.

Channels are model.channels.Channel: the observations 0..6 in the order of the model's
h(x), then the elevator [rad], the throttle [0..1] or thrust [N] and, where asked for
(link.density_from_pressure), the air density [kg/m^3]. Several messages may carry one
channel (q: HIGHRES_IMU, SCALED_IMU*, RAW_IMU, ATTITUDE): each is decoded; which one a
vehicle's frames take is channel_sources.py's choice. Auxiliary signals (AUX_NAMES) ride
along. Units on the wire: docs/telemetry.md. Downstream code never sees a MAVLink
object.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from gcs_estimator.config import DataConfig, LinkConfig
from gcs_estimator.ingest.telemetry import pwm
from gcs_estimator.ingest.telemetry.mavlink import (
    MAV_AUTOPILOT_ARDUPILOTMEGA,
    MAV_AUTOPILOT_INVALID,
    MAV_TYPE_FIXED_WING,
    MAV_TYPE_GCS,
    Decoder,
    FieldReader,
    MAVLinkMessage,
    header,
    read_fields,
    text,
)
from gcs_estimator.model import atmosphere
from gcs_estimator.model.channels import Channel

Ranges = Mapping[Channel, tuple[float, float]]


def ranges_of(data: DataConfig) -> dict[Channel, tuple[float, float]]:
    """The values a fixed-wing aircraft's signals can take [SI] (config.PLAUSIBLE_MAX); a
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
    out[Channel.HDOT] = (-data.plausible("airspeed"), data.plausible("airspeed"))
    out[Channel.PHI] = (-math.pi, math.pi)
    rate = data.plausible("q")
    out[Channel.ROLL_RATE] = (-rate, rate)
    out[Channel.YAW_RATE] = (-rate, rate)
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
    aux: tuple[tuple[str, float], ...] = ()
    """Auxiliary values (AUX_NAMES), finite ones only; not used by the filters yet."""
    outputs: tuple[float, ...] = ()
    """A servo message's every output (PWM [us]; PX4: as its driver gives it): what the
    vehicle's own servo parameters map to the elevator and throttle (params.ServoMap)."""


_new_tuple = tuple.__new__
"""A named tuple made from its fields in order, without its __new__'s argument handling
(a third of the cost: Columns.sample and with_values run once per packet)."""


def with_values(
    sample: Sample, values: tuple[tuple[Channel, float], ...], aux: tuple[tuple[str, float], ...]
) -> Sample:
    """sample._replace(values=values, aux=aux), at a fifth of its cost."""
    system_id, message, t_vehicle_s, t_recv_s, _, wrap_s, _, outputs = sample
    made: Sample = _new_tuple(
        Sample, (system_id, message, t_vehicle_s, t_recv_s, values, wrap_s, aux, outputs)
    )
    return made


@dataclass(frozen=True)
class Heartbeat:
    """A HEARTBEAT: presence of a vehicle (or of another ground station)."""

    ground_station: bool
    mav_type: int = MAV_TYPE_FIXED_WING
    """What the sender says it is (MAV_TYPE)."""
    autopilot: bool = True
    """Whether the sending component is an autopilot (its HEARTBEAT autopilot is not
    MAV_AUTOPILOT_INVALID): the vehicle itself, not a gimbal, camera or companion
    computer on the same system id."""
    autopilot_kind: int = MAV_AUTOPILOT_ARDUPILOTMEGA
    """Which autopilot (MAV_AUTOPILOT: ArduPilot, PX4, ...): whose conventions its
    messages and parameters follow."""


@dataclass(frozen=True)
class CommandAck:
    command: int
    result: int
    target_system: int = 0
    """Whom it answers (0: everyone)."""


@dataclass(frozen=True)
class ParamValue:
    """A PARAM_VALUE: one of the vehicle's parameters (the answer to a request, or a
    ground station's fetch recorded in a tlog). The value as sent: PX4 sends integer
    parameters bytewise in the float (params.param_number reads them)."""

    name: str
    value: float
    param_type: int


@dataclass(frozen=True)
class Unknown:
    """A message the dialect does not know."""

    name: str


@dataclass(frozen=True)
class Ignored:
    """A valid message that carries nothing the estimator uses."""


Event = Sample | Heartbeat | CommandAck | ParamValue | Unknown | Ignored


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
    plan = _plans(link).get(kind)
    if plan is not None or kind == "ACTUATOR_OUTPUT_STATUS":
        sample = decode_message(msg, t_recv_s, link, stats, ranges)
        event = Ignored() if sample is None else sample
    elif kind == "HEARTBEAT":
        event = Heartbeat(
            int(msg.type) == MAV_TYPE_GCS,
            int(msg.type),
            int(msg.autopilot) != MAV_AUTOPILOT_INVALID,
            int(msg.autopilot),
        )
    elif kind == "PARAM_VALUE":
        event = ParamValue(_name(msg.param_id), float(msg.param_value), int(msg.param_type))
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


class SampleReader:
    """The channel-carrying messages straight from their packets: what decoded_message
    makes of Decoder.decode's message, without the message (mavlink.read_fields reads
    the fields the table below uses, and nothing else). A replay spends most of its time
    per packet; this is its common case."""

    def __init__(self, link: LinkConfig, stats: DecodeStats, ranges: Ranges = PLAUSIBLE) -> None:
        self._plans = {p.reader.msgid: p for p in _plans(link).values()}
        self._readers = {k: p.reader for k, p in self._plans.items()}
        self._stats = stats
        self._ranges = ranges

    def __call__(self, packet: bytes, t_recv_s: float) -> Decoded | bool | None:
        """The packet's meaning; False if it fails its CRC; None if it is not one of
        these messages (or is signed): decoded_message(Decoder.decode(...)) then."""
        got = read_fields(packet, self._readers)
        if not isinstance(got, tuple):
            return got
        reader, seq, sysid, compid, fields = got
        return self.of_fields(reader.msgid, seq, sysid, compid, fields, t_recv_s)

    def columns(
        self,
        msgid: int,
        fields: tuple[Any, ...],
        system_ids: list[int],
        t_recv_s: list[float],
    ) -> Columns | None:
        """Many packets of one of these messages at once (tlog_kernel's columns, each
        field a float64 column, a char[] field the raw bytes all of them have), as
        of_fields reads each (Columns.sample); None where the message's plan reads no
        columns, or none of these packets."""
        plan = self._plans[msgid]
        if plan.columns is None:
            return None
        found, rows = plan.columns(fields)
        if found is None:  # (a name no channel has): of_fields counts each
            return None
        return Columns(plan.reader.msgname, found, rows, system_ids, t_recv_s, self._ranges)

    @property
    def readers(self) -> dict[int, FieldReader]:
        """The messages read here, by id, with the fields each is read for."""
        return self._readers

    def of_fields(
        self, msgid: int, seq: int, sysid: int, compid: int, fields: Any, t_recv_s: float
    ) -> Decoded:
        """The meaning of a packet of one of these messages that passed its CRC, from its
        fields as its FieldReader reads them (or tlog_kernel, which reads them alike)."""
        plan = self._plans[msgid]
        found = plan.make(fields)
        sample = _sample(sysid, plan.reader.msgname, found, t_recv_s, self._stats, self._ranges)
        return Decoded(sysid, compid, seq, Ignored() if sample is None else sample)


class Columns:
    """The Found of many packets of one message type, each value a column: the Sample
    that of_fields makes of packet k where all its values are finite and in range
    (_sample's test, on the columns), else None (of_fields then counts what it drops).
    Samples are made one at a time as the link takes them: made all at once, a run's
    thousands of tuples would wake the garbage collector over the whole process."""

    def __init__(
        self,
        kind: str,
        found: Found,
        rows: Any,
        system_ids: list[int],
        t_recv_s: list[float],
        ranges: Ranges,
    ) -> None:
        t, vals, aux, outputs = found
        good = np.ones(len(system_ids), np.bool_) if rows is None else np.array(rows, np.bool_)
        for ch, v in vals:
            lo, hi = ranges[ch]
            good &= np.isfinite(v) & (v >= lo) & (v <= hi)
        for _, v in aux:
            good &= np.isfinite(v)
        self.kind = kind
        self.wrap = TIME_WRAP_S.get(kind)
        self.good: list[bool] = good.tolist()
        self.system_ids = system_ids
        self.t_recv_s = t_recv_s
        self.times: list[float] | None = None if t is None else np.asarray(t).tolist()
        self.values = _pairs(tuple(ch for ch, _ in vals), [np.asarray(v).tolist() for _, v in vals])
        self.aux = _pairs(tuple(k for k, _ in aux), [np.asarray(v).tolist() for _, v in aux])
        self.outputs = np.column_stack(outputs) if outputs else None

    def sample(self, k: int) -> Sample | None:
        if not self.good[k]:
            return None
        times = self.times
        made: Sample = _new_tuple(
            Sample,
            (
                self.system_ids[k],
                self.kind,
                None if times is None else times[k],
                self.t_recv_s[k],
                self.values(k),
                self.wrap,
                self.aux(k),
                () if self.outputs is None else tuple(self.outputs[k].tolist()),
            ),
        )
        return made


def _pairs(keys: tuple[Any, ...], cols: list[list[float]]) -> Callable[[int], tuple[Any, ...]]:
    """k -> ((keys[0], cols[0][k]), (keys[1], cols[1][k]), ...): written out for the
    lengths the messages have (a quarter of a comprehension's cost, per packet)."""
    n = len(keys)
    if n == 0:
        return lambda k: ()
    if n == 1:
        (a,), (x,) = keys, cols
        return lambda k: ((a, x[k]),)
    if n == 2:
        (a, b), (x, y) = keys, cols
        return lambda k: ((a, x[k]), (b, y[k]))
    if n == 3:
        (a, b, c), (x, y, z) = keys, cols
        return lambda k: ((a, x[k]), (b, y[k]), (c, z[k]))
    if n == 4:
        (a, b, c, d), (x, y, z, w) = keys, cols
        return lambda k: ((a, x[k]), (b, y[k]), (c, z[k]), (d, w[k]))
    if n == 5:
        (a, b, c, d, e), (x, y, z, w, v) = keys, cols
        return lambda k: ((a, x[k]), (b, y[k]), (c, z[k]), (d, w[k]), (e, v[k]))
    return lambda k: tuple([(key, col[k]) for key, col in zip(keys, cols, strict=True)])


WRAP_US32_S = 2**32 * 1e-6
"""A 32-bit time_usec wraps after 71.6 minutes [s]."""
WRAP_MS32_S = 2**32 * 1e-3
"""A 32-bit time_boot_ms wraps after 49.7 days [s]."""
TIME_WRAP_S: dict[str, float] = {
    "SERVO_OUTPUT_RAW": WRAP_US32_S,
    "RAW_IMU": WRAP_US32_S,
    "ATTITUDE": WRAP_MS32_S,
    "SCALED_IMU": WRAP_MS32_S,
    "SCALED_IMU2": WRAP_MS32_S,
    "SCALED_IMU3": WRAP_MS32_S,
    "SCALED_PRESSURE": WRAP_MS32_S,
    "NAMED_VALUE_FLOAT": WRAP_MS32_S,
    "GLOBAL_POSITION_INT": WRAP_MS32_S,
    "LOCAL_POSITION_NED": WRAP_MS32_S,
}
"""Messages whose vehicle time is a 32-bit field (HIGHRES_IMU, AOA_SSA and
ACTUATOR_OUTPUT_STATUS have 64 bits). RAW_IMU's field has 64 bits, but ArduPilot fills
it from its 32-bit microsecond clock (AP_HAL::micros), so it wraps as that does."""

G_MSS = 9.80665
"""Standard gravity [m/s^2]: ArduPilot's GRAVITY_MSS, by which it scales milli-g."""
MILLI_G = G_MSS * 1e-3
"""One milli-g [m/s^2] (SCALED_IMU* and ArduPilot's RAW_IMU accelerations)."""

AUX_NAMES: tuple[str, ...] = (
    "phi",
    "p",
    "r",
    "vz",
    "wind_dir",
    "wind_speed",
    "wind_vz",
    "vn",
    "ve",
    "vd",
)
"""Auxiliary signals decoded beside the channels (not used by the filters yet):
bank angle phi [rad], roll and yaw rates p, r [rad/s] (ATTITUDE), vertical speed vz
[m/s, down positive] (LOCAL_POSITION_NED, GLOBAL_POSITION_INT, VFR_HUD.climb), the wind
the vehicle estimates: the direction it blows from [rad], its speed and its vertical
speed [m/s] (WIND); the velocity over the ground north, east, down [m/s]
(GLOBAL_POSITION_INT: the autopilot's GPS-aided estimate; the data compatibility check's
GPS velocity, decision 0056)."""

Aux = tuple[tuple[str, float], ...]


class Found(NamedTuple):
    """What one message carries: its vehicle time [s] (None: untimed), channel values,
    auxiliary values (AUX_NAMES) and, for a servo message, every output's raw value."""

    t: float | None
    values: list[tuple[Channel, float]]
    aux: Aux = ()
    outputs: tuple[float, ...] = ()


class _Plan(NamedTuple):
    """How one message type gives channel values: the fields it reads, and what it
    makes of them (the same for a pymavlink message and for mavlink.read_fields)."""

    reader: FieldReader
    make: Callable[[tuple[Any, ...]], Found | None]
    columns: Callable[[tuple[Any, ...]], tuple[Found | None, Any]] | None = None
    """`make` on columns (each field an array of many packets' values; a char[] field
    one value for them all), with the rows it reads whole (a bool array; None: all): the
    same arithmetic, no branch on a value (SampleReader.columns). None: this message is
    read packet by packet."""


DEG_TO_RAD = math.pi / 180.0
"""math.radians(x) is x * DEG_TO_RAD (CPython's degToRad), bit for bit: the makers
multiply by it so that one definition serves a value and a column."""


def _name(raw: str | bytes) -> str:
    return (raw if isinstance(raw, str) else text(raw)).rstrip("\x00")


SERVO_FIELDS: tuple[str, ...] = tuple(f"servo{i}_raw" for i in range(1, 17))


def servo_values(link: LinkConfig, outputs: tuple[float, ...]) -> list[tuple[Channel, float]]:
    """Elevator [rad] and throttle [0..1] of a servo message's outputs (PWM [us]) by the
    [link] table's servo numbers and calibration (telemetry.pwm); the vehicle's own
    SERVOn parameters, where known, replace these (params.ServoMap)."""
    if len(outputs) < link.elevator_servo:
        return []
    vals = [(Channel.ELEVATOR, pwm.elevator_rad(link, outputs[link.elevator_servo - 1]))]
    if 0 < link.throttle_servo <= len(outputs):
        vals.append((Channel.POWER, pwm.throttle(link, outputs[link.throttle_servo - 1])))
    return vals


def _imu(scale_acc: float, scale_gyro: float, t_scale: float) -> Callable[[tuple[Any, ...]], Found]:
    """An IMU message's (time, xacc, zacc, ygyro) in SI."""

    def make(f: tuple[Any, ...]) -> Found:
        return Found(
            f[0] * t_scale,
            [
                (Channel.AX, f[1] * scale_acc),
                (Channel.AZ, f[2] * scale_acc),
                (Channel.Q, f[3] * scale_gyro),
            ],
        )

    return make


def _attitude(f: tuple[Any, ...]) -> Found:
    t, roll, pitch, rollspeed, pitchspeed, yawspeed = f
    return Found(
        t * 1e-3,
        [
            (Channel.THETA, pitch),
            (Channel.Q, pitchspeed),
            (Channel.PHI, roll),
            (Channel.ROLL_RATE, rollspeed),
            (Channel.YAW_RATE, yawspeed),
        ],
        (("phi", roll), ("p", rollspeed), ("r", yawspeed)),
    )


def _wind(f: tuple[Any, ...]) -> Found:
    return Found(
        None, [], (("wind_dir", f[0] * DEG_TO_RAD), ("wind_speed", f[1]), ("wind_vz", f[2]))
    )


@functools.lru_cache(maxsize=16)
def _plans(link: LinkConfig) -> dict[str, _Plan]:
    """The messages that carry channels, each with what reads them (per link: servo
    numbers, value names and whether pressure gives the density are the link's)."""

    def servo(f: tuple[Any, ...]) -> Found | None:
        if f[1] != 0:
            return None  # ports beyond the first (ArduPilot sends all 16 outputs on port 0)
        outputs = tuple(map(float, f[2:]))
        return Found(f[0] * 1e-6, servo_values(link, outputs), (), outputs)

    def servo_columns(f: tuple[Any, ...]) -> tuple[Found, Any]:
        outputs = f[2:]  # float64 columns: what float() makes of each value
        return Found(f[0] * 1e-6, servo_values(link, outputs), (), outputs), f[1] == 0

    named = {link.qdot_name: Channel.QDOT, link.thrust_name: Channel.POWER}

    def named_value(f: tuple[Any, ...]) -> Found | None:
        channel = named.get(_name(f[2]))
        return None if channel is None else Found(f[0] * 1e-3, [(channel, f[1])])

    def pressure(f: tuple[Any, ...]) -> Found | None:
        if not link.density_from_pressure:
            return None
        p = 100.0 * float(f[1])
        rho = float(atmosphere.density(p)) if 0.0 < p < math.inf else math.nan  # counted
        return Found(f[0] * 1e-3, [(Channel.DENSITY, rho)])

    def plan(
        name: str,
        fields: tuple[str, ...],
        make: Callable[[tuple[Any, ...]], Found | None],
        columns: Callable[[tuple[Any, ...]], tuple[Found | None, Any]] | bool = True,
    ) -> _Plan:
        """columns: True where make itself takes columns (and reads every row)."""
        if columns is True:
            return _Plan(FieldReader(name, fields), make, lambda f: (make(f), None))
        return _Plan(FieldReader(name, fields), make, columns or None)

    imu = ("xacc", "zacc", "ygyro")
    plans = (
        plan("HIGHRES_IMU", ("time_usec", *imu), _imu(1.0, 1.0, 1e-6)),
        plan("RAW_IMU", ("time_usec", *imu), _imu(MILLI_G, 1e-3, 1e-6)),
        plan("SCALED_IMU", ("time_boot_ms", *imu), _imu(MILLI_G, 1e-3, 1e-3)),
        plan("SCALED_IMU2", ("time_boot_ms", *imu), _imu(MILLI_G, 1e-3, 1e-3)),
        plan("SCALED_IMU3", ("time_boot_ms", *imu), _imu(MILLI_G, 1e-3, 1e-3)),
        plan(
            "ATTITUDE",
            ("time_boot_ms", "roll", "pitch", "rollspeed", "pitchspeed", "yawspeed"),
            _attitude,
        ),
        plan(
            "AOA_SSA",
            ("time_usec", "AOA"),
            lambda f: Found(f[0] * 1e-6, [(Channel.ALPHA, f[1] * DEG_TO_RAD)]),
        ),
        plan(
            "VFR_HUD",
            ("airspeed", "climb"),
            lambda f: Found(None, [(Channel.V, f[0])], (("vz", -f[1]),)),
        ),
        plan("SERVO_OUTPUT_RAW", ("time_usec", "port", *SERVO_FIELDS), servo, servo_columns),
        plan("SCALED_PRESSURE", ("time_boot_ms", "press_abs"), pressure, False),
        plan("NAMED_VALUE_FLOAT", ("time_boot_ms", "value", "name"), named_value),
        plan(
            "GLOBAL_POSITION_INT",
            ("time_boot_ms", "vx", "vy", "vz"),
            lambda f: Found(
                f[0] * 1e-3,
                [(Channel.HDOT, f[3] * -1e-2)],  # an int 0 and a float 0 both -0.0
                (
                    ("vz", f[3] * 1e-2),
                    ("vn", f[1] * 1e-2),
                    ("ve", f[2] * 1e-2),
                    ("vd", f[3] * 1e-2),
                ),
            ),
        ),
        plan(
            "LOCAL_POSITION_NED",
            ("time_boot_ms", "vz"),
            lambda f: Found(f[0] * 1e-3, [(Channel.HDOT, -f[1])], (("vz", f[1]),)),
        ),
        plan("WIND", ("direction", "speed", "speed_z"), _wind),
    )
    return {p.reader.msgname: p for p in plans}


def actuator_output_status(msg: MAVLinkMessage, link: LinkConfig) -> Found:
    """PX4's ACTUATOR_OUTPUT_STATUS: its outputs (PWM [us] as PX4's output drivers give
    them, 0 where unused) read as SERVO_OUTPUT_RAW's."""
    outputs = tuple(float(v) for v in msg.actuator[:16])
    return Found(float(msg.time_usec) * 1e-6, servo_values(link, outputs), (), outputs)


def decode_message(
    msg: MAVLinkMessage,
    t_recv_s: float,
    link: LinkConfig,
    stats: DecodeStats,
    ranges: Ranges = PLAUSIBLE,
) -> Sample | None:
    """The sample a message carries, or None if it carries none."""
    kind = msg.get_type()
    plan = _plans(link).get(kind)
    found: Found | None
    if plan is not None:
        found = plan.make(tuple(getattr(msg, f) for f in plan.reader.fields))
    elif kind == "ACTUATOR_OUTPUT_STATUS":
        found = actuator_output_status(msg, link)
    else:
        stats.ignored_messages += 1
        return None
    return _sample(int(msg.get_srcSystem()), kind, found, t_recv_s, stats, ranges)


def _sample(
    system_id: int,
    kind: str,
    found: Found | None,
    t_recv_s: float,
    stats: DecodeStats,
    ranges: Ranges,
) -> Sample | None:
    """The sample of a message's channel values that are finite and in range."""
    if found is None:
        stats.ignored_messages += 1
        return None
    t, vals, aux, outputs = found
    good: list[tuple[Channel, float]] = []
    finite = math.isfinite
    for ch, v in vals:
        lo, hi = ranges[ch]
        fv = float(v)
        if finite(fv) and lo <= fv <= hi:
            good.append((ch, fv))
        else:
            stats.invalid_values += 1
    fine = aux
    if aux:
        fine = tuple([(k, float(v)) for k, v in aux if finite(v)])
        stats.invalid_values += len(aux) - len(fine)
    if not (good or fine or outputs):
        return None
    return Sample(system_id, kind, t, t_recv_s, tuple(good), TIME_WRAP_S.get(kind), fine, outputs)
