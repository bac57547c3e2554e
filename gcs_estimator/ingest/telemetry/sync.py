"""Synchronise one vehicle's samples into frames by the vehicle's own clock.

Every timed observation joins the frame its vehicle time belongs to (samples within
FRAME_WINDOW_S of each other form one frame), however late it arrives, as long as that
frame is still open. Inputs are not part of a frame: each input sample keeps its own
time, and a frame's inputs are the input streams interpolated at the frame's time (or the
earlier sample held, `data.input_hold = "previous"`). So a lost, late or duplicated
input sample changes no other frame than the one it belonged to, and a lost observation
leaves its channel missing in its own frame and nothing else.

Frames leave in time order: a frame goes as soon as it holds every channel the vehicle
streams and its inputs are known at its time, else once the vehicle's clock (from any
later sample) is REORDER_WINDOW_S past it. Nothing here reads a wall clock: a stall of
the ground station, or a replay at any speed, makes the same frames.

The vehicle clock itself is checked:
- 32-bit time fields (SERVO_OUTPUT_RAW.time_usec wraps after 71.6 minutes, every
  time_boot_ms after 49.7 days) are unwrapped per message against the vehicle's other
  clocks; one that wrapped before its first packet arrived (a vehicle up for more than
  71.6 minutes) is aligned to them by whole wraps;
- a sample more than JUMP_S ahead of the newest time, or more than CLOCK_RESET_S behind,
  is held until CONFIRM_SAMPLES samples agree on the new time base (a reboot, or a real
  gap in the data); a single packet with an absurd time never moves the frames. Samples
  no later sample confirmed are dropped and counted.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from gcs_estimator.config import LinkConfig
from gcs_estimator.frames import Frame
from gcs_estimator.ingest.telemetry.decode import Sample
from gcs_estimator.model.channels import N_INPUTS, N_OBS, REQUIRED_INPUTS, Channel

FRAME_WINDOW_S = 0.005
"""Samples this close in vehicle time form one frame [s]: the messages of one autopilot
loop carry times within a few milliseconds of each other."""
REORDER_WINDOW_S = 0.2
"""A frame missing a channel waits until the vehicle's clock is this far past it [s]."""
CLOCK_RESET_S = 1.0
"""A vehicle time this far behind the newest is a clock reset (reboot) once confirmed."""
JUMP_S = 1.0
"""A vehicle time this far ahead of the newest is a gap in the data once confirmed."""
CONFIRM_SAMPLES = 3
"""Timed samples that must agree on a new time base before it is taken."""
ANCHOR_WRAP_S = 86_400.0
"""Samples of a clock that wraps sooner than this wait for one of a clock that does not
(time_boot_ms, a 64-bit time_usec) to align them by whole wraps (VehicleClock) ..."""
ANCHOR_WAIT_SAMPLES = 200
"""... unless this many arrive first: the vehicle has no other clock, and they are taken
as they are."""
WRAP_MATCH_S = 10.0
"""A 32-bit time that went back is a wrap when, unwrapped, it lies this close to the
vehicle's newest time, or when it went from this close below the wrap to this close to 0."""
HOLE_PERIODS = 1.5
"""A frame this many frame periods after the last one processed waits (up to the reorder
window) for the frame between, whose samples may all be late."""
LOST_INPUT_SPACINGS = 1.5
"""Input samples further apart than this many times the input's usual spacing have a
sample lost between them (InputTrack.read); closer, they are the input's own rate, slower
than the frames' where the vehicle sends its servo outputs slower than its sensors."""
INPUT_SPACINGS = 15
"""Recent spacings of an input's samples whose median is its usual spacing (and recent
changes whose median is its usual change)."""
STEP_CHANGES = 4.0
"""Between samples at the input's usual spacing, a change of more than this many times
its usual change from sample to sample is a step (InputTrack.read): an autopilot's
output moves a little at every sample and goes smoothly between them, a pilot's or a
test's doublet holds and then jumps, at an instant its samples do not give."""
PERIOD_SPACINGS = 15
"""Recent frame spacings whose median is the frame period."""
EXPECT_PRESENCE = 0.75
"""A channel is expected in every frame when it was in this share of recent frames."""
PRESENCE_GAIN = 0.1
FIRST_INPUT = int(Channel.ELEVATOR)
"""The first input's channel number (an int: an IntEnum member's look-up costs more than
the subtraction it is for)."""
FIRST_EXPECTED: tuple[int, ...] = tuple(range(Channel.HDOT))
"""The channels expected before any frame has gone: V .. a_z. The climb rate (h_dot, the
last channel), which many vehicles send slower or not at all, becomes expected once it is
present."""


