"""The MAVLink edge: the only module of the ground station that imports pymavlink.

MAVLink 2, ardupilotmega dialect (it includes common), loaded directly from
pymavlink.dialects.v20, so no environment variable has to be set before import. Also
the .tlog format: records of an 8-byte big-endian receive time [us since the Unix epoch]
followed by one raw MAVLink packet.
"""

from __future__ import annotations

import operator
import re
import struct
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, NamedTuple, Protocol, TypeVar

from pymavlink.dialects.v20 import ardupilotmega as dialect
from pymavlink.generator import mavcrc


def _x25_slow(data: bytes, crc: int) -> int:
    acc = mavcrc.x25crc_slow()
    acc.crc = crc
    acc.accumulate(data)
    return int(acc.crc)


_mcrf4xx: Any = mavcrc.mcrf4xx or _x25_slow
"""MAVLink's CRC (CRC-16/MCRF4XX): fastcrc's, as pymavlink uses it, where installed."""

MAVLinkMessage = Any
"""A pymavlink message object; never leaves the telemetry package."""

STX_V1, STX_V2 = 0xFE, 0xFD
SIGNED_FLAG = 0x01
GCS_SYSTEM_ID, GCS_COMPONENT_ID = 255, 190
RATE_REQUEST_COMPONENT = 1
"""The component the ground station's rate requests go to (MAV_COMP_ID_AUTOPILOT1, where
autopilots answer them); only its acknowledgement counts."""

MSG_ID: dict[str, int] = {t.msgname: int(i) for i, t in dialect.mavlink_map.items()}
"""Every message id of the dialect by name."""
MESSAGE_NAME = {v: k for k, v in MSG_ID.items()}
MAV_TYPE_FIXED_WING = dialect.MAV_TYPE_FIXED_WING
MAV_TYPE_GCS = dialect.MAV_TYPE_GCS
MAV_AUTOPILOT_INVALID = dialect.MAV_AUTOPILOT_INVALID
MAV_AUTOPILOT_ARDUPILOTMEGA = dialect.MAV_AUTOPILOT_ARDUPILOTMEGA
MAV_AUTOPILOT_PX4 = dialect.MAV_AUTOPILOT_PX4
"""The HEARTBEAT autopilot of a component that is not one (a gimbal, a camera, a
companion computer, a ground station)."""
MAV_TYPE_GENERIC = dialect.MAV_TYPE_GENERIC
MAV_TYPE_VTOL = tuple(
    v for k, v in vars(dialect).items() if k.startswith("MAV_TYPE_VTOL") and isinstance(v, int)
)
MAV_TYPE_NAMES: dict[int, str] = {
    k: v.name for k, v in dialect.enums["MAV_TYPE"].items() if isinstance(k, int)
}
MAV_CMD_SET_MESSAGE_INTERVAL = dialect.MAV_CMD_SET_MESSAGE_INTERVAL
MAV_RESULT_ACCEPTED = dialect.MAV_RESULT_ACCEPTED
MAV_RESULT_DENIED = dialect.MAV_RESULT_DENIED
MAV_RESULT_UNSUPPORTED = dialect.MAV_RESULT_UNSUPPORTED
MAV_CMD_REQUEST_MESSAGE = dialect.MAV_CMD_REQUEST_MESSAGE
MAV_PARAM_TYPE_REAL32 = dialect.MAV_PARAM_TYPE_REAL32
MAV_DATA_STREAM_ALL = dialect.MAV_DATA_STREAM_ALL
MAV_DATA_STREAM_RAW_SENSORS = dialect.MAV_DATA_STREAM_RAW_SENSORS
MAV_DATA_STREAM_RC_CHANNELS = dialect.MAV_DATA_STREAM_RC_CHANNELS
MAV_DATA_STREAM_EXTRA1 = dialect.MAV_DATA_STREAM_EXTRA1
MAV_DATA_STREAM_EXTRA2 = dialect.MAV_DATA_STREAM_EXTRA2
MAV_DATA_STREAM_EXTRA3 = dialect.MAV_DATA_STREAM_EXTRA3
MAV_DATA_STREAM_POSITION = dialect.MAV_DATA_STREAM_POSITION


def new_codec(system_id: int, component_id: int) -> Any:
    """A MAVLink 2 encoder/decoder that reports bad packets instead of raising."""
    mav = dialect.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
    mav.robust_parsing = True
    return mav


