"""The link end to end on loopback: real vehicle process, real UDP, real .tlog files."""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from gcs_estimator.cli import main as gcs_main
from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.frames import Frame
from gcs_estimator.ingest.flightdata import Recording, load_hfb320
from gcs_estimator.ingest.sources import UdpSource, open_udp
from gcs_estimator.ingest.telemetry.link import MavlinkLink
from gcs_estimator.ingest.telemetry.mavlink import TlogWriter, read_tlog
from gcs_estimator.runtime.decode_worker import tlog_source
from gcs_estimator.runtime.session import Session, run_recording, warm_up
from gcs_estimator.stop import Stop
from sim.cli import command as vehicle_command
from sim.vehicle import SimulatedVehicle
from tests.telemetry.station import start_listen

NOC = ("--config", "noc_uav")
"""A simulated NOC UAV's log names its airframe file (a real log without one is refused)."""

ROOT = Path(__file__).resolve().parents[2]
SHORT = ["simulation.manoeuvre.duration_s=12"]


class Ground:
    """A ground station as the commands build it: a session over a MAVLink link."""

    def __init__(self, config: AircraftConfig, record: Path | None = None) -> None:
        # As the commands do before they listen: kernels compiled (or loaded) now, so a
        # vehicle is never left unanswered while the station compiles them.
        warm_up(config)
        self.session = Session(config)
        self.link = MavlinkLink(config.link, recorder=TlogWriter(record) if record else None)

    def frames(self, sysid: int = 1) -> int:
        return self.session.estimators[sysid].frames

    def final(self, sysid: int = 1) -> dict[str, np.ndarray]:
        return {k: s.coefficients for k, s in self.session.estimators[sysid].snapshot().items()}


def fly_to_station(
    config: AircraftConfig, recs: list[Recording], speed: float, record: Path | None
) -> Ground:
    """Vehicles in threads of this process (real sockets) -> a listening station."""
    import threading

    ground = Ground(config, record)
    sock = open_udp("127.0.0.1", 0)
    port = sock.getsockname()[1]
    vehicles = [
        SimulatedVehicle(r, config.link, ("127.0.0.1", port), system_id=i + 1, speed=speed)
        for i, r in enumerate(recs)
    ]
    threads = [threading.Thread(target=v.run) for v in vehicles]
    for t in threads:
        t.start()
    ground.session.run(UdpSource(sock, ground.link, idle_exit_s=1.0, max_seconds=120))
    for t in threads:
        t.join()
    return ground


def replay(config: AircraftConfig, path: Path) -> Ground:
    ground = Ground(config)
    ground.session.run(tlog_source([path], ground.link))
    return ground


def test_vehicle_process_to_ground_station_and_replay_matches(tmp_path: Path) -> None:
    """Separate vehicle process -> UDP -> station; the recorded tlog replays to the same
    final estimates; the vehicle answered the station's heartbeat and rate requests."""
    config = load_config(ROOT / "configs/noc_uav.toml", SHORT)
    station = Ground(config, record=tmp_path / "live.tlog")
    sock = open_udp("127.0.0.1", 0)
    port = sock.getsockname()[1]
    proc = subprocess.Popen(
        vehicle_command(ROOT / "configs/noc_uav.toml", f"127.0.0.1:{port}", 4.0, SHORT),
        cwd=ROOT,
        stderr=subprocess.PIPE,
        text=True,
    )
    station.session.run(UdpSource(sock, station.link, idle_exit_s=1.5, max_seconds=120))
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0
    assert "GCS heartbeats" in err and " 0 GCS heartbeats" not in err
    assert " 0 rate changes" not in err
    assert station.frames() == 601  # 12 s at 50 Hz, every frame
    assert station.link.health.total().lost == 0 and station.link.health.total().corrupt == 0
    # COMMAND_ACK MAV_RESULT_ACCEPTED for SET_MESSAGE_INTERVAL
    assert 0 in station.link.vehicles[1].acked
    live = station.final()

    again = replay(config, tmp_path / "live.tlog")
    for kind, beta in again.final().items():
        np.testing.assert_array_equal(beta, live[kind])
    # Live, some of the restarts' work may go into idle time (how much depends on the
    # machine's load: none at all on a busy one); the replay has none. The re-runs take
    # over at frames the data fix, whatever was done ahead, so every frame's estimate is
    # the same (work_ahead itself: tests/filters/test_restarts.py).
    live_est, again_est = station.session.estimator(1), again.session.estimator(1)
    assert again_est.restarts.worked_ahead == 0
    assert live_est.final_pass_from == again_est.final_pass_from
    live_result, again_result = live_est.result(), again_est.result()
    for kind, f in live_result.filters.items():
        assert f.track is not None
        other = again_result.filters[kind].track
        assert other is not None
        np.testing.assert_array_equal(f.track.x, other.x)


