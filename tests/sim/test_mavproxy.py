"""The simulated vehicle under a real ground station: MAVProxy (installed by `./run`, see
there) connects to it, shows its mode by name, has every command it sends acknowledged,
and lists its parameters."""

from __future__ import annotations

import os
import queue
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path

from pymavlink import mavutil

from sim.vehicle import STREAM_PARAMS
from tests.udp import loopback, port_of

MAVPROXY = Path(sys.executable).parent / "mavproxy.py"
FLIGHT_S = 34.0
WINDOW_S = 30.0
"""Every command MAVProxy sends in this long after the vehicle is first heard is checked."""
TIMEOUT_S = 120.0


class Console:
    """MAVProxy's console output, line by line, read as it comes."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        self.proc = proc
        self.lines: list[str] = []
        self._queue: queue.Queue[str | None] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self._queue.put(line.rstrip("\n"))
        self._queue.put(None)

    def until(self, text: str) -> str:
        """The first line (from now on) that holds text."""
        end = time.monotonic() + TIMEOUT_S
        while time.monotonic() < end:
            try:
                line = self._queue.get(timeout=1.0)
            except queue.Empty:
                continue
            if line is None:
                break
            self.lines.append(line)
            if text in line:
                return line
        raise AssertionError(f"no {text!r} from MAVProxy:\n" + "\n".join(self.lines))


def _commands_and_acks(tlog: Path) -> tuple[list[tuple[float, int]], list[tuple[float, int]]]:
    """MAVProxy's own log (both directions): the commands it sent in the window after
    the vehicle's first packet, and the vehicle's COMMAND_ACKs addressed to it."""
    log = mavutil.mavlink_connection(str(tlog), dialect="ardupilotmega")
    first = None
    sent, acked = [], []
    while (msg := log.recv_msg()) is not None:
        t, src = msg._timestamp, msg.get_srcSystem()
        if src == 1 and first is None:
            first = t
        kind = msg.get_type()
        if first is None:
            continue
        if src == 255 and kind in ("COMMAND_LONG", "COMMAND_INT") and t - first <= WINDOW_S:
            sent.append((t, int(msg.command)))
        elif src == 1 and kind == "COMMAND_ACK" and msg.target_system == 255:
            acked.append((t, int(msg.command)))
    return sent, acked


def test_mavproxy_sees_a_whole_vehicle(tmp_path: Path) -> None:
    assert MAVPROXY.exists(), f"{MAVPROXY}: MAVProxy is installed by ./run (see there)"
    port = _free_udp_port()
    mavproxy = subprocess.Popen(
        [str(MAVPROXY), f"--master=udpin:127.0.0.1:{port}", "--non-interactive"],
        cwd=tmp_path,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "MAVLINK20": "1"},
    )
    console = Console(mavproxy)
    try:
        console.until("Waiting for heartbeat")
        vehicle = subprocess.run(
            [sys.executable, "-m", "sim.cli", "--target", f"127.0.0.1:{port}", "--speed", "1",
             "--set", f"simulation.manoeuvre.duration_s={FLIGHT_S}"],
            cwd=Path(__file__).resolve().parents[2], capture_output=True, text=True,
            timeout=TIMEOUT_S,
        )  # fmt: skip
        assert vehicle.returncode == 0, vehicle.stderr
        console.until("Received")
    finally:
        if mavproxy.poll() is None:
            assert mavproxy.stdin is not None
            mavproxy.stdin.write("exit\n")
            mavproxy.stdin.flush()
            try:
                mavproxy.wait(timeout=10)
            except subprocess.TimeoutExpired:
                mavproxy.kill()
                mavproxy.wait()
    text = "\n".join(console.lines)
    assert "Mode MANUAL" in text  # a custom mode by its ArduPlane name, not Mode(0x...)
    assert f"Received {len(STREAM_PARAMS)} parameters" in text
    sent, acked = _commands_and_acks(tmp_path / "mav.tlog")
    assert sent, "MAVProxy sent no command to check"
    unanswered = Counter(c for _, c in sent) - Counter(c for _, c in acked)
    assert not unanswered, (unanswered, sent, acked)


def _free_udp_port() -> int:
    with loopback() as s:
        return port_of(s)
