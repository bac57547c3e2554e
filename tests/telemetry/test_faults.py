"""Faults on a real link: ground-station stalls, lost packets at the elevator steps, the
vehicle's 32-bit clock wrapping, a packet from the far future, a bad file among good ones,
corrupt receive times in a tlog, a gimbal and an air-data computer on the vehicle's
system id.

Recorded flights of the simulated vehicle (real pymavlink packets), replayed through the
same link and session as `listen` and `replay`; the stall test goes over real UDP.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from gcs_estimator.cli import main as gcs_main
from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.estimation.estimator import FilterKind, StepOutput
from gcs_estimator.frames import Frame
from gcs_estimator.ingest.flightdata import Recording
from gcs_estimator.ingest.sources import UdpSource, open_udp
from gcs_estimator.ingest.telemetry.decode import WRAP_US32_S
from gcs_estimator.ingest.telemetry.mavlink import Decoder, TlogWriter, read_tlog
from gcs_estimator.stop import Stop
from gcs_estimator.uncertainty.result import VehicleResult
from sim.truth import simulate
from sim.vehicle import SimulatedVehicle
from tests.telemetry.test_link import ROOT, SHORT, Ground, recorded_flight, run_records

NOC = ("--config", "noc_uav")
"""A simulated NOC UAV's log names its airframe file (a real log without one is refused)."""

Records = list[tuple[int, bytes]]


def _no_check(config: AircraftConfig) -> AircraftConfig:
    """Without the structure check, for a test that reads no sigma the check widens: it
    replays the final pass once per channel after every run (decision 0066)."""
    return replace(config, filter=replace(config.filter, structure_check="off"))


def _final(g: Ground) -> dict[str, np.ndarray]:
    return {k: np.array(v) for k, v in g.final().items()}


class StallingSink:
    """A sink that stalls the station (as a slow disk or a busy viewer would) at given
    frames, for given times, while the vehicle goes on sending."""

    def __init__(self, stalls: Mapping[int, float]) -> None:
        self.stalls = dict(stalls)
        self.frames = 0

    def on_frame(self, frame: Frame, outs: Mapping[FilterKind, StepOutput]) -> None:
        self.frames += 1
        pause = self.stalls.get(self.frames)
        if pause:
            time.sleep(pause)  # the fault injected, not a wait for anything

    def tick(self) -> None:
        pass

    def finish(self, results: Mapping[int, VehicleResult], link: Mapping[str, Any] | None) -> None:
        pass


def test_ground_station_stalls_leave_the_estimates_unchanged(tmp_path: Path) -> None:
    """Stalls of 0.1-2 s while the vehicle streams over UDP at 4x: the final estimates are
    exactly those of the unstalled replay of the same packets."""
    config, recs = recorded_flight(tmp_path)
    clean = run_records(config, recs)
    station = Ground(config)
    stalls = StallingSink({50: 0.1, 200: 0.5, 350: 2.0, 500: 1.0})
    station.session.add_sink(stalls)
    sock = open_udp("127.0.0.1", 0)
    port = sock.getsockname()[1]
    fl = simulate(config, seed=3)
    vehicle = SimulatedVehicle(
        Recording(fl.t_s, fl.inputs, fl.measurements, "throttle"),
        config.link,
        ("127.0.0.1", port),
        speed=4.0,
    )
    sender = threading.Thread(target=vehicle.run)
    sender.start()
    station.session.run(UdpSource(sock, station.link, idle_exit_s=1.0, max_seconds=120))
    sender.join()
    assert station.link.health.total().lost == 0
    assert station.frames() == clean.frames() == 601
    for kind, beta in _final(clean).items():
        np.testing.assert_array_equal(_final(station)[kind], beta)


def _elevator_steps(records: Records) -> list[int]:
    """Indices of the SERVO_OUTPUT_RAW packets where the elevator command steps."""
    dec = Decoder()
    out, last = [], None
    for i, (_, pkt) in enumerate(records):
        msg = dec.decode(pkt)
        if msg is not None and msg.get_type() == "SERVO_OUTPUT_RAW":
            if last is not None and abs(msg.servo2_raw - last) > 20:
                out.append(i)
            last = msg.servo2_raw
    return out


