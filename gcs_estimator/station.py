"""The ground station: one pipeline for live UDP and .tlog replay.

packets -> decode (SI samples, both clocks) -> per-vehicle synchroniser (frames) ->
per-vehicle estimator (EKF and IEKF). Every packet received live is recorded to a .tlog
with its receive time; a replay of that file makes the same frames and estimates.
"""

from __future__ import annotations

import math
import select
import signal
import socket
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import Any, TextIO

import numpy as np

from gcs_estimator.config import STREAMED_MESSAGES, AircraftConfig
from gcs_estimator.estimator import Estimator
from gcs_estimator.telemetry import mavlink
from gcs_estimator.telemetry.decode import DecodeStats, decode_message
from gcs_estimator.telemetry.sync import Frame, LinkHealth, Synchronizer
from gcs_estimator.view.live import RerunView
from gcs_estimator.view.outlets import Outlet

RCVBUF_BYTES = 8 * 1024 * 1024
"""Listener socket buffer: the ~212 KB default drops packets at high rates."""


@dataclass
class Vehicle:
    """One aircraft on the link: its synchroniser, estimator and peer address."""

    system_id: int
    sync: Synchronizer
    estimator: Estimator
    address: tuple[str, int] | None = None
    acked: set[int] = field(default_factory=set)
    last_rate_request: float = -math.inf
    frames: int = 0


FrameHook = Callable[[Vehicle, Frame], None]


class Station:
    """Owns the loop state: decoder, link health, vehicles. Pure of sockets and files
    except for the optional tlog recorder; `listen` and `replay` feed it packets."""

    def __init__(
        self,
        config: AircraftConfig,
        backend: str = "fast",
        record: Path | None = None,
        on_frame: FrameHook | None = None,
        log: TextIO = sys.stderr,
    ) -> None:
        self.config = config
        self.backend = backend
        self.decoder = mavlink.Decoder()
        self.health = LinkHealth()
        self.decode_stats = DecodeStats()
        self.vehicles: dict[int, Vehicle] = {}
        self.recorder = mavlink.TlogWriter(record) if record else None
        self.on_frame = on_frame
        self.view: RerunView | None = None
        """The live view, when one is open; gets every frame's outputs."""
        self.t0_recv = math.nan
        """Receive time of the session's first packet: zero of the view's time line."""
        self.t_last_recv = math.nan
        self.log = log
        self._reported: set[str] = set()
        self.unknown_messages = 0
        self._warm_up()

    def _warm_up(self) -> None:
        """Compile (or load) the filter kernels now, not while packets queue up."""
        if self.backend != "fast":
            return
        from gcs_estimator.model.aircraft import trim

        est = Estimator(self.config, keep_history=False)
        t = trim(est.model, np.zeros(est.model.n_coefficients) + 0.1)
        y = np.concatenate([t.state, np.zeros(3)])
        est.step(0.0, t.inputs, y)
        est.step(0.02, t.inputs, y)

    # -------------------------------------------------------------- reporting
    def report_once(self, key: str, text: str) -> None:
        """Say a problem once (it is counted every time)."""
        if key not in self._reported:
            self._reported.add(key)
            print(f"note: {text}", file=self.log)

    # -------------------------------------------------------------- pipeline
    def vehicle(self, system_id: int) -> Vehicle:
        v = self.vehicles.get(system_id)
        if v is None:
            if self.vehicles:
                self.report_once(
                    f"vehicle-{system_id}",
                    f"another vehicle on the link: system id {system_id} (estimated separately)",
                )
            v = Vehicle(
                system_id,
                Synchronizer(system_id, self.config.link),
                Estimator(self.config, backend=self.backend),  # type: ignore[arg-type]
            )
            self.vehicles[system_id] = v
        return v

    def handle_packet(
        self, packet: bytes, t_recv_s: float, address: tuple[str, int] | None = None
    ) -> None:
        """Record, decode and process one packet received at t_recv_s [s since epoch]."""
        if self.recorder is not None:
            self.recorder.write(int(round(t_recv_s * 1e6)), packet)
        if math.isnan(self.t0_recv):
            self.t0_recv = t_recv_s
        self.t_last_recv = t_recv_s
        self.poll(t_recv_s)
        msg = self.decoder.decode(packet)
        if msg is None:
            self.health.corrupt += 1
            self.report_once("corrupt", "corrupt packet(s) (CRC or framing): counted, skipped")
            return
        sysid = int(msg.get_srcSystem())
        if not self.health.on_packet(sysid, int(msg.get_srcComponent()), int(msg.get_seq())):
            self.report_once("dup", "duplicated packet(s): counted, dropped")
            return
        kind = msg.get_type()
        if kind.startswith("UNKNOWN"):
            self.unknown_messages += 1
            self.report_once("unknown", f"message unknown to the dialect ({kind}): skipped")
            return
        if kind == "HEARTBEAT":
            if msg.type == mavlink.MAV_TYPE_GCS:
                return
            v = self.vehicle(sysid)
            if address is not None:
                v.address = address
            return
        if kind == "COMMAND_ACK":
            if msg.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL and sysid in self.vehicles:
                self.vehicles[sysid].acked.add(int(msg.result))
            return
        if sysid == mavlink.GCS_SYSTEM_ID:
            return
        sample = decode_message(msg, t_recv_s, self.config.link, self.decode_stats)
        if self.decode_stats.invalid_values:
            self.report_once("invalid", "NaN or absurd field value(s): counted, dropped")
        if sample is None:
            return
        v = self.vehicle(sysid)
        if address is not None:
            v.address = address
        for frame in v.sync.add(sample):
            self._process(v, frame)

    def poll(self, t_recv_s: float) -> None:
        """Process partial frames that have waited long enough (receive time)."""
        for v in self.vehicles.values():
            for frame in v.sync.poll(t_recv_s):
                self._process(v, frame)

    def _process(self, v: Vehicle, frame: Frame) -> None:
        if frame.clock_reset:
            self.report_once(
                f"reset-{v.system_id}",
                f"vehicle {v.system_id}: clock went back (reboot?): estimates kept, "
                "states re-initialised",
            )
            v.estimator.rebase(frame.t_vehicle_s, frame.y)
        outs = v.estimator.step(frame.t_vehicle_s, frame.inputs, frame.y)
        v.frames += 1
        if self.view is not None:
            self.view.step(
                v.system_id,
                frame.t_recv_s - self.t0_recv,
                frame.t_vehicle_s,
                frame.inputs,
                frame.y,
                outs,
            )
        if v.sync.stats.late_samples:
            self.report_once("late", "sample(s) older than the last frame: counted, dropped")
        if self.on_frame is not None:
            self.on_frame(v, frame)

    def finish(self) -> None:
        """End of stream: process what is open and close the recording."""
        for v in self.vehicles.values():
            for frame in v.sync.flush():
                self._process(v, frame)
        if self.recorder is not None:
            self.recorder.close()

    # -------------------------------------------------------------- status
    def status_line(self, elapsed_s: float) -> str:
        h = self.health
        parts = [
            f"{elapsed_s:6.1f} s",
            f"pkts {h.received}",
            f"lost {h.lost}",
            f"dup {h.duplicates}",
            f"ooo {h.out_of_order}",
            f"bad {h.corrupt}",
        ]
        for v in self.vehicles.values():
            cur = v.estimator.current().get("IEKF")
            est = ""
            if cur is not None:
                names = v.estimator.names
                show = [n for n in ("CLa", "Cma", "Cmq", "Cmde") if n in names]
                est = " ".join(f"{n} {cur[0][names.index(n)]:+.3g}" for n in show)
            parts.append(f"[sys {v.system_id}: {v.frames} frames {est}]")
        return " | ".join(parts)

    def attach_view(
        self, outlets: Sequence[Outlet], clock: Callable[[], float] = time.monotonic
    ) -> RerunView:
        """Send every vehicle's estimates, the link health and the live tables to these
        outlets from now on."""
        from gcs_estimator.report import live_table

        self.view = RerunView(
            outlets,
            self.config,
            link_source=self.link_now,
            table_source=lambda sid: live_table(self.vehicles[sid].estimator),
            clock=clock,
        )
        return self.view

    def link_now(self) -> tuple[float, dict[str, int]]:
        """(session time of the newest packet [s], link counters), for the live view."""
        return self.t_last_recv - self.t0_recv, self.health.as_dict()

    def link_stats(self) -> dict[str, Any]:
        out: dict[str, Any] = dict(self.health.as_dict())
        out["unknown_messages"] = self.unknown_messages
        out["invalid_values"] = self.decode_stats.invalid_values
        out["ignored_messages"] = self.decode_stats.ignored_messages
        out["vehicles"] = {
            str(v.system_id): {
                "frames": v.sync.stats.frames,
                "partial_frames": v.sync.stats.partial_frames,
                "late_samples": v.sync.stats.late_samples,
                "clock_resets": v.sync.stats.clock_resets,
                "frames_before_inputs": v.sync.stats.waiting_for_inputs,
            }
            for v in self.vehicles.values()
        }
        return out


# ------------------------------------------------------------------ sources


class Stop:
    """Set by SIGINT/SIGTERM; the loops check it and end cleanly."""

    def __init__(self) -> None:
        self.requested = False

    def install(self) -> None:
        def handler(signum: int, frame: FrameType | None) -> None:
            self.requested = True

        signal.signal(signal.SIGINT, handler)
        signal.signal(signal.SIGTERM, handler)