@dataclass
class SyncStats:
    frames: int = 0
    partial_frames: int = 0
    """Frames processed with a channel the vehicle streams missing."""
    late_samples: int = 0
    """Samples whose frame had already been processed, or stale copies: dropped."""
    clock_resets: int = 0
    clock_wraps: int = 0
    """32-bit vehicle time fields unwrapped."""
    time_jumps: int = 0
    """Confirmed forward jumps of the vehicle clock (gaps in the data)."""
    implausible_times: int = 0
    """Samples with a time ahead of the vehicle's that no later sample confirmed: dropped."""
    waiting_for_inputs: int = 0
    """Frames dropped before any elevator and power sample had arrived."""
    inputs_guessed: int = 0
    """Frames whose input sample was lost while the input changed (Frame.inputs_known)."""
    other_component: int = 0
    """Samples of a message that another component of the same system id sends too (a
    gimbal's ATTITUDE beside the autopilot's): dropped (MavlinkLink._sample)."""

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


@dataclass
class VehicleClock:
    """Unwraps the vehicle's 32-bit time fields, per message (each has its own field).

    A field that wraps within hours (SERVO_OUTPUT_RAW.time_usec, every 71.6 min) may have
    wrapped before its first packet arrived: it is still the vehicle's time since boot,
    so its first sample is aligned by whole wraps to the newest time of the vehicle's
    other clocks (`newest`). Synchronizer.add holds such samples until a clock that does
    not wrap within days has given that time (ANCHOR_WRAP_S)."""

    _last: dict[str, float] = field(default_factory=dict)
    _offset: dict[str, float] = field(default_factory=dict)
    wraps: int = 0

    def unwrap(self, message: str, t: float, wrap_s: float | None, newest: float) -> float:
        if wrap_s is None:
            return t
        last = self._last.get(message)
        if last is None:
            offset = 0.0
            if math.isfinite(newest):
                offset = max(0, round((newest - t) / wrap_s)) * wrap_s
                self.wraps += round(offset / wrap_s)
            self._offset[message] = offset
        else:
            offset = self._offset[message]
        if last is not None and t < last - wrap_s / 2:
            near_newest = math.isfinite(newest) and abs(t + offset + wrap_s - newest) < WRAP_MATCH_S
            at_edge = last > wrap_s - WRAP_MATCH_S and t < WRAP_MATCH_S
            if near_newest or at_edge:
                offset += wrap_s
                self._offset[message] = offset
                self.wraps += 1
        self._last[message] = t
        return t + offset

    def reset(self) -> None:
        self._last.clear()
        self._offset.clear()


@dataclass
class ClockAnchor:
    """Before the first sample of a clock that does not wrap within days, samples of one
    that does wait for it (VehicleClock aligns them to it), unless ANCHOR_WAIT_SAMPLES
    say the vehicle has no such clock."""

    anchored: bool = False
    """Whether a clock that does not wrap within days has given the vehicle's time."""
    held: list[Sample] = field(default_factory=list)

    def take(self, sample: Sample) -> list[Sample]:
        """The timed samples to process now, in order."""
        if self.anchored:
            return [sample]
        if (sample.wrap_s or math.inf) < ANCHOR_WRAP_S:
            self.held.append(sample)
            if len(self.held) < ANCHOR_WAIT_SAMPLES:
                return []
            return self.release()
        return [sample, *self.release()]

    def release(self) -> list[Sample]:
        self.anchored = True
        held, self.held = self.held, []
        return held


