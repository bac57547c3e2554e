"""Serial links and a vehicle that waits for the station: `listen DEVICE,BAUD` and
`gcs-sim --target DEVICE,BAUD` through a real pty pair wired like a null-modem cable, and
`gcs-sim --target udpin:` with `listen udpout:`, as two processes each."""

from __future__ import annotations

import json
import os
import select
import subprocess
import sys
import threading
import tty
from collections.abc import Iterator
from pathlib import Path

import pytest

from gcs_estimator.cli import main
from gcs_estimator.config import ConfigError
from gcs_estimator.ingest import endpoints
from gcs_estimator.ingest.telemetry.mavlink import read_tlog
from sim.cli import _target

FLIGHT = ["--set", "simulation.manoeuvre.duration_s=12"]
TIMEOUT_S = 120.0


@pytest.mark.parametrize(
    ("text", "device", "baud"),
    [
        ("/dev/ttyUSB0,57600", "/dev/ttyUSB0", 57600),
        ("/dev/ttyACM0:115200", "/dev/ttyACM0", 115200),
        ("serial:/dev/ttyAMA0,921600", "/dev/ttyAMA0", 921600),
        ("/dev/serial/by-id/usb-radio", "/dev/serial/by-id/usb-radio", 57600),
        ("COM3,115200", "COM3", 115200),
    ],
)
def test_serial_connection_strings(text: str, device: str, baud: int) -> None:
    e = endpoints.parse(text, default_listen=True)
    assert (e.serial, e.device, e.port) == (True, device, baud)
    assert str(e) == f"{device},{baud}"


@pytest.mark.parametrize("text", ["/dev/ttyUSB0,fast", "COMX,9600", "serial:", "/dev/ttyUSB0,0"])
def test_bad_serial_strings_say_the_form(text: str) -> None:
    with pytest.raises(ConfigError, match=r"serial device|baud rate"):
        endpoints.parse(text, default_listen=True)


def test_a_missing_device_is_one_line_and_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code = main(["listen", "/dev/no-such-tty,57600", "--view", "off", "--out", str(tmp_path)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err[-1].startswith("error: endpoint /dev/no-such-tty,57600: cannot open")


class NullModem:
    """Two pty pairs whose master sides a thread joins, as a crossed serial cable: what
    one program writes to its end comes out at the other program's end."""

    def __init__(self) -> None:
        self._masters: list[int] = []
        self._slaves: list[int] = []  # held open, so the line stays up between programs
        self.ends: list[str] = []
        for _ in range(2):
            master, slave = os.openpty()
            tty.setraw(slave)
            self._masters.append(master)
            self._slaves.append(slave)
            self.ends.append(os.ttyname(slave))
        self._stop = threading.Event()
        self.carried = 0
        self._thread = threading.Thread(target=self._carry, daemon=True)
        self._thread.start()

    def _carry(self) -> None:
        a, b = self._masters
        while not self._stop.is_set():
            ready, _, _ = select.select([a, b], [], [], 0.1)
            for fd in ready:
                try:
                    data = os.read(fd, 65536)
                except OSError:
                    continue
                other = b if fd == a else a
                view = memoryview(data)
                while view:
                    n = os.write(other, view)
                    view = view[n:]
                self.carried += len(data)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        for fd in (*self._masters, *self._slaves):
            os.close(fd)


@pytest.fixture
def cable() -> Iterator[NullModem]:
    modem = NullModem()
    yield modem
    modem.close()


def _gcs(*args: str, cwd: Path) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "gcs_estimator", *args],
        cwd=cwd,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )


def _sim(*args: str, cwd: Path) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "sim.cli", *args, *FLIGHT],
        cwd=cwd,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )


def _line(proc: subprocess.Popen[str], start: str) -> str:
    """The first line of proc's stderr that starts with start (what it printed so far
    if it ends without one)."""
    assert proc.stderr is not None
    seen = []
    for line in proc.stderr:
        if line.startswith(start):
            return line
        seen.append(line)
    raise AssertionError("".join(seen))


def _results(folder: Path) -> dict[str, object]:
    return dict(json.loads((folder / "results_sys1.json").read_text()))


def test_station_and_vehicle_over_a_serial_cable(tmp_path: Path, cable: NullModem) -> None:
    """The station reads the flight from its serial port and speaks back on it: every
    packet the vehicle sent arrives, none is lost, and the vehicle hears the station."""
    vehicle_tlog = tmp_path / "vehicle"
    station = _gcs(
        "listen", f"{cable.ends[0]},115200", "--view", "off", "--idle-exit", "2",
        "--out", str(tmp_path / "run"), *FLIGHT, cwd=tmp_path,
    )  # fmt: skip
    assert _line(station, "reading serial").startswith(f"reading serial {cable.ends[0]}")
    vehicle = _sim(
        "--target", f"{cable.ends[1]},115200", "--speed", "6", "--tlog", str(vehicle_tlog),
        cwd=tmp_path,
    )  # fmt: skip
    _, vehicle_err = vehicle.communicate(timeout=TIMEOUT_S)
    _, station_err = station.communicate(timeout=TIMEOUT_S)
    assert vehicle.returncode == 0 and station.returncode == 0, (vehicle_err, station_err)
    sent = len(list(read_tlog(Path(f"{vehicle_tlog}_1.tlog"))))
    res = _results(tmp_path / "run")
    link = res["link"]
    assert isinstance(link, dict)
    assert link["received"] == sent and link["lost"] == 0 and link["corrupt"] == 0, link
    heard = int(vehicle_err.split("packets, ")[1].split()[0])
    assert heard > 0, vehicle_err  # the station's heartbeats came back over the cable
    filters = res["filters"]
    assert isinstance(filters, dict) and len(filters["IEKF"]["estimates"]) == 11


def test_a_vehicle_that_waits_for_the_station_to_speak(tmp_path: Path) -> None:
    """gcs-sim on udpin: prints its port and waits; listen udpout: speaks first, and the
    flight comes back to the station's own port."""
    vehicle = _sim("--target", "udpin:127.0.0.1:0", "--speed", "6", cwd=tmp_path)
    port = _line(vehicle, "gcs-sim: waiting").split("udp ")[1].split()[0].rsplit(":", 1)[1]
    station = _gcs(
        "listen", f"udpout:127.0.0.1:{port}", "--view", "off", "--idle-exit", "2",
        "--out", str(tmp_path / "run"), *FLIGHT, cwd=tmp_path,
    )  # fmt: skip
    _, vehicle_err = vehicle.communicate(timeout=TIMEOUT_S)
    _, station_err = station.communicate(timeout=TIMEOUT_S)
    assert vehicle.returncode == 0 and station.returncode == 0, (vehicle_err, station_err)
    assert "ground station at" in vehicle_err
    link = _results(tmp_path / "run")["link"]
    assert isinstance(link, dict)
    sent = int(vehicle_err.split("sent ")[1].split()[0])
    assert link["received"] == sent and link["lost"] == 0, (link, vehicle_err)


def test_the_simulated_vehicle_takes_udpin_and_serial() -> None:
    assert isinstance(_target("udpin:127.0.0.1:0"), endpoints.Endpoint)
    serial = _target("/dev/ttyUSB0,57600")
    assert isinstance(serial, endpoints.Endpoint) and serial.device == "/dev/ttyUSB0"
    assert _target("udp:127.0.0.1:14550") == ("127.0.0.1", 14550)  # as MAVProxy's --out=udp:
