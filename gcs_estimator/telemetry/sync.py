"""Synchronise samples into frames by vehicle time, and count link health.

A frame gathers the samples whose vehicle times lie within the frame window. It is
processed as soon as it holds every observation channel, else when a later sample opens
the next frame, else when it has waited `max_wait_s` in receive time: a lost packet
never stalls the filter. Inputs are held between samples. Waiting is measured in receive
time, never wall-clock time, so that a replay of the recorded packets makes the same
frames as the live run did.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import LinkConfig
from gcs_estimator.frames import Frame
from gcs_estimator.model.channels import N_INPUTS, N_OBS, REQUIRED_INPUTS, Channel
from gcs_estimator.telemetry.decode import Sample

CLOCK_RESET_S = 1.0
"""A vehicle time this far behind the last frame is a clock reset (reboot), not lateness."""


@dataclass
class SyncStats:
    frames: int = 0
    partial_frames: int = 0
    late_samples: int = 0
    """Samples older than the last processed frame: dropped."""
    clock_resets: int = 0
    waiting_for_inputs: int = 0
    """Frames dropped before any elevator and power sample had arrived."""


@dataclass
class _Open:
    t: float
    t_first_recv: float
    t_last_recv: float
    y: FloatArray


@dataclass
class Synchronizer:
    """Frames of one vehicle."""

    system_id: int
    link: LinkConfig
    stats: SyncStats = field(default_factory=SyncStats)
    _open: _Open | None = None
    _last_t: float = -math.inf
    _inputs: list[float] = field(default_factory=lambda: [math.nan] * N_INPUTS)
    _untimed: list[tuple[Channel, float]] = field(default_factory=list)
    _reset_pending: bool = False

    def add(self, sample: Sample) -> list[Frame]:
        """Take one sample; return the frames it completes (zero, one or two)."""
        for ch, v in sample.values:
            if ch in (Channel.ELEVATOR, Channel.POWER, Channel.DENSITY):
                self._inputs[ch - Channel.ELEVATOR] = v
        obs = [(ch, v) for ch, v in sample.values if ch < N_OBS]
        t = sample.t_vehicle_s
        if t is None:
            return self._add_untimed(obs, sample.t_recv_s)
        out = self._close_before(t)
        if self._open is None:
            if t <= self._last_t:
                self.stats.late_samples += 1
                return out
            y = np.full(N_OBS, np.nan)
            self._open = _Open(t, sample.t_recv_s, sample.t_recv_s, y)
            for ch, v in self._untimed:
                y[ch] = v
            self._untimed = []
        elif t < self._open.t - self.link.frame_window_s:
            self.stats.late_samples += 1
            return out
        return out + self._fill(obs, sample.t_recv_s)

    def _add_untimed(self, obs: list[tuple[Channel, float]], t_recv_s: float) -> list[Frame]:
        """A sample without a timestamp (VFR_HUD) belongs with the frame being filled."""
        if self._open is None:
            self._untimed += obs
            return []
        return self._fill(obs, t_recv_s)

    def _fill(self, obs: list[tuple[Channel, float]], t_recv_s: float) -> list[Frame]:
        assert self._open is not None
        for ch, v in obs:
            self._open.y[ch] = v
        self._open.t_last_recv = t_recv_s
        return self._emit_if_complete()

    def _close_before(self, t: float) -> list[Frame]:
        """Frames that a sample at vehicle time t closes: the open one if t starts a new
        frame, and, when t went back by more than CLOCK_RESET_S, everything before it."""
        out: list[Frame] = []
        if t < self._last_t - CLOCK_RESET_S or (
            self._open is not None and t < self._open.t - CLOCK_RESET_S
        ):
            self.stats.clock_resets += 1
            out += self._emit()
            self._last_t = -math.inf
            self._reset_pending = True
        if self._open is not None and t > self._open.t + self.link.frame_window_s:
            out += self._emit()
        return out

    def poll(self, t_recv_s: float) -> list[Frame]:
        """Process a partial frame that has waited longer than max_wait_s."""
        if self._open is not None and t_recv_s - self._open.t_first_recv > self.link.max_wait_s:
            return self._emit()
        return []

    def flush(self) -> list[Frame]:
        """Process whatever is open (end of stream)."""
        return self._emit()

    def _emit_if_complete(self) -> list[Frame]:
        assert self._open is not None
        if np.all(np.isfinite(self._open.y)) and self._have_inputs():
            return self._emit()
        return []

    def _have_inputs(self) -> bool:
        """Elevator and power have arrived (air density is optional)."""
        return all(math.isfinite(v) for v in self._inputs[:REQUIRED_INPUTS])

    def _emit(self) -> list[Frame]:
        op = self._open
        if op is None:
            return []
        self._open = None
        self._last_t = op.t
        if not self._have_inputs():
            self.stats.waiting_for_inputs += 1
            return []
        self.stats.frames += 1
        if not np.all(np.isfinite(op.y)):
            self.stats.partial_frames += 1
        reset = self._reset_pending
        self._reset_pending = False
        return [Frame(self.system_id, op.t, op.t_last_recv, np.array(self._inputs), op.y, reset)]


@dataclass
class LinkHealth:
    """Packet counts per link, from 8-bit sequence numbers per (system, component)."""

    received: int = 0
    lost: int = 0
    duplicates: int = 0
    out_of_order: int = 0
    corrupt: int = 0
    """Packets that failed the CRC or could not be framed."""
    junk_bytes: int = 0
    _last_seq: dict[tuple[int, int], int] = field(default_factory=dict)

    def on_packet(self, system_id: int, component_id: int, seq: int) -> bool:
        """Count a packet; False if it is a duplicate to be dropped."""
        key = (system_id, component_id)
        last = self._last_seq.get(key)
        self.received += 1
        if last is None:
            self._last_seq[key] = seq
            return True
        d = (seq - last) & 0xFF
        if d == 0:
            self.duplicates += 1
            self.received -= 1
            return False
        if d < 128:
            self.lost += d - 1
            self._last_seq[key] = seq
            return True
        # Behind the newest: a packet counted lost has arrived after all.
        self.out_of_order += 1
        self.lost = max(0, self.lost - 1)
        return True

    def as_dict(self) -> dict[str, int]:
        return {
            "received": self.received,
            "lost": self.lost,
            "duplicates": self.duplicates,
            "out_of_order": self.out_of_order,
            "corrupt": self.corrupt,
            "junk_bytes": self.junk_bytes,
        }