class Codec:
    """This end of a link (ground station or vehicle): encodes its messages with its own
    system and component ids and sequence numbers, and parses what it receives."""

    def __init__(self, system_id: int, component_id: int) -> None:
        self.mav = new_codec(system_id, component_id)
        """The dialect's encoder: build messages with its *_encode methods, then pack()."""

    def pack(self, msg: MAVLinkMessage) -> bytes:
        """The packet of a message; advances the sequence number (pack() itself does not)."""
        buf: bytes = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        return buf

    def heartbeat(self, mav_type: int) -> bytes:
        """HEARTBEAT of a ground station (MAV_TYPE_GCS) or a fixed-wing ArduPilot vehicle."""
        if mav_type == MAV_TYPE_GCS:
            autopilot, base_mode = dialect.MAV_AUTOPILOT_INVALID, 0
        else:  # flying, armed, in ArduPlane's MANUAL mode (custom mode 0)
            autopilot = dialect.MAV_AUTOPILOT_ARDUPILOTMEGA
            base_mode = (
                dialect.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
                | dialect.MAV_MODE_FLAG_SAFETY_ARMED
                | dialect.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
            )
        return self.pack(
            self.mav.heartbeat_encode(
                mav_type, autopilot, base_mode, dialect.PLANE_MODE_MANUAL, dialect.MAV_STATE_ACTIVE
            )
        )

    def set_message_interval(self, target_system: int, message: str, rate_hz: float) -> bytes:
        """COMMAND_LONG MAV_CMD_SET_MESSAGE_INTERVAL: stream `message` at rate_hz (0: stop)."""
        interval_us = 1e6 / rate_hz if rate_hz > 0 else -1
        msg = self.mav.command_long_encode(
            target_system,
            RATE_REQUEST_COMPONENT,
            MAV_CMD_SET_MESSAGE_INTERVAL,
            0,
            MSG_ID[message],
            interval_us,
            0,
            0,
            0,
            0,
            0,
        )
        return self.pack(msg)

    def param_request_read(self, target_system: int, name: str) -> bytes:
        """PARAM_REQUEST_READ of one parameter by name (the autopilot answers PARAM_VALUE)."""
        return self.pack(
            self.mav.param_request_read_encode(
                target_system, RATE_REQUEST_COMPONENT, name.encode("ascii"), -1
            )
        )

    def param_request_list(self, target_system: int) -> bytes:
        """PARAM_REQUEST_LIST: every parameter (PARAM_VALUE each)."""
        return self.pack(self.mav.param_request_list_encode(target_system, RATE_REQUEST_COMPONENT))

    def request_data_stream(self, target_system: int, stream: int, rate_hz: float) -> bytes:
        """REQUEST_DATA_STREAM: a stream group at rate_hz (ArduPilot sets its SRn_ rate of
        the port it arrives on; whole hertz, at least 1)."""
        rate = max(1, min(65535, round(rate_hz)))
        return self.pack(
            self.mav.request_data_stream_encode(
                target_system, RATE_REQUEST_COMPONENT, stream, rate, 1
            )
        )

    def command_ack(
        self, command: int, result: int, target_system: int = 0, target_component: int = 0
    ) -> bytes:
        return self.pack(
            self.mav.command_ack_encode(
                command, result, target_system=target_system, target_component=target_component
            )
        )

    def parse(self, data: bytes) -> list[MAVLinkMessage]:
        """The messages in a received datagram (bad packets are skipped)."""
        return list(self.mav.parse_buffer(data) or [])


def packet_length(buf: bytes | bytearray, start: int = 0) -> int:
    """Length of the MAVLink packet starting at buf[start], from its header; 0 if the
    byte there is no start marker or the header is incomplete."""
    if start >= len(buf):
        return 0
    stx = buf[start]
    if stx == STX_V2:
        if start + 3 > len(buf):
            return 0
        n = buf[start + 1]
        signed = buf[start + 2] & SIGNED_FLAG
        return 12 + n + (13 if signed else 0)
    if stx == STX_V1:
        if start + 2 > len(buf):
            return 0
        return 8 + buf[start + 1]
    return 0


MAX_PAYLOAD: dict[int, int] = {k: v.unpacker.size for k, v in dialect.mavlink_map.items()}
"""Longest payload of each known message id [bytes] (MAVLink 2 trims trailing zeros)."""


