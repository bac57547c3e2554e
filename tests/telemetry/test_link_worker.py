"""`listen --link-worker`: the link in a second process, end to end on loopback (real
vehicle process, real UDP, real .tlog), against the station in one process."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import threading
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import pytest

from gcs_estimator.cli import main as gcs_main
from gcs_estimator.config import load_config
from gcs_estimator.estimation.estimator import FilterKind, StepOutput
from gcs_estimator.frames import Frame
from gcs_estimator.ingest.flightdata import Recording
from gcs_estimator.ingest.sources import SourceError, UdpSource, open_udp
from gcs_estimator.ingest.telemetry.link import MavlinkLink
from gcs_estimator.outputs.view import layout as lay
from gcs_estimator.runtime import link_worker
from gcs_estimator.runtime.decode_worker import LinkArgs
from gcs_estimator.runtime.link_worker import LiveJob, WorkerUdpSource
from gcs_estimator.runtime.session import Session
from gcs_estimator.stop import Stop
from gcs_estimator.uncertainty.result import VehicleResult
from sim.cli import command as vehicle_command
from sim.truth import simulate
from sim.vehicle import SimulatedVehicle
from tests.telemetry.station import bound_port, start_listen
from tests.view.test_rerun import read_scalars

ROOT = Path(__file__).resolve().parents[2]
SHORT = ["simulation.manoeuvre.duration_s=12"]
QUICK = ["--set", "filter.structure_check=off", "--view", "off"]


def _results(folder: Path) -> dict[str, Any]:
    out: dict[str, Any] = json.loads((folder / "results_sys1.json").read_text())
    return out


def test_a_station_with_its_link_in_a_worker_gives_what_its_recording_replays_to(
    tmp_path: Path,
) -> None:
    """Vehicle process -> UDP -> `listen --link-worker`: every frame arrives, the worker
    records the tlog and answers the vehicle, and a replay of that recording ends with
    the same estimates, sigmas and history."""
    live = tmp_path / "live"
    listen = ["udpin:127.0.0.1:0", "--link-worker", "--idle-exit", "1.5", "--out", str(live)]
    station, line = start_listen(*listen, "--set", "filter.structure_check=off", "--view", "save")
    assert "the link in a second process" in line, line
    port = bound_port(line)
    vehicle = subprocess.run(
        vehicle_command(ROOT / "configs/noc_uav.toml", f"127.0.0.1:{port}", 4.0, SHORT),
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert vehicle.returncode == 0, vehicle.stderr
    assert " 0 GCS heartbeats" not in vehicle.stderr  # the worker spoke to the vehicle
    _out, err = station.communicate(timeout=120)
    assert station.returncode == 0, err
    got = _results(live)
    assert got["diagnostics"]["frames"] == 601  # 12 s at 50 Hz, every frame
    assert got["link"]["lost"] == 0 and got["link"]["received"] > 3000

    # The view has every frame on the link's receive clock too (the worker sends the
    # clock with the first frames; without it they had none, and were dropped).
    config = load_config(ROOT / "configs/noc_uav.toml")
    axis = config.structure.axes[config.coefficient_names.index("Cma")]
    entity = lay.coefficient_path(1, "Cma", axis)
    t_flight, _ = read_scalars(live / "view.rrd", entity)
    t_recv, _ = read_scalars(live / "view.rrd", entity, lay.RECEIVE_TIMELINE)
    assert len(t_recv) == len(t_flight) > 0 and np.all(np.isfinite(t_recv))
    assert t_recv[0] < 1.0  # seconds since the first packet

    again = tmp_path / "again"
    assert gcs_main(["replay", str(live / "telemetry.tlog"), "--out", str(again), *QUICK]) == 0
    want = _results(again)
    assert got["filters"] == want["filters"]
    assert got["diagnostics"] == want["diagnostics"]
    history = "results_sys1_history.parquet"
    assert pq.read_table(live / history).equals(pq.read_table(again / history))


class _KillAfter:
    """A sink that kills the link's worker process after `frames` frames."""

    def __init__(self, source: WorkerUdpSource, frames: int) -> None:
        self.source = source
        self.frames = frames
        self.seen = 0

    def on_frame(self, frame: Frame, outs: Mapping[FilterKind, StepOutput]) -> None:
        self.seen += 1
        if self.seen == self.frames:
            worker = self.source._worker
            assert worker is not None
            os.kill(worker._process.pid, signal.SIGKILL)

    def tick(self) -> None:
        pass

    def finish(self, results: Mapping[int, VehicleResult], link: Mapping[str, Any] | None) -> None:
        pass


@pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="needs SIGKILL")
def test_a_link_worker_that_dies_is_reported_and_the_frames_it_gave_are_kept() -> None:
    config = load_config(ROOT / "configs/noc_uav.toml", SHORT)
    fl = simulate(config, seed=1)
    rec = Recording(fl.t_s, fl.inputs, fl.measurements, "throttle")
    link = MavlinkLink(config.link)
    sock = open_udp("127.0.0.1", 0)
    port = sock.getsockname()[1]
    job = LiveJob(
        sock.fileno(),
        LinkArgs(link.config, link.linear_inputs, link.ranges),
        None,
        None,
        1.0,
        60.0,
        None,
    )
    source = WorkerUdpSource(sock, job, link)
    session = Session(config)
    killer = _KillAfter(source, 200)
    session.add_sink(killer)
    vehicle = SimulatedVehicle(rec, config.link, ("127.0.0.1", port), speed=4.0)
    thread = threading.Thread(target=vehicle.run)
    thread.start()
    try:
        with pytest.raises(SourceError, match="link process ended early"):
            session.run(source)
    finally:
        thread.join()
    # What arrived before the worker died was estimated, and the results say so.
    assert killer.seen >= 200
    assert session.estimators[1].frames == killer.seen
    assert session.results()[1].result.frames == killer.seen


def test_a_link_worker_is_refused_on_tcp(capsys: pytest.CaptureFixture[str]) -> None:
    assert gcs_main(["listen", "tcp:127.0.0.1:9", "--link-worker", *QUICK]) != 0
    assert "--link-worker: UDP endpoints only" in capsys.readouterr().err


def test_sigterm_stops_a_station_and_its_link_worker_cleanly(tmp_path: Path) -> None:
    record = tmp_path / "x.tlog"
    proc, _line = start_listen(
        "udpin:127.0.0.1:0", "--link-worker", "--record", str(record), "--out", str(tmp_path)
    )
    proc.terminate()
    _out, err = proc.communicate(timeout=60)
    # Stopped cleanly (the worker too: its recording is closed), and says (exit 1) that
    # nothing arrived to estimate from.
    assert proc.returncode == 1, err
    assert "no vehicle data received" in err and "no usable frame arrived" in err
    assert record.exists()


def test_a_link_worker_that_cannot_start_says_why(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A recording it cannot open (its folder is a file) ends the run before it listens,
    with the worker's reason and no traceback."""
    blocker = tmp_path / "not_a_folder"
    blocker.write_text("")
    listen = ["listen", "udpin:127.0.0.1:0", "--link-worker", "--record", str(blocker / "x.tlog")]
    assert gcs_main([*listen, "--out", str(tmp_path / "out"), *QUICK]) == 2
    err = capsys.readouterr().err
    assert "error: the link process failed" in err and "before it could receive" in err
    assert "listening on" not in err


def test_the_first_frames_go_with_the_link_clock() -> None:
    """The worker's receive loop (on a real socket and link): it reports the counters
    while idle, before any packet; when the first frames come soon after, they still go
    with the link's clock (the view times frames from it)."""
    config = load_config(ROOT / "configs/noc_uav.toml", SHORT)
    fl = simulate(config, seed=1)
    rec = Recording(fl.t_s, fl.inputs, fl.measurements, "throttle")
    sock = open_udp("127.0.0.1", 0)
    port = sock.getsockname()[1]
    source = UdpSource(sock, MavlinkLink(config.link), idle_exit_s=0.5, max_seconds=30)
    vehicle = SimulatedVehicle(rec, config.link, ("127.0.0.1", port), speed=4.0)
    thread = threading.Thread(target=vehicle.run)
    messages: list[tuple[Any, ...]] = []

    def send(msg: tuple[Any, ...]) -> None:
        if not messages:  # the idle report, before anything was sent: now fly
            assert math.isnan(msg[3].t_first_recv)
            thread.start()
        messages.append(msg)

    try:
        link_worker._receive(source, Stop(), send)
    finally:
        thread.join()
        source.close()
    frames = [list(link_worker.unpack(m[1], m[2])) for m in messages]
    first = next(k for k, f in enumerate(frames) if f)
    assert messages[first][3] is not None and math.isfinite(messages[first][3].t_first_recv)
    every = [f for batch in frames for f in batch]
    assert len(every) == 601
    # The frames' bytes give them back exactly, flags and all.
    every[5] = replace(every[5], clock_reset=True, inputs_known=False)
    again = list(link_worker.unpack(*link_worker.pack(every)))
    for a, b in zip(every, again, strict=True):
        assert (a.system_id, a.t_vehicle_s, a.t_recv_s) == (b.system_id, b.t_vehicle_s, b.t_recv_s)
        assert (a.clock_reset, a.inputs_known) == (b.clock_reset, b.inputs_known)
        np.testing.assert_array_equal(a.inputs, b.inputs)
        np.testing.assert_array_equal(a.y, b.y)
