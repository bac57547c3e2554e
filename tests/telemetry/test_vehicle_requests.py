"""`listen` asks a vehicle for what it needs, over real UDP on loopback: a test-local
pymavlink peer plays an older ArduPlane (it answers MAV_CMD_SET_MESSAGE_INTERVAL with
UNSUPPORTED, honours REQUEST_DATA_STREAM and the parameter protocol) and records what
the station sent. The station asks for the rates (SET_MESSAGE_INTERVAL of its messages,
then ArduPilot's stream groups), reads the servo parameters by PARAM_REQUEST_READ, and
uses them: the elevator is read from the vehicle's output 4, not [link]'s output 2."""

from __future__ import annotations

import json
import math
import select
import socket
import time
from dataclasses import dataclass, field
from pathlib import Path

import pyarrow.parquet as pq
from pymavlink.dialects.v20 import ardupilotmega as dialect

from gcs_estimator.ingest.telemetry import mavlink
from gcs_estimator.ingest.telemetry.mavlink import Codec
from tests.telemetry.station import start_listen
from tests.telemetry.test_message_sets import ARDUPLANE_PARAMS
from tests.udp import loopback, port_of

PARAMS = ARDUPLANE_PARAMS
"""The peer's servo parameters: the elevator on output 4, reversed, trimmed off centre."""
SERVO4_US = 1700
"""(1700 - 1450) / (1900 - 1450) = 5/9 of full output, reversed: 5/9 nose down."""
TRAVEL_DEG = 18.0
ELEVATOR_RAD = math.radians(TRAVEL_DEG * 5 / 9)
DEFAULT_HZ = 4.0
"""ArduPlane's default stream rate before anyone asks."""
ASKED_CAP_HZ = 25.0
"""The peer streams no faster than this (a loaded test machine)."""
STREAM_OF = {
    "RAW_IMU": dialect.MAV_DATA_STREAM_RAW_SENSORS,
    "ATTITUDE": dialect.MAV_DATA_STREAM_EXTRA1,
    "VFR_HUD": dialect.MAV_DATA_STREAM_EXTRA2,
    "SERVO_OUTPUT_RAW": dialect.MAV_DATA_STREAM_RC_CHANNELS,
}
DEADLINE_S = 240.0


@dataclass
class Peer:
    """An ArduPlane as far as the station's requests go."""

    sock: socket.socket
    codec: Codec = field(default_factory=lambda: Codec(1, 1))
    station: tuple[str, int] | None = None
    intervals: list[int] = field(default_factory=list)
    """Message ids the station asked intervals for."""
    streams: dict[int, int] = field(default_factory=dict)
    """REQUEST_DATA_STREAM: stream id -> rate [Hz]."""
    param_reads: list[str] = field(default_factory=list)
    sent: int = 0

    def receive(self) -> None:
        data, address = self.sock.recvfrom(65536)
        self.station = address
        for msg in self.codec.parse(data):
            self.answer(msg)

    def answer(self, msg: object) -> None:
        kind = msg.get_type()  # type: ignore[attr-defined]
        if kind == "COMMAND_LONG" and msg.command == dialect.MAV_CMD_SET_MESSAGE_INTERVAL:  # type: ignore[attr-defined]
            self.intervals.append(int(msg.param1))  # type: ignore[attr-defined]
            ack = self.codec.command_ack(msg.command, dialect.MAV_RESULT_UNSUPPORTED, 255, 190)  # type: ignore[attr-defined]
            self.send(ack)
        elif kind == "REQUEST_DATA_STREAM":
            self.streams[int(msg.req_stream_id)] = int(msg.req_message_rate)  # type: ignore[attr-defined]
        elif kind == "PARAM_REQUEST_READ":
            name = msg.param_id  # type: ignore[attr-defined]
            self.param_reads.append(name)
            if name in PARAMS:
                index = list(PARAMS).index(name)
                pv = self.codec.mav.param_value_encode(
                    name.encode(), PARAMS[name], dialect.MAV_PARAM_TYPE_REAL32, 900, index
                )
                self.send(self.codec.pack(pv))

    def send(self, packet: bytes) -> None:
        if self.station is not None:
            self.sock.sendto(packet, self.station)
            self.sent += 1

    def rate(self, name: str) -> float:
        asked = self.streams.get(STREAM_OF[name])
        return DEFAULT_HZ if asked is None else min(float(asked), ASKED_CAP_HZ)

    def messages(self, name: str, t: float) -> bytes:
        mav = self.codec.mav
        if name == "RAW_IMU":
            # pitch rate as a slow sine [mrad/s], level flight's -1 g on z
            q = round(50 * math.sin(t))
            return self.codec.pack(
                mav.raw_imu_encode(int(t * 1e6), 30, 0, -1000, 0, q, 0, 0, 0, 0, 0, 0)
            )
        if name == "ATTITUDE":
            return self.codec.pack(mav.attitude_encode(int(t * 1e3), 0, 0.05, 0, 0, 0, 0))
        if name == "VFR_HUD":
            return self.codec.pack(mav.vfr_hud_encode(18.0, 18.0, 0, 40, 100.0, 0.0))
        servos = [1500] * 16
        servos[3], servos[2] = SERVO4_US, 1400
        return self.codec.pack(mav.servo_output_raw_encode(int(t * 1e6), 0, *servos))


def _done(peer: Peer) -> bool:
    return (
        mavlink.MSG_ID["RAW_IMU"] in peer.intervals
        and dialect.MAV_DATA_STREAM_RAW_SENSORS in peer.streams
        and "SERVO4_REVERSED" in peer.param_reads
    )


def _fly(peer: Peer) -> None:
    """Stream (at the rates asked for) until the station has asked for everything and
    a few seconds more have been flown at those rates; then fall silent."""
    start = time.monotonic()
    due = dict.fromkeys(STREAM_OF, 0.0)
    heartbeat = 0.0
    settled: float | None = None
    while True:
        t = time.monotonic() - start
        assert t < DEADLINE_S, (peer.intervals, peer.streams, peer.param_reads)
        if settled is None and _done(peer):
            settled = t
        if settled is not None and t > settled + 6.0:
            return
        if peer.station is not None:
            if t >= heartbeat:
                peer.send(peer.codec.heartbeat(mavlink.MAV_TYPE_FIXED_WING))
                heartbeat = t + 1.0
            for name, when in due.items():
                if t >= when:
                    peer.send(peer.messages(name, t + 100.0))
                    due[name] = when + 1.0 / peer.rate(name) if when else t + 1.0 / peer.rate(name)
        nxt = min([*due.values(), heartbeat]) - (time.monotonic() - start)
        ready, _, _ = select.select([peer.sock], [], [], max(0.0, min(nxt, 0.05)))
        if ready:
            peer.receive()


def test_listen_asks_for_rates_and_parameters_and_uses_them(tmp_path: Path) -> None:
    sock = loopback()
    port = port_of(sock)
    out = tmp_path / "run"
    proc, _line = start_listen(
        f"udpout:127.0.0.1:{port}", "--view", "off", "--idle-exit", "2", "--out", str(out),
        "--set", f"airframe.elevator_travel_deg={TRAVEL_DEG}",
        "--set", "filter.structure_check=off",
    )  # fmt: skip
    peer = Peer(sock)
    try:
        _fly(peer)
    finally:
        sock.close()
    stdout, stderr = proc.communicate(timeout=120)
    assert "Traceback" not in stderr, stderr

    # What it asked: every message's interval, ArduPilot's stream groups once that was
    # refused, and the servo parameters, the elevator's range once its output was known.
    assert {mavlink.MSG_ID[n] for n in ("RAW_IMU", "ATTITUDE", "VFR_HUD")} <= set(peer.intervals)
    assert all(peer.streams[STREAM_OF[n]] >= 10 for n in STREAM_OF), peer.streams
    assert {"SERVO1_FUNCTION", "SERVO16_FUNCTION", "SERVO4_TRIM"} <= set(peer.param_reads)

    # What it made of it: the vehicle's parameters read the elevator; q from RAW_IMU at
    # the rate the stream request gave (above the default 4 Hz).
    res = json.loads((out / "results_sys1.json").read_text())
    sources = res["link"]["sources"]["1"]
    assert sources["servos"].startswith("vehicle parameters: elevator on output 4"), sources
    assert sources["channels"]["q"]["message"] == "RAW_IMU"
    assert sources["channels"]["q"]["rate_hz"] > 2 * DEFAULT_HZ
    assert "REQUEST_DATA_STREAM" in " ".join(sources["asked"])
    assert "servos of system id 1: vehicle parameters" in stdout
    history = pq.read_table(out / "results_sys1_history.parquet").to_pydict()
    assert history["in_elevator_rad"][-1] == pytest_approx(ELEVATOR_RAD)
    assert history["in_throttle"][-1] == pytest_approx(0.4)


def pytest_approx(x: float) -> object:
    import pytest

    return pytest.approx(x, abs=1e-6)
