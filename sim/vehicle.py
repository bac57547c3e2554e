"""The simulated UAV as a MAVLink 2 vehicle on UDP (ardupilotmega dialect).

Streams a flight (simulated, or played back from a data file) at the vehicle clock:
HEARTBEAT and SYSTEM_TIME at 1 Hz; HIGHRES_IMU, ATTITUDE, AOA_SSA, VFR_HUD,
SERVO_OUTPUT_RAW and NAMED_VALUE_FLOAT (QDOT, and THRUST where thrust is measured) at
the configured rates. Answers a ground station's HEARTBEAT and SET_MESSAGE_INTERVAL
(with COMMAND_ACK) and keeps streaming when the ground station goes away.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import STREAMED_MESSAGES, ConfigError, LinkConfig
from gcs_estimator.ingest.flightdata import Recording
from gcs_estimator.ingest.telemetry import mavlink, pwm
from gcs_estimator.ingest.telemetry.mavlink import Codec, TlogWriter
from gcs_estimator.ingest.telemetry.signing import load_key, sign_outgoing
from gcs_estimator.model.channels import Channel
from sim.ports import Port, UdpOut

BOOT_OFFSET_S = 5.0
"""The vehicle has been up this long when the recording starts [s]."""


@dataclass
class VehicleStats:
    sent: int = 0
    gcs_heartbeats: int = 0
    rate_changes: int = 0


@dataclass
class SimulatedVehicle:
    """One vehicle: a recording to stream, a link mapping, and a UDP target or a port
    (sim.ports: udpin, serial, shared by several vehicles)."""

    recording: Recording
    link: LinkConfig
    target: tuple[str, int] | Port
    system_id: int = 1
    speed: float = 1.0
    """Multiple of real time; 0 = as fast as possible."""
    tlog: Path | None = None
    boot_s: float = BOOT_OFFSET_S
    """How long the vehicle has been up when the flight starts [s] (its clock's origin);
    beyond 4,295 s its 32-bit SERVO_OUTPUT_RAW.time_usec has wrapped."""
    stats: VehicleStats = field(default_factory=VehicleStats)
    rates: dict[str, float] = field(default_factory=dict)
    requested: set[str] = field(default_factory=set)
    """Messages asked for once (REQUEST_MESSAGE), sent with the next sample."""

    def __post_init__(self) -> None:
        self.rates = {m: self.link.rate(m) for m in STREAMED_MESSAGES}
        self.codec = Codec(self.system_id, 1)
        self.mav = self.codec.mav
        if self.link.signing_key_file:
            # Signs what it sends, and its parser refuses unsigned or wrongly signed packets.
            try:
                key = load_key(self.link.signing_key_file)
            except (OSError, ValueError) as exc:
                raise ConfigError(f"link.signing_key_file: {exc}") from exc
            sign_outgoing(self.mav, key, time.time())
        self.port: Port = UdpOut(self.target) if isinstance(self.target, tuple) else self.target
        self._tlog = TlogWriter(self.tlog) if self.tlog else None

    def _send(self, msg: Any) -> None:
        self._send_packet(self.codec.pack(msg))

    def _send_packet(self, buf: bytes) -> None:
        self.port.send(buf)
        self.stats.sent += 1
        if self._tlog is not None:
            self._tlog.write(int(time.time() * 1e6), buf)

    def _serve(self) -> None:
        """Answer what the ground station sent."""
        for data in self.port.receive():
            for msg in self.codec.parse(data):
                self._answer(msg)

    def _answer(self, msg: Any) -> None:
        """One message from the ground: commands, data streams, the parameter protocol."""
        kind = msg.get_type()
        if kind == "HEARTBEAT":
            self.stats.gcs_heartbeats += 1
        elif kind in ("COMMAND_LONG", "COMMAND_INT"):
            self._command(msg)
        elif getattr(msg, "target_system", 0) not in (0, self.system_id):
            return
        elif kind == "REQUEST_DATA_STREAM":
            self._data_stream(int(msg.req_stream_id), msg.req_message_rate, msg.start_stop)
        elif kind == "PARAM_REQUEST_LIST":
            for index in range(len(STREAM_PARAMS)):
                self._param_value(index)
        elif kind == "PARAM_REQUEST_READ":
            self._param_value(self._param_index(msg.param_id, int(msg.param_index)))
        elif kind == "PARAM_SET":
            self._param_set(msg.param_id, float(msg.param_value))

    def _command(self, msg: Any) -> None:
        """A command for this vehicle (or for every vehicle): acknowledged to its sender;
        UNSUPPORTED unless it is SET_MESSAGE_INTERVAL."""
        if int(msg.target_system) not in (0, self.system_id):
            return
        result = mavlink.MAV_RESULT_UNSUPPORTED
        if msg.get_type() == "COMMAND_LONG" and msg.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            result = self._set_interval(int(msg.param1), float(msg.param2))
        elif msg.command == mavlink.MAV_CMD_REQUEST_MESSAGE:
            result = self._request_message(int(msg.param1))
        ack = self.codec.command_ack(
            int(msg.command), result, msg.get_srcSystem(), msg.get_srcComponent()
        )
        self._send_packet(ack)

    def _set_interval(self, message_id: int, interval_us: float) -> int:
        """SET_MESSAGE_INTERVAL: stream the message at 1e6 / interval_us Hz (-1: stop; 0: the
        default rate); DENIED for a message this vehicle does not stream."""
        name = mavlink.MESSAGE_NAME.get(message_id)
        ok = name in STREAMED_MESSAGES
        if name is not None and ok:
            rate = 1e6 / interval_us if interval_us > 0 else self.link.rate(name)
            self.rates[name] = 0.0 if interval_us < 0 else rate
            self.stats.rate_changes += 1
        return int(mavlink.MAV_RESULT_ACCEPTED if ok else mavlink.MAV_RESULT_DENIED)

    def _request_message(self, message_id: int) -> int:
        """REQUEST_MESSAGE: a heartbeat at once, a streamed message with the next sample;
        DENIED for any other."""
        if message_id == mavlink.MSG_ID["HEARTBEAT"]:
            self._send_packet(self.codec.heartbeat(mavlink.MAV_TYPE_FIXED_WING))
            return int(mavlink.MAV_RESULT_ACCEPTED)
        name = mavlink.MESSAGE_NAME.get(message_id)
        if name not in STREAMED_MESSAGES:
            return int(mavlink.MAV_RESULT_DENIED)
        self.requested.add(str(name))
        return int(mavlink.MAV_RESULT_ACCEPTED)

    def _data_stream(self, stream_id: int, rate_hz: float, start: int) -> None:
        """REQUEST_DATA_STREAM (the older way): the stream's messages at rate_hz, or off."""
        for name in STREAMS.get(stream_id, ()):
            if name in STREAMED_MESSAGES:
                self.rates[name] = float(rate_hz) if start else 0.0
                self.stats.rate_changes += 1

    @staticmethod
    def _param_index(param_id: str | bytes, index: int) -> int:
        name = param_id.decode() if isinstance(param_id, bytes) else param_id
        names = [p for p, _ in STREAM_PARAMS]
        return names.index(name) if name in names else index

    def _param_value(self, index: int) -> None:
        if not 0 <= index < len(STREAM_PARAMS):
            return
        name, stream = STREAM_PARAMS[index]
        value = max((self.rates[m] for m in STREAMS[stream] if m in self.rates), default=0.0)
        self._send(
            self.mav.param_value_encode(
                name.encode(), value, mavlink.MAV_PARAM_TYPE_REAL32, len(STREAM_PARAMS), index
            )
        )

    def _param_set(self, param_id: str | bytes, value: float) -> None:
        """PARAM_SET of a stream rate: applied, and answered with the value now held."""
        index = self._param_index(param_id, -1)
        if index >= 0:
            self._data_stream(STREAM_PARAMS[index][1], value, int(value > 0))
            self._param_value(index)

    def run(self, stop_after_s: float | None = None) -> VehicleStats:
        """Stream the whole recording (or until stop_after_s of vehicle time)."""
        rec = self.recording
        start_wall = time.time()
        t_first = float(rec.t_s[0])
        next_due = {m: t_first for m in STREAMED_MESSAGES}
        next_hb = t_first
        for i in range(len(rec)):
            t = float(rec.t_s[i])
            if stop_after_s is not None and t - t_first > stop_after_s:
                break
            self._pace(t - t_first, start_wall)
            self._serve()
            tv = t - t_first + self.boot_s
            # time_boot_ms is 32-bit (wraps after 49.7 days), servo time_usec too (71.6 min).
            us, ms = int(round(tv * 1e6)), int(round(tv * 1e3)) & 0xFFFFFFFF
            if t >= next_hb - 1e-9:
                next_hb += 1.0
                self._send_packet(self.codec.heartbeat(mavlink.MAV_TYPE_FIXED_WING))
                self._send(self.mav.system_time_encode(int(time.time() * 1e6), ms))
            due = self._due(t, next_due) | self.requested
            self.requested = set()
            climb = self._climb(i)
            for msg in self._messages(due, us, ms, rec.measurements[i], rec.inputs[i], climb):
                self._send(msg)
        self._serve()
        self.close()
        return self.stats

    def _pace(self, t_rel: float, start_wall: float) -> None:
        """At speed > 0, wait until t_rel [s] of flight has passed in real time / speed."""
        if self.speed > 0:
            delay = t_rel / self.speed - (time.time() - start_wall)
            if delay > 0:
                time.sleep(delay)

    def _due(self, t: float, next_due: dict[str, float]) -> set[str]:
        """The messages due at vehicle time t at their current rates."""
        due = set()
        for m in STREAMED_MESSAGES:
            r = self.rates[m]
            if r > 0 and t >= next_due[m] - 1e-6:
                due.add(m)
                next_due[m] += 1.0 / r
                if next_due[m] < t:  # rate above the sample rate: once per sample
                    next_due[m] = t + 1.0 / r
        return due

    def _climb(self, i: int) -> float:
        """The true climb rate [m/s, up positive] at sample i: the recording's vertical
        speed (aux "vz", down positive), else its measured h_dot, else 0."""
        rec = self.recording
        vz = rec.aux.get("vz")
        if vz is not None and math.isfinite(vz[i]):
            return -float(vz[i])
        y = rec.measurements[i]
        return float(y[Channel.HDOT]) if math.isfinite(y[Channel.HDOT]) else 0.0

    def _messages(
        self, due: set[str], us: int, ms: int, y: FloatArray, inputs: FloatArray, climb: float
    ) -> list[Any]:
        """The due messages of one sample. Inputs first, then observations: a frame is
        complete when its last observation arrives."""
        link, mav = self.link, self.mav
        de, power = float(inputs[0]), float(inputs[1])
        out: list[Any] = []
        if "SERVO_OUTPUT_RAW" in due:
            servos = [0] * 16
            servos[link.elevator_servo - 1] = _pwm(pwm.elevator_pwm(link, de))
            if link.throttle_servo:
                servos[link.throttle_servo - 1] = _pwm(pwm.throttle_pwm(link, power))
            out.append(mav.servo_output_raw_encode(us & 0xFFFFFFFF, 0, *servos))
        if "NAMED_VALUE_FLOAT" in due:
            if not link.throttle_servo:
                out.append(mav.named_value_float_encode(ms, link.thrust_name.encode(), power))
            if math.isfinite(y[4]):
                out.append(mav.named_value_float_encode(ms, link.qdot_name.encode(), float(y[4])))
        if "AOA_SSA" in due and math.isfinite(y[1]):  # no vane: no AOA_SSA
            out.append(mav.aoa_ssa_encode(us, math.degrees(float(y[1])), 0.0))
        if "ATTITUDE" in due:
            roll, p, r = _lateral(inputs)
            out.append(mav.attitude_encode(ms, roll, float(y[2]), 0.0, p, float(y[3]), r))
        if "HIGHRES_IMU" in due:
            imu = (float(y[5]), 0.0, float(y[6]), 0.0, float(y[3]), 0.0) + (0.0,) * 7
            out.append(mav.highres_imu_encode(us, *imu, 0b11111))
        if "VFR_HUD" in due:
            out.extend(self._climb_messages(ms, y, power, climb))
        return out

    def _climb_messages(self, ms: int, y: FloatArray, power: float, climb: float) -> list[Any]:
        """VFR_HUD with the true climb rate [m/s, up positive], and before it, where the
        vehicle has a climb-rate sensor (simulation.climb_rate), its h_dot as
        GLOBAL_POSITION_INT.vz (cm/s, down positive) at VFR_HUD's rate."""
        link, mav = self.link, self.mav
        out: list[Any] = []
        if len(y) > Channel.HDOT and math.isfinite(y[Channel.HDOT]):
            vz_cm = int(round(-100.0 * float(y[Channel.HDOT])))
            out.append(mav.global_position_int_encode(ms, 0, 0, 0, 0, 0, 0, vz_cm, 0))
        thr_pct = max(0, min(100, int(round(100 * power)) if link.throttle_servo else 0))
        out.append(mav.vfr_hud_encode(float(y[0]), float(y[0]), 0, thr_pct, 100.0, climb))
        return out

    def close(self) -> None:
        if self._tlog is not None:
            self._tlog.close()
            self._tlog = None
        self.port.close()


def _lateral(inputs: FloatArray) -> tuple[float, float, float]:
    """Bank angle, roll and yaw rate of a sample's inputs (model.channels; 0 wings level
    where the flight has none)."""
    if inputs.shape[0] < 6:
        return 0.0, 0.0, 0.0
    return tuple(float(v) if math.isfinite(v) else 0.0 for v in inputs[3:6])  # type: ignore[return-value]


STREAMS: dict[int, tuple[str, ...]] = {
    mavlink.MAV_DATA_STREAM_ALL: tuple(STREAMED_MESSAGES),
    mavlink.MAV_DATA_STREAM_RAW_SENSORS: ("HIGHRES_IMU",),
    mavlink.MAV_DATA_STREAM_RC_CHANNELS: ("SERVO_OUTPUT_RAW",),
    mavlink.MAV_DATA_STREAM_EXTRA1: ("ATTITUDE",),
    mavlink.MAV_DATA_STREAM_EXTRA2: ("VFR_HUD",),
    mavlink.MAV_DATA_STREAM_EXTRA3: ("AOA_SSA", "NAMED_VALUE_FLOAT"),
}
"""REQUEST_DATA_STREAM's streams and the messages in each (as ArduPlane groups them)."""
STREAM_PARAMS: tuple[tuple[str, int], ...] = (
    ("SR0_RAW_SENS", mavlink.MAV_DATA_STREAM_RAW_SENSORS),
    ("SR0_RC_CHAN", mavlink.MAV_DATA_STREAM_RC_CHANNELS),
    ("SR0_EXTRA1", mavlink.MAV_DATA_STREAM_EXTRA1),
    ("SR0_EXTRA2", mavlink.MAV_DATA_STREAM_EXTRA2),
    ("SR0_EXTRA3", mavlink.MAV_DATA_STREAM_EXTRA3),
)
"""The vehicle's parameters: ArduPilot's stream rates [Hz], read and set."""


def _pwm(us: float) -> int:
    return max(0, min(65535, int(round(us))))