def test_link_reaches_the_offline_estimate(tmp_path: Path, noc_config: AircraftConfig) -> None:
    """The link quantises the elevator to 1 us of PWM (0.06 deg, 1/50 of the multistep)
    and sends float32 fields: the estimates move by a fraction of their sigma, no more."""
    from sim.truth import simulate

    config = load_config(ROOT / "configs/noc_uav.toml", SHORT)
    fl = simulate(config, seed=9)
    rec = Recording(fl.t_s, fl.inputs, fl.measurements, "throttle")
    station = fly_to_station(config, [rec], speed=0.0, record=None)
    offline = run_recording(config, fl.t_s, fl.inputs, fl.measurements).result
    for kind, f in offline.filters.items():
        assert np.all(np.abs(station.final()[kind] - f.coefficients) < 0.5 * f.sigma), kind


def test_hfb320_playback_through_the_link(tmp_path: Path, hfb_data_path: Path) -> None:
    # The estimates and the covariance's sigma alone: no structure check (decision 0066).
    config = load_config(ROOT / "configs/hfb320.toml", ["filter.structure_check=off"])
    rec = load_hfb320(hfb_data_path)
    station = fly_to_station(config, [rec], speed=0.0, record=None)
    assert station.frames() == len(rec)
    offline = run_recording(config, rec.t_s, rec.inputs, rec.measurements).result
    for kind, f in offline.filters.items():
        # float32 fields and 1 us elevator PWM: differences a fraction of the sigmas.
        assert np.all(np.abs(station.final()[kind] - f.coefficients) < 0.5 * f.sigma), kind


def test_two_vehicles_on_one_port(tmp_path: Path) -> None:
    from sim.truth import simulate

    config = load_config(ROOT / "configs/noc_uav.toml", SHORT)
    other = config.with_truth(tuple(np.array(config.truth or ()) * 1.2))
    recs = []
    for c, seed in ((config, 1), (other, 2)):
        fl = simulate(c, seed=seed)
        recs.append(Recording(fl.t_s, fl.inputs, fl.measurements, "throttle"))
    station = fly_to_station(config, recs, speed=0.0, record=None)
    assert sorted(station.session.estimators) == [1, 2]
    assert station.frames(1) == station.frames(2) == 601
    cla = config.coefficient_names.index("Cma")
    a, b = station.final(1)["IEKF"][cla], station.final(2)["IEKF"][cla]
    assert b / a == pytest.approx(1.2, rel=0.03)  # each vehicle its own estimate


# ------------------------------------------------------------------ bad input


def recorded_flight(
    tmp_path: Path, seed: int = 3
) -> tuple[AircraftConfig, list[tuple[int, bytes]]]:
    config = load_config(ROOT / "configs/noc_uav.toml", SHORT)
    from sim.truth import simulate

    tmp_path.mkdir(parents=True, exist_ok=True)
    fl = simulate(config, seed=seed)
    rec = Recording(fl.t_s, fl.inputs, fl.measurements, "throttle")
    v = SimulatedVehicle(rec, config.link, ("127.0.0.1", 9), speed=0.0, tlog=tmp_path / "v.tlog")
    v.run()
    return config, [(r.t_recv_us, r.packet) for r in read_tlog(tmp_path / "v.tlog")]


class Packets:
    """A source of packets as single datagrams (session.Source), received 2 ms apart:
    deterministic and well inside max_wait."""

    def __init__(self, link: MavlinkLink, records: list[tuple[int, bytes]]) -> None:
        self.link = link
        self.records = records

    def frames(self, stop: Stop) -> Iterator[Frame | None]:
        t0 = self.records[0][0]
        for i, (_, pkt) in enumerate(self.records):
            yield from self.link.packet(pkt, (t0 + 2000 * i) * 1e-6)
        yield from self.link.flush()

    def link_stats(self) -> dict[str, Any]:
        return self.link.stats()

    def close(self) -> None:
        self.link.close()