def could_be_packet(buf: bytes | bytearray, i: int) -> bool:
    """Cheap header checks before a candidate's CRC is computed: MAVLink 2's only
    incompatibility flag is signing, and a known message's payload has at most its full
    length (at least one byte)."""
    if buf[i] == STX_V2:
        if buf[i + 2] & ~SIGNED_FLAG:
            return False
        msgid = buf[i + 7] | buf[i + 8] << 8 | buf[i + 9] << 16
    else:
        msgid = buf[i + 5]
    longest = MAX_PAYLOAD.get(msgid)
    return longest is None or 0 < buf[i + 1] <= longest


def header(packet: bytes) -> tuple[int, int, int]:
    """(sequence, system id, component id) from a packet's header."""
    if packet[0] == STX_V2:
        return packet[4], packet[5], packet[6]
    return packet[2], packet[3], packet[4]


def is_unknown(msg: MAVLinkMessage) -> bool:
    """A message the dialect does not know: framed, but its checksum cannot be checked."""
    return str(msg.get_type()).startswith("UNKNOWN")


def next_marker(buf: bytes | bytearray, start: int) -> int:
    """Index of the first start marker at or after start (len(buf) if none)."""
    v2 = buf.find(STX_V2, start)
    v1 = buf.find(STX_V1, start)
    found = [i for i in (v1, v2) if i >= 0]
    return min(found) if found else len(buf)


class _Light(tuple):  # type: ignore[type-arg]
    """A decoded message of a type the station reads, as a tuple: (seq, system id,
    component id, then the fields in pymavlink's order). Answers the accessors the
    station uses of a pymavlink message, field names included."""

    __slots__ = ()
    msgname = ""

    def get_type(self) -> str:
        return self.msgname

    def get_seq(self) -> int:
        return int(self[0])

    def get_srcSystem(self) -> int:
        return int(self[1])

    def get_srcComponent(self) -> int:
        return int(self[2])


def text(raw: bytes) -> str:
    """A char[] field as pymavlink gives it: up to the first NUL, ASCII."""
    return raw.split(b"\x00", 1)[0].decode("ascii", errors="replace")


@dataclass(frozen=True)
class _Layout:
    """How to read one message type straight from its packet."""

    cls: type[_Light]
    unpacker: struct.Struct
    crc_extra: bytes
    pick: Any
    """itemgetter: the unpacked payload in field order."""
    text_fields: tuple[int, ...]
    """Positions (in field order) of char[] fields."""


def _layout(msgid: int) -> _Layout:
    t = dialect.mavlink_map[msgid]
    if any(n != 1 for n in t.lengths) or len(t.fieldnames) < 2:
        raise ValueError(f"{t.msgname}: arrays are left to pymavlink")
    attrs: dict[str, Any] = {"__slots__": (), "msgname": t.msgname}
    for i, name in enumerate(t.fieldnames):
        attrs[name] = property(operator.itemgetter(3 + i))
    cls = type(f"Light_{t.msgname}", (_Light,), attrs)
    text = tuple(i for i, ft in enumerate(t.fieldtypes) if ft == "char")
    return _Layout(cls, t.unpacker, bytes([t.crc_extra]), operator.itemgetter(*t.orders), text)


FAST_MESSAGES = (
    "HEARTBEAT",
    "COMMAND_ACK",
    "ATTITUDE",
    "HIGHRES_IMU",
    "RAW_IMU",
    "SCALED_IMU",
    "SCALED_IMU2",
    "SCALED_IMU3",
    "GLOBAL_POSITION_INT",
    "LOCAL_POSITION_NED",
    "WIND",
    "PARAM_VALUE",
    "VFR_HUD",
    "SERVO_OUTPUT_RAW",
    "AOA_SSA",
    "NAMED_VALUE_FLOAT",
    "SCALED_PRESSURE",
    "SYSTEM_TIME",
)
"""The messages the station reads (and the vehicles send most): decoded without a
pymavlink object per packet; tested field by field against pymavlink."""
_FAST: dict[int, _Layout] = {
    getattr(dialect, f"MAVLINK_MSG_ID_{name}"): _layout(getattr(dialect, f"MAVLINK_MSG_ID_{name}"))
    for name in FAST_MESSAGES
}


def _crc(data: bytes, extra: bytes) -> int:
    return int(_mcrf4xx(extra, _mcrf4xx(data, 0xFFFF)))


