"""The MAVLink edge: the only module of the ground station that imports pymavlink.

MAVLink 2, ardupilotmega dialect (it includes common), loaded directly from
pymavlink.dialects.v20, so no environment variable has to be set before import. Also
the .tlog format: records of an 8-byte big-endian receive time [us since the Unix epoch]
followed by one raw MAVLink packet.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

from pymavlink.dialects.v20 import ardupilotmega as dialect

MAVLinkMessage = Any
"""A pymavlink message object; never leaves the telemetry package."""

STX_V1, STX_V2 = 0xFE, 0xFD
SIGNED_FLAG = 0x01
GCS_SYSTEM_ID, GCS_COMPONENT_ID = 255, 190

MSG_ID = {
    "HEARTBEAT": dialect.MAVLINK_MSG_ID_HEARTBEAT,
    "SYSTEM_TIME": dialect.MAVLINK_MSG_ID_SYSTEM_TIME,
    "ATTITUDE": dialect.MAVLINK_MSG_ID_ATTITUDE,
    "HIGHRES_IMU": dialect.MAVLINK_MSG_ID_HIGHRES_IMU,
    "VFR_HUD": dialect.MAVLINK_MSG_ID_VFR_HUD,
    "SERVO_OUTPUT_RAW": dialect.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW,
    "AOA_SSA": dialect.MAVLINK_MSG_ID_AOA_SSA,
    "NAMED_VALUE_FLOAT": dialect.MAVLINK_MSG_ID_NAMED_VALUE_FLOAT,
}
MESSAGE_NAME = {v: k for k, v in MSG_ID.items()}
MAV_TYPE_FIXED_WING = dialect.MAV_TYPE_FIXED_WING
MAV_TYPE_GCS = dialect.MAV_TYPE_GCS
MAV_CMD_SET_MESSAGE_INTERVAL = dialect.MAV_CMD_SET_MESSAGE_INTERVAL
MAV_RESULT_ACCEPTED = dialect.MAV_RESULT_ACCEPTED
MAV_RESULT_DENIED = dialect.MAV_RESULT_DENIED


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
        else:
            autopilot = dialect.MAV_AUTOPILOT_ARDUPILOTMEGA
            base_mode = dialect.MAV_MODE_FLAG_AUTO_ENABLED
        return self.pack(
            self.mav.heartbeat_encode(mav_type, autopilot, base_mode, 0, dialect.MAV_STATE_ACTIVE)
        )

    def set_message_interval(self, target_system: int, message: str, rate_hz: float) -> bytes:
        """COMMAND_LONG MAV_CMD_SET_MESSAGE_INTERVAL: stream `message` at rate_hz (0: stop)."""
        interval_us = 1e6 / rate_hz if rate_hz > 0 else -1
        msg = self.mav.command_long_encode(
            target_system,
            1,
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

    def command_ack(self, command: int, result: int) -> bytes:
        return self.pack(self.mav.command_ack_encode(command, result))

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


def split_packets(datagram: bytes) -> tuple[list[bytes], int]:
    """Split a datagram into packets by their headers; returns (packets, junk bytes)."""
    packets: list[bytes] = []
    i = junk = 0
    while i < len(datagram):
        n = packet_length(datagram, i)
        if n == 0 or i + n > len(datagram):
            # Resynchronise on the next start marker.
            j = i + 1
            while j < len(datagram) and datagram[j] not in (STX_V1, STX_V2):
                j += 1
            junk += j - i
            i = j
            continue
        packets.append(datagram[i : i + n])
        i += n
    return packets, junk


class Decoder:
    """Decodes single packets; bad ones come back as None with the reason counted."""

    def __init__(self) -> None:
        self._mav = new_codec(GCS_SYSTEM_ID, GCS_COMPONENT_ID)

    def decode(self, packet: bytes) -> MAVLinkMessage | None:
        try:
            msg = self._mav.decode(bytearray(packet))
        except Exception:  # pymavlink raises its own MAVError and struct.error alike
            return None
        if msg is None or msg.get_type() == "BAD_DATA":
            return None
        return msg


# ------------------------------------------------------------------------------ tlog


@dataclass(frozen=True)
class TlogRecord:
    t_recv_us: int
    packet: bytes


class TlogError(ValueError):
    """The file is not a tlog at all."""


def tlog_record(t_recv_us: int, packet: bytes) -> bytes:
    """One .tlog record: the receive time [us since the Unix epoch], big-endian, then the
    packet."""
    return struct.pack(">Q", t_recv_us) + packet


class TlogWriter:
    """Appends records; flushed on close (and by the caller at will)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh: BinaryIO = open(self.path, "wb")  # noqa: SIM115 - owned until close()
        self.records = 0

    def write(self, t_recv_us: int, packet: bytes) -> None:
        self._fh.write(tlog_record(t_recv_us, packet))
        self.records += 1

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


RESYNC_WINDOW_US = 86_400_000_000
"""After garbage, a candidate record's time must lie within a day of the last good one."""


def _plausible_record(data: bytes, i: int, n: int, t_us: int, last_t: int | None) -> bool:
    """Whether a record found while resynchronising is real: any 0xFD or 0xFE byte looks
    like a packet start (timestamps hold them too), so its time must follow the last
    good record's and the next record, if any, must start where this one ends."""
    if last_t is not None and abs(t_us - last_t) > RESYNC_WINDOW_US:
        return False
    end = i + 8 + n
    return end == len(data) or packet_length(data, end + 8) > 0


def read_tlog(path: str | Path, stats: TlogStats | None = None) -> Iterator[TlogRecord]:
    """Records of a .tlog, resynchronising over garbage and stopping at a truncated tail.

    Raises TlogError if the start of the file holds no valid record at all.
    """
    data = Path(path).read_bytes()
    st = stats if stats is not None else TlogStats()
    i = 0
    first = True
    resyncing = False
    last_t: int | None = None
    while i + 8 < len(data):
        n = packet_length(data, i + 8)
        if n and i + 8 + n <= len(data):
            (t_us,) = struct.unpack_from(">Q", data, i)
            if not resyncing or _plausible_record(data, i, n, t_us, last_t):
                first = resyncing = False
                last_t = t_us
                st.records += 1
                yield TlogRecord(t_us, data[i + 8 : i + 8 + n])
                i += 8 + n
                continue
        elif n and i + 8 + n > len(data):
            st.truncated_tail = True
            return
        if first and i >= 4096:
            raise TlogError(f"{path}: not a tlog (no MAVLink record in the first 4 KiB)")
        st.junk_bytes += 1
        resyncing = True
        i += 1
    if first and len(data) > 0:
        raise TlogError(f"{path}: not a tlog (no MAVLink record found)")
    if i < len(data):
        st.truncated_tail = True