def test_a_lost_packet_at_any_elevator_step_moves_no_estimate_by_a_sigma(tmp_path: Path) -> None:
    config, recs = recorded_flight(tmp_path)
    config = _no_check(config)  # the estimates and the covariance's sigma alone
    clean = run_records(config, recs)
    snap = clean.session.estimators[1].snapshot()
    steps = _elevator_steps(recs)
    assert len(steps) >= 6
    for i in steps:
        lossy = run_records(config, recs[:i] + recs[i + 1 :])
        assert lossy.link.health.total().lost == 1
        for kind, s in snap.items():
            moved = np.abs(_final(lossy)[kind] - s.coefficients) / s.sigma
            assert moved.max() < 1.0, (i, kind, moved.round(2))


def test_the_vehicle_clock_wrapping_changes_nothing(tmp_path: Path) -> None:
    """The flight flown by a vehicle that has been up for 4,290 s: its 32-bit servo clock
    wraps 5 s in. Every frame is kept, nothing is taken for a reboot or a gap, and the
    estimates are those of the same flight flown just after boot."""
    config = load_config(ROOT / "configs/noc_uav.toml", SHORT)
    fl = simulate(config, seed=3)
    rec = Recording(fl.t_s, fl.inputs, fl.measurements, "throttle")
    runs = {}
    for boot in (5.0, WRAP_US32_S - 5.0):
        path = tmp_path / f"boot{boot:.0f}.tlog"
        SimulatedVehicle(
            rec, config.link, ("127.0.0.1", 9), speed=0.0, tlog=path, boot_s=boot
        ).run()
        runs[boot] = run_records(config, [(r.t_recv_us, r.packet) for r in read_tlog(path)])
    wrapped = runs[WRAP_US32_S - 5.0]
    stats = wrapped.link.vehicles[1].sync.stats
    assert stats.clock_wraps == 1 and stats.clock_resets == 0 and stats.time_jumps == 0
    assert wrapped.frames() == runs[5.0].frames() == 601
    for kind, beta in _final(runs[5.0]).items():
        np.testing.assert_allclose(_final(wrapped)[kind], beta, rtol=1e-6, atol=1e-9)


def test_a_vehicle_up_for_hours_is_estimated_as_one_just_booted(tmp_path: Path) -> None:
    """Up 2 hours before the flight (the station first hears it then): its 32-bit servo
    clock wrapped before the first packet; aligned to its other clocks by whole wraps, it
    gives the frames and estimates of the same flight flown at boot (to numerical noise:
    the vehicle times differ by 7,200 s)."""
    config = load_config(ROOT / "configs/noc_uav.toml", SHORT)
    fl = simulate(config, seed=3)
    rec = Recording(fl.t_s, fl.inputs, fl.measurements, "throttle")
    runs = {}
    for boot in (0.0, 7200.0):
        path = tmp_path / f"boot{boot:.0f}.tlog"
        SimulatedVehicle(
            rec, config.link, ("127.0.0.1", 9), speed=0.0, tlog=path, boot_s=boot
        ).run()
        runs[boot] = run_records(config, [(r.t_recv_us, r.packet) for r in read_tlog(path)])
    up = runs[7200.0]
    stats = up.link.vehicles[1].sync.stats
    assert stats.clock_resets == stats.time_jumps == stats.late_samples == 0
    assert stats.clock_wraps == 1  # the one before first contact
    assert up.frames() == runs[0.0].frames() == 601
    assert up.link.health.total().lost == 0
    for kind, beta in _final(runs[0.0]).items():
        np.testing.assert_allclose(_final(up)[kind], beta, rtol=1e-6, atol=1e-9)


def test_a_packet_from_the_far_future_is_dropped(tmp_path: Path) -> None:
    config, recs = recorded_flight(tmp_path)
    config = _no_check(config)  # the estimates alone
    clean = run_records(config, recs)
    from pymavlink.dialects.v20 import ardupilotmega as d

    mav = d.MAVLink(None, srcSystem=1, srcComponent=1)
    for jump_s in (1_000.0, 3_600.0, 1e5, 1e9):
        future = mav.aoa_ssa_encode(int(jump_s * 1e6), 3.0, 0.0).pack(mav)
        faulty = [*recs[:1000], (recs[1000][0], future), *recs[1000:]]
        station = run_records(config, faulty)
        assert station.link.vehicles[1].sync.stats.implausible_times == 1
        assert station.frames() == clean.frames()
        for kind, beta in _final(clean).items():
            np.testing.assert_array_equal(_final(station)[kind], beta)