class _Checked(Protocol):
    @property
    def crc_extra(self) -> bytes: ...


K = TypeVar("K", bound=_Checked)


def _checked(packet: bytes, table: dict[int, K]) -> tuple[K, int, int, int, int] | bool | None:
    """(table entry, payload start, sequence, system id, component id) of an unsigned
    packet of a type in table whose CRC passes; False if its CRC fails; None if it is of
    another type, signed, or its length does not match its header (pymavlink decides)."""
    n = len(packet)
    if n < 8:
        return None
    if packet[0] == STX_V2:
        if n < 12 or packet[2]:
            return None
        entry = table.get(packet[7] | packet[8] << 8 | packet[9] << 16)
        head = 10
        seq, sysid, compid = packet[4], packet[5], packet[6]
    elif packet[0] == STX_V1:
        entry = table.get(packet[5])
        head = 6
        seq, sysid, compid = packet[2], packet[3], packet[4]
    else:
        return None
    if entry is None or packet[1] != n - head - 2:
        return None
    if _crc(packet[1 : n - 2], entry.crc_extra) != packet[n - 2] | packet[n - 1] << 8:
        return False
    return entry, head, seq, sysid, compid


class Decoder:
    """Decodes single packets; a packet that fails its CRC or framing comes back None.

    Unsigned packets of the types in FAST_MESSAGES are read with one struct call; every
    other packet (signed ones, other types) goes through pymavlink."""

    def __init__(self) -> None:
        self._mav = new_codec(GCS_SYSTEM_ID, GCS_COMPONENT_ID)

    def decode(self, packet: bytes) -> MAVLinkMessage | None:
        fast = self._fast(packet)
        if fast is not None:
            return None if fast is False else fast
        try:
            msg = self._mav.decode(bytearray(packet))
        except Exception:  # pymavlink raises its own MAVError and struct.error alike
            return None
        if msg is None or msg.get_type() == "BAD_DATA":
            return None
        return msg

    @staticmethod
    def _fast(packet: bytes) -> _Light | bool | None:
        """The message, False if it fails its CRC, None if it is not for the fast path."""
        got = _checked(packet, _FAST)
        if not isinstance(got, tuple):
            return got
        layout, head, seq, sysid, compid = got
        n = len(packet)
        payload = packet[head : n - 2]
        size = layout.unpacker.size
        if len(payload) != size:
            payload = (payload + bytes(size))[:size]
        fields = layout.pick(layout.unpacker.unpack(payload))
        if layout.text_fields:
            fields = tuple(text(v) if i in layout.text_fields else v for i, v in enumerate(fields))
        return layout.cls((seq, sysid, compid, *fields))


class FieldReader:
    """Chosen fields of one message type read straight from its packets: one struct call
    over the payload (the other fields skipped as padding), no message object. The
    fields come in the order asked for; char[] fields as the raw bytes (`text` reads them
    as pymavlink does)."""

    def __init__(self, msgname: str, fields: tuple[str, ...]) -> None:
        t = dialect.mavlink_map[getattr(dialect, f"MAVLINK_MSG_ID_{msgname}")]
        codes = re.findall(r"(\d*)([a-zA-Z?])", t.unpacker.format.lstrip("<"))
        if len(codes) != len(t.ordered_fieldnames):
            raise ValueError(f"{msgname}: array fields are left to pymavlink")
        wire = [f for f in t.ordered_fieldnames if f in fields]
        missing = set(fields) - set(wire)
        if missing:
            raise ValueError(f"{msgname} has no field(s) {sorted(missing)}")
        fmt = "<"
        for name, (count, code) in zip(t.ordered_fieldnames, codes, strict=True):
            item = count + code
            fmt += item if name in fields else f"{struct.calcsize('<' + item)}x"
        self.msgid: int = t.id
        self.msgname: str = msgname
        self.fields: tuple[str, ...] = fields
        self.size: int = t.unpacker.size
        self.crc_extra: bytes = bytes([t.crc_extra])
        self.unpack: Callable[[bytes], tuple[Any, ...]] = struct.Struct(fmt).unpack
        order = tuple(wire.index(f) for f in fields)
        self.pick: Callable[[tuple[Any, ...]], tuple[Any, ...]] | None = (
            None if order == tuple(range(len(fields))) else _picker(order)
        )

    def read(self, packet: bytes, head: int) -> tuple[Any, ...]:
        """The fields of a packet whose CRC passed (MAVLink 2 trims trailing zeros of
        the payload: they are put back)."""
        payload = packet[head:-2]
        if len(payload) != self.size:
            payload = (payload + bytes(self.size))[: self.size]
        values = self.unpack(payload)
        return values if self.pick is None else self.pick(values)