@dataclass
class InputTrack:
    """One input's samples by vehicle time (kept from just before the oldest open frame)."""

    t: list[float] = field(default_factory=list)
    v: list[float] = field(default_factory=list)
    spacings: deque[float] = field(default_factory=lambda: deque(maxlen=INPUT_SPACINGS))
    """Recent spacings of samples that came in time order [s]."""
    changes: deque[float] = field(default_factory=lambda: deque(maxlen=INPUT_SPACINGS))
    """Their changes of value, in magnitude."""

    def add(self, t: float, v: float) -> None:
        times = self.t
        if not times or times[-1] < t:  # after every sample: the common case
            if times:
                self.spacings.append(t - times[-1])
                self.changes.append(abs(v - self.v[-1]))
            times.append(t)
            self.v.append(v)
            return
        i = bisect.bisect_left(times, t)
        if i < len(self.t) and self.t[i] == t:
            self.v[i] = v  # a copy of the same sample
            return
        self.t.insert(i, t)
        self.v.insert(i, v)

    def known_at(self, t: float, window: float) -> bool:
        """Whether a sample at t, or one after it, has arrived (the value at t is final)."""
        return bool(self.t) and self.t[-1] >= t - window

    def at(self, t: float, window: float, linear: bool) -> float:
        """The value at t: the sample at t, else interpolated between the samples around
        it (or the earlier held), else the last before it held; NaN before any."""
        return self.read(t, window, linear)[0]

    def usual_spacing(self) -> float:
        """The median of the recent spacings [s] (0 until three are known: every gap
        then counts as a lost sample)."""
        return _median(self.spacings)

    def usual_change(self) -> float:
        """The median of the recent changes (0 until three are known, or where the
        input mostly holds: every change then counts as a step)."""
        return _median(self.changes)

    def uncertain_at(self, t: float, window: float) -> bool:
        """Whether the value at t is a guess: no sample at t arrived, the samples around
        it differ, and either they lie further apart than LOST_INPUT_SPACINGS times the
        usual spacing (a sample between them was lost) or their change is a step
        (STEP_CHANGES times the usual change): its instant may lie anywhere between them.
        Between samples at the input's own rate, slower than the frames', an input that
        moves as it usually does is the data's own resolution: interpolated or held,
        not a guess (decision 0084)."""
        return self.read(t, window, True)[1]

    def read(self, t: float, window: float, linear: bool) -> tuple[float, bool]:
        """at() and uncertain_at() by one search (a frame asks both of each input)."""
        times = self.t
        if not times:
            return math.nan, False
        i = bisect.bisect_left(times, t - window)
        n = len(times)
        v = self.v
        if i < n and times[i] <= t + window:
            return v[i], False
        if i == 0:
            return math.nan, False
        if i == n:
            return v[i - 1], False
        before, after = v[i - 1], v[i]
        t0, t1 = times[i - 1], times[i]
        guess = before != after and (
            t1 - t0 > LOST_INPUT_SPACINGS * self.usual_spacing()
            or abs(after - before) > STEP_CHANGES * self.usual_change()
        )
        if not linear:
            return before, guess
        w = (t - t0) / (t1 - t0)
        return before + w * (after - before), guess

    def prune(self, before: float) -> None:
        """Forget samples before `before` but the last one (the hold needs it)."""
        if len(self.t) < 2 or self.t[1] >= before:
            return  # (sorted) nothing to forget
        i = bisect.bisect_left(self.t, before)
        if i > 1:
            del self.t[: i - 1]
            del self.v[: i - 1]

    def clear(self) -> None:
        self.t.clear()
        self.v.clear()
        self.spacings.clear()
        self.changes.clear()