def test_a_gap_in_the_data_restarts_the_flight_states_only(tmp_path: Path) -> None:
    """A second flight an hour later on the vehicle's clock (confirmed by the packets
    after the jump): no prediction over the gap; the flight states start again from the
    measurements and the coefficients are kept."""
    config, recs = recorded_flight(tmp_path)
    fl = simulate(config, seed=4)
    rec = Recording(fl.t_s, fl.inputs, fl.measurements, "throttle")
    later = tmp_path / "later.tlog"
    SimulatedVehicle(rec, config.link, ("127.0.0.1", 9), speed=0.0, tlog=later, boot_s=3605.0).run()
    station = run_records(config, recs + [(r.t_recv_us, r.packet) for r in read_tlog(later)])
    est = station.session.estimators[1]
    assert station.link.vehicles[1].sync.stats.time_jumps == 1
    assert est.gaps == 1 and station.frames() == 2 * 601
    clean = run_records(config, recs).session.estimators[1].snapshot()["IEKF"]
    snap = est.snapshot()["IEKF"]
    # Two flights' worth of information: the sigmas shrink, the estimates stay close.
    assert np.all(snap.sigma <= clean.sigma * 1.01)
    assert np.all(np.abs(snap.coefficients - clean.coefficients) < 3 * clean.sigma)


