"""Replay on two cores: the worker process makes exactly the frames, counters and notes
a replay in one process makes; a stop, a bad file and a dead worker end the replay with
what was processed and a clear message."""

from __future__ import annotations

import io
import math
import os
import signal
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.frames import Frame
from gcs_estimator.ingest.flightdata import Recording
from gcs_estimator.ingest.sources import SourceError, TlogSource
from gcs_estimator.ingest.telemetry.link import MavlinkLink
from gcs_estimator.ingest.telemetry.mavlink import TlogWriter
from gcs_estimator.runtime import decode_worker
from gcs_estimator.runtime.decode_worker import WorkerTlogSource
from gcs_estimator.runtime.session import Session, warm_up
from gcs_estimator.stop import Stop
from sim.truth import simulate
from sim.vehicle import SimulatedVehicle
from tests.telemetry.test_link import recorded_flight


def _damaged_tlog(tmp_path: Path) -> tuple[AircraftConfig, Path]:
    """A recorded flight with garbage between records, a duplicated and a lost packet,
    a corrupted one, and a truncated tail."""
    config, recs = recorded_flight(tmp_path)
    path = tmp_path / "damaged.tlog"
    w = TlogWriter(path)
    for i, (t, pkt) in enumerate(recs):
        if i == 300:
            continue  # lost
        if i == 400:
            pkt = pkt[:-1] + bytes([pkt[-1] ^ 0xFF])  # CRC fails
        w.write(t, pkt)
        if i == 500:
            w.write(t, pkt)  # a copy
        if i == 1000:
            w._fh.write(b"\xfd\x00\xfe" * 40)  # garbage full of start markers
    w._fh.write(b"\x00\x05\xfd\x00")  # a record cut short
    w.close()
    return config, path


def _replay(
    config: AircraftConfig, paths: list[Path], workers: bool
) -> tuple[list[Frame], dict[str, Any], str, TlogSource | WorkerTlogSource]:
    log = io.StringIO()
    link = MavlinkLink(config.link, log=log)
    source = (WorkerTlogSource if workers else TlogSource)(paths, link, log=log)
    frames = [f for f in source.frames(Stop()) if f is not None]
    stats = source.link_stats()
    source.close()
    return frames, stats, log.getvalue(), source


def _rows(frames: list[Frame]) -> np.ndarray:
    return np.array(
        [
            [f.system_id, f.t_vehicle_s, f.t_recv_s, *f.inputs, *f.y, f.clock_reset, f.inputs_known]
            for f in frames
        ]
    )


def test_worker_makes_the_same_frames_counters_and_notes(tmp_path: Path) -> None:
    config, path = _damaged_tlog(tmp_path)
    one, stats_one, notes_one, _ = _replay(config, [path], workers=False)
    two, stats_two, notes_two, _ = _replay(config, [path], workers=True)
    assert len(one) > 500
    np.testing.assert_array_equal(_rows(one), _rows(two))  # NaN where NaN, bit for bit
    assert stats_one == stats_two
    counts = stats_two
    assert counts["corrupt"] == 1 and counts["duplicates"] == 1 and counts["lost"] >= 1
    assert notes_one == notes_two
    assert "garbage bytes skipped" in notes_two and "truncated at the end" in notes_two


def test_worker_estimates_equal_one_process_estimates(tmp_path: Path) -> None:
    config, path = _damaged_tlog(tmp_path)
    warm_up(config)
    finals = []
    for workers in (False, True):
        link = MavlinkLink(config.link, log=io.StringIO())
        session = Session(config)
        source = WorkerTlogSource if workers else TlogSource
        results = session.run(source([path], link, log=io.StringIO()))
        est = results[1].result
        finals.append({k: np.r_[f.coefficients, f.sigma] for k, f in est.filters.items()})
    for kind in finals[0]:
        np.testing.assert_array_equal(finals[0][kind], finals[1][kind])


def test_a_bad_file_is_reported_and_the_good_ones_replayed(tmp_path: Path) -> None:
    config, path = _damaged_tlog(tmp_path)
    bad = tmp_path / "not_a.tlog"
    bad.write_bytes(b"hello, this is not a tlog\n" * 400)
    frames, _, notes, source = _replay(config, [path, bad, path], workers=True)
    one, _, _, _ = _replay(config, [path], workers=True)
    assert len(source.errors) == 1 and "not_a.tlog" in source.errors[0]
    assert notes.count("error:") == 1 and "skipped" in notes  # said once
    assert len(frames) > len(one)  # both good files' frames arrived


def _longer_than_the_queue(tmp_path: Path) -> tuple[AircraftConfig, Path]:
    """A recorded flight with more frames than the parent's queue, the pipe and the
    worker's batch in hand together hold: the worker cannot finish before the parent
    reads, so a stop after the first frames always ends it early."""
    frames = (decode_worker.QUEUE_BATCHES + 8) * decode_worker.BATCH_FRAMES
    duration_s = math.ceil(frames / 50.0)  # frames at 50 Hz
    config = load_config("noc_uav", [f"simulation.manoeuvre.duration_s={duration_s}"])
    fl = simulate(config, seed=3)
    rec = Recording(fl.t_s, fl.inputs, fl.measurements, "throttle")
    path = tmp_path / "long.tlog"
    SimulatedVehicle(rec, config.link, ("127.0.0.1", 9), speed=0.0, tlog=path).run()
    return config, path


def test_a_stop_ends_the_worker_and_keeps_what_arrived(tmp_path: Path) -> None:
    config, path = _longer_than_the_queue(tmp_path)
    full, _, _, _ = _replay(config, [path], workers=False)
    stop = Stop()
    source = WorkerTlogSource([path], MavlinkLink(config.link, log=io.StringIO()))
    got = []
    for f in source.frames(stop):
        if f is not None:
            got.append(f)
            if len(got) == 20:
                stop.requested = True
    stats = source.link_stats()
    source.close()
    assert 20 <= len(got) < len(full)
    # Up to the frames still open at the stop (they go as they are, partial), the
    # frames are the ones of the whole replay.
    settled = [f for f in got if f.t_vehicle_s < got[-1].t_vehicle_s - 0.5]
    assert len(settled) >= 10
    np.testing.assert_array_equal(_rows(settled), _rows(full[: len(settled)]))
    assert stats["received"] > 0
    worker = source._worker
    assert worker is not None and worker._process.poll() is not None  # reaped


def test_a_killed_worker_is_an_error_that_names_it(tmp_path: Path) -> None:
    config, path = _damaged_tlog(tmp_path)
    source = WorkerTlogSource([path], MavlinkLink(config.link, log=io.StringIO()))
    got = 0
    with pytest.raises(SourceError, match="decoding process ended early"):
        for f in source.frames(Stop()):
            if got == 0 and source._worker is not None:
                os.kill(source._worker._process.pid, signal.SIGKILL)
            got += f is not None
    source.close()