def _median(values: deque[float]) -> float:
    """The median of at least three values, else 0."""
    if len(values) < 3:
        return 0.0
    ordered = sorted(values)
    return ordered[len(ordered) // 2]


@dataclass(slots=True)
class _Open:
    t: float
    t_last_recv: float
    y: list[float]


def _time_of(frame: _Open) -> float:
    return frame.t


# Over 200 lines: one vehicle's samples to frames (clock anchoring, input tracks, open
# frames, late samples) with the common cases' shortcuts (decision 0058) beside the rules
# they skip, so that each shortcut is read next to what it must equal.
@dataclass
class Synchronizer:
    """Frames of one vehicle."""

    system_id: int
    link: LinkConfig
    linear_inputs: bool = True
    stats: SyncStats = field(default_factory=SyncStats)
    clock: VehicleClock = field(default_factory=VehicleClock)
    anchor: ClockAnchor = field(default_factory=ClockAnchor)
    _open: list[_Open] = field(default_factory=list)
    """Open frames in time order."""
    _newest: float = -math.inf
    """Newest vehicle time on the current time base."""
    _last_emitted: float = -math.inf
    _inputs: list[InputTrack] = field(
        default_factory=lambda: [InputTrack() for _ in range(N_INPUTS)]
    )
    _untimed: list[tuple[Channel, float]] = field(default_factory=list)
    _pending: list[tuple[float | None, Sample]] = field(default_factory=list)
    """Samples off the current time base, waiting for confirmation (timed ones' times)."""
    _presence: list[float] = field(default_factory=lambda: [1.0] * len(FIRST_EXPECTED) + [0.0])
    _spacings: deque[float] = field(default_factory=lambda: deque(maxlen=PERIOD_SPACINGS))
    _expected: list[int] = field(default_factory=lambda: list(FIRST_EXPECTED))
    """Channels the vehicle sends in (nearly) every frame."""
    _period: float = math.inf
    """Median spacing of recent frames (inf until known)."""
    _reset_pending: bool = False

    def add(self, sample: Sample) -> list[Frame]:
        """Take one sample; return the frames it lets go (in time order)."""
        t0 = sample.t_vehicle_s
        if t0 is None:
            if self._pending:
                self._pending.append((None, sample))
                return []
            return self._add_untimed(sample)
        if self.anchor.anchored:  # the common case: ClockAnchor.take would give [sample]
            return self._timed(sample, t0)
        return [f for s in self.anchor.take(sample) for f in self._timed(s)]

    def _timed(self, sample: Sample, t0: float | None = None) -> list[Frame]:
        """A timed sample (t0: its time, where the caller has it)."""
        if t0 is None:
            t0 = sample.t_vehicle_s or 0.0  # always a time here (ClockAnchor: timed ones)
        newest = self._newest
        if sample.wrap_s is None:  # VehicleClock.unwrap would give t0 and count no wrap
            t = t0
        else:
            t = self.clock.unwrap(sample.message, t0, sample.wrap_s, newest)
            self.stats.clock_wraps = self.clock.wraps
        if newest == -math.inf or newest - CLOCK_RESET_S <= t <= newest + JUMP_S:  # on base
            if not self._pending:
                return self._accept(t, sample)
            return self._drop_pending() + self._accept(t, sample)
        return self._off_base(t, sample)

    def _drop_pending(self) -> list[Frame]:
        """The vehicle went on at its old time base: what waited was stale (behind) or
        implausible (ahead); its untimed samples belong to the current frames."""
        out: list[Frame] = []
        pending, self._pending = self._pending, []
        for t, sample in pending:
            if t is None:
                out += self._add_untimed(sample)
            elif t < self._newest:
                self.stats.late_samples += 1
            else:
                self.stats.implausible_times += 1
        return out

    def _off_base(self, t: float, sample: Sample) -> list[Frame]:
        timed = [tp for tp, _ in self._pending if tp is not None]
        if timed and abs(t - timed[-1]) > JUMP_S:
            self._drop_pending()  # an earlier candidate that nothing confirmed
            timed = []
        self._pending.append((t, sample))
        if len(timed) + 1 < CONFIRM_SAMPLES:
            return []
        return self._new_base(t < self._newest)

    def _new_base(self, backward: bool) -> list[Frame]:
        """Confirmed: the vehicle clock went back (reboot) or jumped ahead (a gap).
        Whatever is open goes now; inputs from the old base are forgotten."""
        out = self.flush()
        if backward:
            self.stats.clock_resets += 1
            self._reset_pending = True
            self.clock.reset()
        else:
            self.stats.time_jumps += 1
        self._newest = self._last_emitted = -math.inf
        self._spacings.clear()
        self._period = math.inf
        for track in self._inputs:
            track.clear()
        pending, self._pending = self._pending, []
        for _, sample in pending:
            out += self.add(sample)
        return out

    def _accept(self, t: float, sample: Sample) -> list[Frame]:
        if t > self._newest:
            self._newest = t
        window = FRAME_WINDOW_S
        obs = []
        inputs = self._inputs
        for ch, v in sample.values:
            if ch >= N_OBS:
                inputs[ch - FIRST_INPUT].add(t, v)
            else:
                obs.append((ch, v))
        if obs:
            if t <= self._last_emitted + window:
                self.stats.late_samples += 1
            else:
                frame = self._frame_at(t, sample.t_recv_s)
                for ch, v in obs:
                    frame.y[ch] = v
        return self._emit_ready()

    def _frame_at(self, t: float, t_recv_s: float) -> _Open:
        """The open frame that time t belongs to (a new one if none)."""
        window = FRAME_WINDOW_S
        opened = self._open
        if opened and opened[-1].t < t - window:
            i = len(opened)  # after the newest open frame: the common case
        else:
            i = bisect.bisect_left(opened, t - window, key=_time_of)
        if i < len(opened) and opened[i].t <= t + window:
            frame = opened[i]
            frame.t_last_recv = max(frame.t_last_recv, t_recv_s)
            return frame
        frame = _Open(t, t_recv_s, [math.nan] * N_OBS)
        self._open.insert(i, frame)
        if self._untimed and i == len(self._open) - 1:
            for ch, v in self._untimed:
                frame.y[ch] = v
            self._untimed = []
        return frame

    def _add_untimed(self, sample: Sample) -> list[Frame]:
        """A sample without a timestamp (VFR_HUD) belongs with the newest open frame, or
        with the next one if that has gone."""
        obs = [(ch, v) for ch, v in sample.values if ch < N_OBS]
        if self._open and self._open[-1].t >= self._newest - FRAME_WINDOW_S:
            frame = self._open[-1]
            for ch, v in obs:
                frame.y[ch] = v
            frame.t_last_recv = max(frame.t_last_recv, sample.t_recv_s)
            return self._emit_ready()
        self._untimed = obs
        return []

    def _ready(self, frame: _Open) -> bool:
        if self._newest > frame.t + REORDER_WINDOW_S:
            return True
        y = frame.y
        for c in self._expected:
            if y[c] != y[c]:  # NaN: not arrived
                return False
        if frame.t - self._last_emitted > HOLE_PERIODS * self._period:
            return False
        window = FRAME_WINDOW_S
        return all(tr.known_at(frame.t, window) for tr in self._inputs[:REQUIRED_INPUTS])

    def _emit_ready(self) -> list[Frame]:
        out: list[Frame] = []
        while self._open and self._ready(self._open[0]):
            out += self._emit(self._open.pop(0))
        return out

    def flush(self) -> list[Frame]:
        """Process whatever is open (end of stream, or a new time base)."""
        out: list[Frame] = []
        while self._open:
            out += self._emit(self._open.pop(0))
        return out

    def finish(self) -> list[Frame]:
        """End of stream: what is open goes; samples still unconfirmed are dropped."""
        out = [f for s in self.anchor.release() for f in self._timed(s)] + self._drop_pending()
        return out + self.flush()

    def _emit(self, op: _Open) -> list[Frame]:
        t = op.t
        if math.isfinite(self._last_emitted):
            self._spacings.append(t - self._last_emitted)
            if len(self._spacings) >= 3:
                self._period = _median(self._spacings)
        self._last_emitted = t
        have = list(map(math.isfinite, op.y))
        complete = all([have[c] for c in self._expected])
        presence = self._presence
        expected = []
        for c in range(N_OBS):
            p = presence[c] = presence[c] + PRESENCE_GAIN * (have[c] - presence[c])
            if p >= EXPECT_PRESENCE:
                expected.append(c)
        self._expected = expected
        window = FRAME_WINDOW_S
        reads = [tr.read(t, window, self.linear_inputs) for tr in self._inputs]
        u = [value for value, _ in reads]
        guessed = any([guess for _, guess in reads[:REQUIRED_INPUTS]])
        for tr in self._inputs:
            tr.prune(t - window)
        if not all(map(math.isfinite, u[:REQUIRED_INPUTS])):
            self.stats.waiting_for_inputs += 1
            return []
        self.stats.frames += 1
        if not complete:
            self.stats.partial_frames += 1
        reset = self._reset_pending
        self._reset_pending = False
        if guessed:
            self.stats.inputs_guessed += 1
        y = np.array(op.y)
        return [Frame(self.system_id, t, op.t_last_recv, np.array(u), y, reset, not guessed)]