def test_a_bad_file_among_good_ones_keeps_the_results_of_the_good(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _config, recs = recorded_flight(tmp_path)
    good = tmp_path / "good.tlog"
    w = TlogWriter(good)
    for t, pkt in recs:
        w.write(t, pkt)
    w.close()
    bad = tmp_path / "bad.tlog"
    bad.write_text("not a tlog\n" * 1000)
    out = tmp_path / "out"
    assert gcs_main(["replay", str(good), str(bad), *NOC, "--out", str(out), "--view", "off"]) == 2
    assert "not a tlog" in capsys.readouterr().err
    res = json.loads((out / "results_sys1.json").read_text())
    assert res["diagnostics"]["frames"] == 601


def test_corrupt_receive_times_in_a_tlog_change_no_estimate(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """One record in fifty with its receive time 36 minutes off (a flipped byte of the
    tlog's own header; the packet intact): the replay keeps every frame and ends where the
    clean recording does, and says how many times it mended. The estimates come from the
    vehicle's own clock, so a receive time the reader mends cannot move them."""
    _config, recs = recorded_flight(tmp_path)
    clean, mended = tmp_path / "clean.tlog", tmp_path / "mended.tlog"
    for path, shift in ((clean, 0), (mended, 36 * 60 * 1_000_000)):
        w = TlogWriter(path)
        for k, (t, pkt) in enumerate(recs):
            w.write(t + (shift if k % 50 == 25 else 0), pkt)
        w.close()
    results = {}
    for path in (clean, mended):
        out = tmp_path / path.stem
        assert gcs_main(["replay", str(path), *NOC, "--out", str(out), "--view", "off"]) == 0
        results[path] = json.loads((out / "results_sys1.json").read_text())
    err = capsys.readouterr().err
    assert f"{len(recs[25::50])} record(s) with a corrupt receive time kept" in err
    a, b = results[clean], results[mended]
    assert a["diagnostics"]["frames"] == b["diagnostics"]["frames"] == 601
    for kind in ("EKF", "IEKF"):
        assert a["filters"][kind]["estimates"] == b["filters"][kind]["estimates"]


def test_a_gimbal_on_the_vehicles_system_id_changes_no_estimate(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A gimbal (component 154) on the autopilot's system id streams its own ATTITUDE,
    each just before the autopilot's, and a HEARTBEAT that says it is a gimbal; an
    air-data computer (component 158) sends the angle of attack instead of the
    autopilot. Read as the aircraft's, the gimbal's pitch once moved Cmq by 18 % with no
    word. Now each message comes from one component (the autopilot's where its
    HEARTBEAT says so): the estimates are the clean recording's to the bit, the
    gimbal's samples are counted and said, and its HEARTBEAT raises no warning about
    the aircraft's type."""
    from pymavlink.dialects.v20 import ardupilotmega as dialect

    from gcs_estimator.ingest.telemetry.mavlink import Codec

    _config, recs = recorded_flight(tmp_path)
    decoder = Decoder()
    gimbal, air_data = Codec(1, 154), Codec(1, 158)
    mixed: Records = []
    for t, pkt in recs:
        msg: Any = decoder.decode(pkt)
        kind = msg.get_type() if msg is not None else ""
        if kind == "ATTITUDE":
            att = gimbal.mav.attitude_encode(msg.time_boot_ms, 0.0, 0.3, 0.0, 0.0, 0.05, 0.0)
            mixed.append((t - 100, gimbal.pack(att)))
        elif kind == "HEARTBEAT":
            hb = gimbal.mav.heartbeat_encode(
                dialect.MAV_TYPE_GIMBAL, dialect.MAV_AUTOPILOT_INVALID, 0, 0, 0
            )
            mixed.append((t + 50, gimbal.pack(hb)))
        if kind == "AOA_SSA":
            aoa = air_data.mav.aoa_ssa_encode(msg.time_usec, msg.AOA, msg.SSA)
            mixed.append((t, air_data.pack(aoa)))
        else:
            mixed.append((t, pkt))
    results = {}
    for name, records in (("clean", recs), ("mixed", mixed)):
        w = TlogWriter(tmp_path / f"{name}.tlog")
        for t, pkt in records:
            w.write(t, pkt)
        w.close()
        out = tmp_path / name
        argv = ["replay", str(tmp_path / f"{name}.tlog"), *NOC, "--out", str(out), "--view", "off"]
        assert gcs_main(argv) == 0
        results[name] = json.loads((out / "results_sys1.json").read_text())
    err = capsys.readouterr().err
    assert "system id 1: ATTITUDE taken from component 1 (its autopilot" in err
    assert "component 154 sends ATTITUDE too" in err and "says it is" not in err
    clean, mixed_run = results["clean"], results["mixed"]
    assert mixed_run["link"]["vehicles"]["1"]["other_component"] > 500
    assert clean["link"]["vehicles"]["1"]["other_component"] == 0
    for kind in ("EKF", "IEKF"):
        assert mixed_run["filters"][kind]["estimates"] == clean["filters"][kind]["estimates"]


def test_a_paced_replay_stops_within_a_slice_when_asked(tmp_path: Path) -> None:
    """A replay at real time with an hour's gap in receive time ends as soon as a stop is
    requested, instead of sleeping through the gap."""
    from gcs_estimator.ingest.sources import TlogSource
    from gcs_estimator.ingest.telemetry.link import MavlinkLink

    config, recs = recorded_flight(tmp_path)
    path = tmp_path / "gap.tlog"
    w = TlogWriter(path)
    for k, (t, pkt) in enumerate(recs[:100]):
        w.write(t + (3_600_000_000 if k >= 50 else 0), pkt)
    w.close()
    stop = Stop()
    source = TlogSource([path], MavlinkLink(config.link), speed=1.0)

    def consume() -> None:
        for _ in source.frames(stop):
            if source.done == 50:
                stop.requested = True  # as the SIGINT handler does

    worker = threading.Thread(target=consume, daemon=True)
    worker.start()
    worker.join(timeout=60)
    assert not worker.is_alive() and source.done <= 51


def test_a_paced_replay_of_joined_recordings_does_not_wait_out_the_jump(tmp_path: Path) -> None:
    """Two recordings in one file, the second two days after the first: a replay at 20x
    real time paces each at its own times and goes from the first to the second at once
    (the reader counts the jump) instead of waiting out two days."""
    from gcs_estimator.ingest.sources import TlogSource
    from gcs_estimator.ingest.telemetry.link import MavlinkLink

    config, recs = recorded_flight(tmp_path)
    part = recs[:200]
    path = tmp_path / "joined.tlog"
    w = TlogWriter(path)
    for shift in (0, 2 * 86_400_000_000):
        for t, pkt in part:
            w.write(t + shift, pkt)
    w.close()
    source = TlogSource([path], MavlinkLink(config.link), speed=20.0)
    stop = Stop()

    def consume() -> None:
        for _ in source.frames(stop):
            pass

    worker = threading.Thread(target=consume, daemon=True)
    worker.start()
    worker.join(timeout=60)
    stop.requested = True  # ends a replay still waiting (the failure) within a slice
    assert not worker.is_alive()
    assert source.done == 2 * len(part) and source._stats.time_jumps == 1