def _picker(order: tuple[int, ...]) -> Callable[[tuple[Any, ...]], tuple[Any, ...]]:
    get = operator.itemgetter(*order)
    return (lambda v: (get(v),)) if len(order) == 1 else get


def read_fields(
    packet: bytes, readers: dict[int, FieldReader]
) -> tuple[FieldReader, int, int, int, tuple[Any, ...]] | bool | None:
    """(reader, sequence, system id, component id, fields) of an unsigned packet of a
    type in readers; False if its CRC or length fails; None if it is of another type
    (or signed): then Decoder.decode is the way. The same checks as Decoder._fast."""
    got = _checked(packet, readers)
    if not isinstance(got, tuple):
        return got
    reader, head, seq, sysid, compid = got
    return reader, seq, sysid, compid, reader.read(packet, head)


MAX_PACKET_BYTES = 280
"""The longest MAVLink 2 packet: 10 header, 255 payload, 2 CRC, 13 signature."""


def incomplete_tail(buf: bytes, start: int) -> int | None:
    """On a byte stream: the first start marker at or after start whose packet runs past
    the end of buf (its header or its body is still to come), or None."""
    i = next_marker(buf, start)
    while i < len(buf):
        size = packet_length(buf, i)
        if (size == 0 or i + size > len(buf)) and len(buf) - i < MAX_PACKET_BYTES:
            return i
        i = next_marker(buf, i + 1)
    return None


def scan(data: bytes, decoder: Decoder) -> Iterator[tuple[bytes, MAVLinkMessage] | int]:
    """The packets in a buffer that pass their CRC, with the length of each run of bytes
    between them that does not (an int). Where a candidate fails, the search goes on from
    the next start marker, so junk (even junk full of start markers) never costs a valid
    packet after it. A message the dialect does not know cannot be checked: it is taken
    only where no valid packet starts inside it and a valid one or the end follows it."""
    i = run = 0
    n = len(data)
    while i < n:
        size = packet_length(data, i)
        if size and i + size <= n and could_be_packet(data, i):
            pkt = data[i : i + size]
            msg = decoder.decode(pkt)
            if msg is not None and _framed(data, i, size, msg, decoder):
                if run:
                    yield run
                    run = 0
                yield pkt, msg
                i += size
                continue
        j = next_marker(data, i + 1)
        run += j - i
        i = j
    if run:
        yield run


def _known_at(data: bytes, i: int, decoder: Decoder) -> bool:
    size = packet_length(data, i)
    if not size or i + size > len(data) or not could_be_packet(data, i):
        return False
    msg = decoder.decode(data[i : i + size])
    return msg is not None and not is_unknown(msg)


def _framed(data: bytes, i: int, size: int, msg: MAVLinkMessage, decoder: Decoder) -> bool:
    """Whether a candidate that decoded is a packet of its own. A packet cut short just
    before a packet that starts with the byte its CRC lacked decodes too: the packet
    that starts at its last byte wins."""
    if is_unknown(msg):
        return _unknown_framed(data, i, size, decoder)
    last = i + size - 1
    return data[last] not in (STX_V1, STX_V2) or not _known_at(data, last, decoder)


def _unknown_framed(data: bytes, i: int, size: int, decoder: Decoder) -> bool:
    end = i + size
    k = next_marker(data, i + 1)
    while k < end:
        if _known_at(data, k, decoder):
            return False
        k = next_marker(data, k + 1)
    return end == len(data) or _known_at(data, end, decoder)


# ------------------------------------------------------------------------------ tlog


class TlogRecord(NamedTuple):
    """One record of a tlog (a named tuple: built once per packet)."""

    t_recv_us: int
    packet: bytes


class TlogError(ValueError):
    """The file is not a tlog at all."""


def tlog_record(t_recv_us: int, packet: bytes) -> bytes:
    """One .tlog record: the receive time [us since the Unix epoch], big-endian, then the
    packet."""
    return struct.pack(">Q", t_recv_us) + packet


TLOG_FLUSH_S = 1.0
"""A recording reaches the file at least this often [s]: a killed process loses at most
the last second."""