def open_udp(host: str, port: int) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    # SO_RCVBUF is capped by net.core.rmem_max; FORCE (privileged) is not.
    try:
        sock.setsockopt(socket.SOL_SOCKET, getattr(socket, "SO_RCVBUFFORCE", 33), RCVBUF_BYTES)
    except OSError:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RCVBUF_BYTES)
    sock.bind((host, port))
    sock.setblocking(False)
    return sock


def _gcs_messages(
    station: Station, codec: Any, now: float, send: Callable[[bytes, tuple[str, int]], None]
) -> None:
    """Heartbeat to every vehicle, and ask for the configured rates until acknowledged."""
    for v in station.vehicles.values():
        if v.address is None:
            continue
        send(codec.heartbeat_encode(mavlink.MAV_TYPE_GCS, 8, 0, 0, 4).pack(codec), v.address)
        if 0 not in v.acked and now - v.last_rate_request > 5.0:
            v.last_rate_request = now
            for name in STREAMED_MESSAGES:
                rate = station.config.link.rate(name)
                interval_us = 1e6 / rate if rate > 0 else -1
                pkt = codec.command_long_encode(
                    v.system_id,
                    1,
                    mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                    0,
                    mavlink.MSG_ID[name],
                    interval_us,
                    0,
                    0,
                    0,
                    0,
                    0,
                ).pack(codec)
                send(pkt, v.address)


def listen(
    station: Station,
    sock: socket.socket,
    stop: Stop,
    idle_exit_s: float | None = None,
    status_every_s: float = 1.0,
    status_out: TextIO | None = sys.stderr,
    max_seconds: float | None = None,
) -> None:
    """Receive until stopped (signal), idle for idle_exit_s after data, or max_seconds."""
    codec = mavlink.new_codec(mavlink.GCS_SYSTEM_ID, mavlink.GCS_COMPONENT_ID)
    start = time.time()
    last_data = None
    last_gcs = last_status = 0.0

    def send(pkt: bytes, addr: tuple[str, int]) -> None:
        codec.seq = (codec.seq + 1) % 256  # pack() does not advance the sequence number
        try:
            sock.sendto(pkt, addr)
        except OSError:
            station.report_once("send", f"cannot send to {addr}: vehicle gone?")

    while not stop.requested:
        now = time.time()
        if max_seconds is not None and now - start > max_seconds:
            break
        if idle_exit_s is not None and last_data is not None and now - last_data > idle_exit_s:
            break
        ready, _, _ = select.select([sock], [], [], 0.02)
        if ready:
            while True:
                try:
                    data, addr = sock.recvfrom(65535)
                except BlockingIOError:
                    break
                except OSError:
                    break
                t = time.time()
                last_data = t
                packets, junk = mavlink.split_packets(data)
                if junk:
                    station.health.junk_bytes += junk
                    station.health.corrupt += 1
                    station.report_once("junk", "bytes that are no MAVLink packet: skipped")
                for pkt in packets:
                    station.handle_packet(pkt, t, addr)
        now = time.time()
        station.poll(now)
        if station.view is not None:
            station.view.tick()
        if now - last_gcs >= 1.0:
            last_gcs = now
            _gcs_messages(station, codec, now, send)
        tty = status_out is not None and status_out.isatty()
        every = status_every_s if tty else 10 * status_every_s
        if status_out is not None and now - last_status >= every:
            last_status = now
            line = station.status_line(now - start)
            if tty:
                print("\r\033[K" + line, end="", file=status_out, flush=True)
            else:
                print(line, file=status_out, flush=True)
    if status_out is not None and status_out.isatty():
        print(file=status_out)


def replay(
    station: Station,
    records: Iterable[mavlink.TlogRecord],
    total: int | None = None,
    speed: float = 0.0,
    stop: Stop | None = None,
    progress_out: TextIO | None = None,
) -> None:
    """Feed recorded packets through the pipeline; speed 0 = as fast as possible,
    otherwise a multiple of real time (by the recorded receive times)."""
    t0_rec = t0_wall = None
    shown = -1
    for i, rec in enumerate(records):
        if stop is not None and stop.requested:
            break
        t = rec.t_recv_us * 1e-6
        if speed > 0:
            if t0_rec is None:
                t0_rec, t0_wall = t, time.time()
            assert t0_wall is not None
            delay = (t - t0_rec) / speed - (time.time() - t0_wall)
            if delay > 0:
                time.sleep(delay)
        station.handle_packet(rec.packet, t)
        if progress_out is not None and total:
            pct = int(100 * (i + 1) / total)
            if pct != shown:
                shown = pct
                bar = "#" * (pct // 4)
                print(
                    f"\rreplay [{bar:<25}] {pct:3d} % ({i + 1}/{total} packets)",
                    end="",
                    file=progress_out,
                    flush=True,
                )
    if progress_out is not None and total:
        print(file=progress_out)