def run_records(config: AircraftConfig, records: list[tuple[int, bytes]]) -> Ground:
    ground = Ground(config)
    ground.session.run(Packets(ground.link, records))
    return ground


def test_bad_packets_are_counted_and_skipped(tmp_path: Path) -> None:
    config, recs = recorded_flight(tmp_path)
    clean = run_records(config, recs)
    n_frames = clean.frames()

    bad: list[tuple[int, bytes]] = []
    for i, (t, pkt) in enumerate(recs):
        if i == 100:
            corrupt = bytearray(pkt)
            corrupt[-1] ^= 0xFF  # CRC fails
            bad.append((t, bytes(corrupt)))
            continue
        if i == 200:
            bad.append((t, pkt[:-3]))  # truncated packet
            continue
        bad.append((t, pkt))
        if i == 300:
            bad.append((t, pkt))  # duplicated
    station = run_records(config, bad)
    h = station.link.health.total()
    assert h.corrupt == 2 and h.duplicates == 1 and h.lost == 2
    assert station.frames() == n_frames  # partial frames, nothing stalls
    assert np.all(np.isfinite(station.final()["IEKF"]))


def test_nan_absurd_values_reorder_clock_reset_unknown_and_second_vehicle(
    tmp_path: Path,
) -> None:
    from pymavlink.dialects.v20 import ardupilotmega as d

    config, recs = recorded_flight(tmp_path)
    mav = d.MAVLink(None, srcSystem=1, srcComponent=1)
    mav.seq = 0
    nan_pkt = mav.vfr_hud_encode(math.nan, 0, 0, 0, 0, 0).pack(mav)
    absurd = mav.aoa_ssa_encode(1, 500.0, 0).pack(mav)  # 500 deg angle of attack
    other = d.MAVLink(None, srcSystem=7, srcComponent=1)
    hb7 = other.heartbeat_encode(1, 3, 0, 0, 4).pack(other)
    unknown = bytearray(mav.aoa_ssa_encode(1, 2.0, 0).pack(mav))
    unknown[7:10] = (60000).to_bytes(3, "little")  # a message id no dialect has

    seq = list(recs)
    seq.insert(50, (seq[50][0], nan_pkt))
    seq.insert(60, (seq[60][0], absurd))
    seq.insert(70, (seq[70][0], hb7))
    seq.insert(80, (seq[80][0], bytes(unknown)))
    seq[400], seq[401] = seq[401], seq[400]  # reordered
    # The vehicle reboots and flies again, its clock and sequence numbers from the start.
    _, again = recorded_flight(tmp_path / "again", seed=4)
    seq += again[: len(again) // 2]
    station = run_records(config, seq)
    link = station.link
    assert link.decode_stats.invalid_values == 2
    assert 7 in link.vehicles  # second vehicle known, estimated separately
    assert link.vehicles[1].sync.stats.clock_resets == 1
    assert link.health.total().out_of_order >= 1
    assert link.health.total().unknown == 1  # decoded as UNKNOWN_60000, skipped
    beta = station.final()["IEKF"]
    assert np.all(np.isfinite(beta))
    # The estimates known before the reboot are kept (not reset to zero).
    assert abs(beta[config.coefficient_names.index("Cma")]) > 1.0


def test_truncated_and_garbage_tlogs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _config, recs = recorded_flight(tmp_path)
    path = tmp_path / "flight.tlog"
    w = TlogWriter(path)
    # Times whose third byte is 0xFD, a MAVLink 2 start marker: resynchronising over the
    # garbage must not take the next record's timestamp for a packet.
    t0 = 0x0005_FD00_0000_0000  # July 2023 in microseconds
    for i, (_, pkt) in enumerate(recs):
        w.write(t0 + 2000 * i, pkt)
        if i in (500, 1500):
            w._fh.write(b"\x00garbage\x11" * 5)  # junk between records
    w.close()
    data = path.read_bytes()
    (tmp_path / "cut.tlog").write_bytes(data[: len(data) - 7])
    out = tmp_path / "res"
    assert gcs_main(["replay", str(tmp_path / "cut.tlog"), *NOC, "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "garbage bytes skipped" in err and "truncated at the end" in err
    res = json.loads((out / "results_sys1.json").read_text())
    assert res["link"]["received"] == len(recs) - 1  # all but the cut last record

    (tmp_path / "notes.txt").write_text("this is not a tlog\n" * 500)
    # A run's folder is never written over: the same --out is refused, --force allows it.
    assert gcs_main(["replay", str(tmp_path / "notes.txt"), "--out", str(out)]) == 2
    assert "holds a run's outputs already" in capsys.readouterr().err
    assert (
        gcs_main(["replay", str(tmp_path / "notes.txt"), *NOC, "--out", str(out), "--force"]) == 2
    )
    assert "not a tlog" in capsys.readouterr().err

    # An empty file is skipped as one that is not a tlog is.
    (tmp_path / "empty.tlog").write_bytes(b"")
    assert (
        gcs_main(["replay", str(tmp_path / "empty.tlog"), *NOC, "--out", str(tmp_path / "e")]) == 2
    )
    err = capsys.readouterr().err
    assert f"error: {tmp_path / 'empty.tlog'}: an empty file (no MAVLink record); skipped" in err


def test_sigterm_stops_cleanly_with_results(tmp_path: Path) -> None:
    proc, _line = start_listen(
        "udpin:127.0.0.1:0", "--out", str(tmp_path), "--record", str(tmp_path / "x.tlog")
    )
    proc.terminate()
    _out, err = proc.communicate(timeout=60)
    # Stopped cleanly, and says (exit 1) that nothing arrived to estimate from.
    assert proc.returncode == 1, err
    assert "no vehicle data received" in err and "no usable frame arrived" in err
    assert (tmp_path / "x.tlog").exists()


def _catches_sigterm(pid: int) -> bool:
    """Whether the process has installed a SIGTERM handler (Linux: SigCgt in /proc)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("SigCgt:"):
            return bool(int(line.split()[1], 16) >> (signal.SIGTERM - 1) & 1)
    return False


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="needs Linux /proc")
def test_a_signal_during_start_up_ends_the_run_cleanly(tmp_path: Path) -> None:
    """The handlers come before the estimator is imported and its kernels loaded: a
    SIGTERM as soon as they are in place (long before the station listens) still ends
    the run cleanly, with the exit status and reason of a run that got no data."""
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "gcs_estimator",
            "listen",
            "udpin:127.0.0.1:0",
            "--out",
            str(tmp_path),
        ],
        cwd=ROOT,
        stderr=subprocess.PIPE,
        text=True,
    )
    while proc.poll() is None and not _catches_sigterm(proc.pid):
        pass
    proc.terminate()
    _out, err = proc.communicate(timeout=60)
    assert proc.returncode == 1, err  # ended cleanly: nothing to estimate, and it says so
    assert "no usable frame arrived" in err and "Traceback" not in err


def test_a_datagram_of_one_packet_is_read_as_the_scan_reads_it(tmp_path: Path) -> None:
    """A datagram that is exactly one channel message is read directly (link.datagram's
    short way); the same packets in datagrams of three, where the scan finds them, give
    the same frames and the same counts. A corrupt one-packet datagram still goes to the
    scan and is counted."""
    config, recs = recorded_flight(tmp_path)
    recs = recs[:900]
    corrupt = bytearray(recs[400][1])
    corrupt[-1] ^= 0xFF
    recs[400] = (recs[400][0], bytes(corrupt))
    single = Ground(config)
    batched = Ground(config)
    got_single: list[Frame] = []
    got_batched: list[Frame] = []
    for t_us, pkt in recs:
        got_single += single.link.datagram(pkt, t_us * 1e-6, ("127.0.0.1", 5760))
    for i in range(0, len(recs), 3):
        group = recs[i : i + 3]
        data = b"".join(p for _, p in group)
        got_batched += batched.link.datagram(data, group[-1][0] * 1e-6, ("127.0.0.1", 5760))
    assert len(got_single) == len(got_batched) > 100
    for a, b in zip(got_single, got_batched, strict=True):
        assert (a.system_id, a.t_vehicle_s) == (b.system_id, b.t_vehicle_s)
        np.testing.assert_array_equal(a.y, b.y)
        np.testing.assert_array_equal(a.inputs, b.inputs)
    one, three = single.link.health.total(), batched.link.health.total()
    assert one.corrupt == three.corrupt == 1
    assert (one.received, one.lost, one.duplicates) == (
        three.received,
        three.lost,
        three.duplicates,
    )