class TlogWriter:
    """Appends records; written through to the file every TLOG_FLUSH_S and on close."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh: BinaryIO = open(self.path, "wb")  # noqa: SIM115 - owned until close()
        self.records = 0
        self._flushed = time.monotonic()

    def write(self, t_recv_us: int, packet: bytes) -> None:
        self._fh.write(tlog_record(t_recv_us, packet))
        self.records += 1
        now = time.monotonic()
        if now - self._flushed >= TLOG_FLUSH_S:
            self._flushed = now
            self._fh.flush()

    def flush(self) -> None:
        self._fh.flush()

    def close(self) -> None:
        if not self._fh.closed:
            self._fh.close()


@dataclass
class TlogStats:
    records: int = 0
    junk_bytes: int = 0
    truncated_tail: bool = False
    position: int = 0
    """Bytes of the file read so far."""
    bad_times: int = 0
    """Records kept whose receive time was corrupt (neither the record before nor the one
    after agrees with it): stamped with the time of the record before."""
    time_jumps: int = 0
    """Places where the recording's clock jumped and the records after agree with the new
    time (recordings joined into one file, or the recorder's clock set): kept."""


FORWARD_US = 86_400_000_000
"""A record's time lies within a day after the last good record's ..."""
BACK_US = 60_000_000
"""... and at most a minute before it."""


def _follows(t_before: int, t: int) -> bool:
    """Whether a record at time t can follow one at t_before (FORWARD_US, BACK_US)."""
    return t_before - BACK_US <= t <= t_before + FORWARD_US


def _record_time(t: int, last_t: int | None, t_next: int | None, st: TlogStats) -> int:
    """The receive time to give a record whose packet is real, at time t, after a record
    at last_t and before one at t_next (None: none read), judged by both neighbours: a time
    the next record agrees with but the last does not is a new time base (a jump, kept);
    one that agrees with neither, or that the next record contradicts where it agrees
    with the last, is corrupt and takes last_t. Counted in st."""
    if last_t is None:
        return t
    next_new = t_next is not None and _follows(t, t_next)
    next_old = t_next is not None and _follows(last_t, t_next)
    if _follows(last_t, t):
        if next_new or not next_old:
            return t
    elif next_new and not next_old:
        st.time_jumps += 1
        return t
    st.bad_times += 1
    return last_t


def _checks_out(data: bytes, i: int, end: int, framed: bool, decoder: Decoder) -> bool:
    """Whether a record that is not plainly framed (or follows garbage) is real: its
    packet passes its CRC (an unknown message, whose CRC cannot be checked, only where
    the next record's header starts where it ends)."""
    msg = decoder.decode(data[i + 8 : end])
    return msg is not None and (framed or not is_unknown(msg))


def _taken_time(
    data: bytes,
    i: int,
    end: int,
    following: int,
    last_t: int | None,
    resyncing: bool,
    decoder: Decoder,
    st: TlogStats,
) -> int | None:
    """The time of a record at data[i] not plainly framed and in time (see read_tlog);
    None if it is not taken."""
    (t_us,) = _TIME_US(data, i)
    framed = end == len(data) or following > 0
    t_next = _TIME_US(data, end)[0] if following > 0 else None
    in_time = last_t is None or _follows(last_t, t_us)
    timely = in_time or not resyncing or (t_next is not None and _follows(t_us, t_next))
    if (framed and not resyncing and in_time) or (
        timely and _checks_out(data, i, end, framed and in_time, decoder)
    ):
        return _record_time(t_us, last_t, t_next, st)
    return None


def _junk_byte(path: str | Path, st: TlogStats, first: bool, position: int) -> None:
    """Count a byte that starts no record; a file with none in its first 4 KiB is no tlog."""
    if first and position >= 4096:
        raise TlogError(f"{path}: not a tlog (no MAVLink record in the first 4 KiB)")
    st.junk_bytes += 1


_TIME_US = struct.Struct(">Q").unpack_from
"""A tlog record's 8-byte big-endian receive time [us]."""


READ_CHUNK = 1 << 20
"""A tlog is read in pieces this large [bytes]: memory does not grow with the file."""
RECORD_JUNK = 255
"""Junk bytes between a record's time and its packet that are skipped to the packet (as
a live link's scan skips junk before one)."""
LOOKAHEAD = 8 + RECORD_JUNK + 280 + 8 + 3
"""Bytes a record's checks may look at: the record (8-byte time, junk, a packet of at
most 280 bytes) and the next record's header."""


def _junk_record(
    data: bytes, i: int, last_t: int | None, decoder: Decoder, st: TlogStats
) -> tuple[TlogRecord, int] | None:
    """A record at data[i], after a good one at last_t, whose time follows that one's but
    whose packet does not start right after its time: the packet after the junk
    (_after_junk), and where the next record starts; None if there is none."""
    if last_t is None or i + 8 > len(data) or not _follows(last_t, _TIME_US(data, i)[0]):
        return None
    j = _after_junk(data, i, decoder)
    if j < 0:
        return None
    end = j + packet_length(data, j)
    st.junk_bytes += j - i - 8
    st.records += 1
    return TlogRecord(_TIME_US(data, i)[0], data[j:end]), end


def _after_junk(data: bytes, i: int, decoder: Decoder) -> int:
    """Where the packet of a record at data[i] starts when junk sits between its time and
    its packet: the first start marker within RECORD_JUNK bytes at which a known message
    passes its CRC (-1: none)."""
    j = next_marker(data, i + 9)
    while j <= i + 8 + RECORD_JUNK:
        size = packet_length(data, j)
        if size and j + size <= len(data) and could_be_packet(data, j):
            msg = decoder.decode(data[j : j + size])
            if msg is not None and not is_unknown(msg):
                return j
        j = next_marker(data, j + 1)
    return -1


def read_tlog(path: str | Path, stats: TlogStats | None = None) -> Iterator[TlogRecord]:
    """Records of a .tlog, resynchronising over garbage and stopping at a truncated tail;
    read a piece at a time (stats.position says how far).

    Raises TlogError if the start of the file holds no valid record at all.
    """
    st = stats if stats is not None else TlogStats()
    decoder = Decoder()
    first = True
    resyncing = False
    last_t: int | None = None
    data = b""
    offset = i = 0  # data[0] is the file's byte `offset`
    known = -1  # the next record's packet length, where the last record's check read it
    eof = False
    back = BACK_US  # inlined where every record goes
    with open(path, "rb") as fh:
        while True:
            st.position = offset + i
            if not eof and len(data) - i < LOOKAHEAD:
                chunk = fh.read(READ_CHUNK)
                eof = not chunk
                offset += i
                data = data[i:] + chunk
                i = 0
                continue
            if i + 8 >= len(data):
                break
            n = packet_length(data, i + 8) if known < 0 else known
            known = -1
            end = i + 8 + n
            if n and end <= len(data):
                # Any 0xFD or 0xFE byte looks like a packet start (timestamps and
                # payloads hold them too). A record right after the last one, within a
                # minute of its time, after which the next record's header starts, is
                # taken as it is. Any other (not followed by a header, at a time further
                # away, or after garbage) only if its packet checks out (a message
                # unknown to the dialect, whose CRC cannot be checked, only framed and at
                # a time that follows), and after garbage only if its time follows the
                # last record's or leads to the next one's (a random byte's "time" does
                # neither); its time is judged by the records on both sides
                # (_record_time).
                (t_us,) = _TIME_US(data, i)
                following = packet_length(data, end + 8) if end < len(data) else 0
                framed = end == len(data) or following > 0
                plain = (
                    framed
                    and not resyncing
                    and (last_t is None or last_t - back <= t_us <= last_t + back)
                )
                t_taken = (
                    t_us
                    if plain
                    else _taken_time(data, i, end, following, last_t, resyncing, decoder, st)
                )
                if t_taken is not None:
                    first = resyncing = False
                    last_t = t_taken
                    st.records += 1
                    yield TlogRecord(last_t, data[i + 8 : end])
                    i, known = end, following if following > 0 else -1
                    continue
            elif n:  # the record runs past the end of the file
                st.truncated_tail = True
                return
            # Junk between a record's time and its packet (after garbage: none known).
            got = _junk_record(data, i, None if resyncing else last_t, decoder, st)
            if got is not None:
                last_t, i = got[0].t_recv_us, got[1]
                yield got[0]
            else:
                _junk_byte(path, st, first, offset + i)
                resyncing = True
                i += 1
    if first and len(data) > 0:
        raise TlogError(f"{path}: not a tlog (no MAVLink record found)")
    if i < len(data):
        st.truncated_tail = True
