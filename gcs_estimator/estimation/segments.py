"""The parts of a record the model covers: segments of airborne fixed-wing flight.

A log holds more than the model describes: time on the ground, take-off and landing, a
VTOL's hover, turns steeper than the model's bank limit, airspeeds far from trim. The
filters step only within segments: runs of frames where the aircraft flew on its wing,
its bank within the limit (Recording.aux["phi"] where the log has it), its airspeed within
a range of the airframe's trim, long enough to say something. Between segments the
coefficients and their covariance are carried; each segment's first frame starts the
flight states afresh from its measurements (decision 0050).

Pure functions over arrays (a Recording's): `find(...)` gives a Plan, the segments used
and the frames left out, counted by reason (REASONS). `parse_windows` reads the command
line's `--window FROM:TO` (repeatable), which the filters and `refine` share. `Gate` is
the same judgement made frame by frame, live, where the future is not known.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gcs_estimator.arrays import BoolArray, FloatArray
from gcs_estimator.config import ConfigError, FilterTuning

Window = tuple[float | None, float | None]
"""Seconds after a flight's first frame (either side open: None)."""

REASONS = ("window", "ground", "hover", "airspeed", "bank", "short")
"""Why frames are left out, in the order they are judged: outside every --window, on the
ground, hovering (a VTOL), airspeed out of range, bank beyond the limit, in a run of
frames too short to be a segment."""

AIRSPEED_RANGE = (0.5, 2.0)
"""The airspeeds the model covers, as multiples of [airframe] trim_airspeed_mps: below,
a take-off roll, a stall or a hover; above, a dive far from the coefficients' trim."""

MIN_SEGMENT_S = 2.0
"""A run of frames shorter than this [s] is left out (too short): its flight states,
started afresh, would barely have settled."""

MAX_GAP_S = 2.0
"""Frames further apart than this [s] belong to different segments (the filters' own
longest prediction, filters.core.MAX_GAP_S)."""


@dataclass(frozen=True)
class Limits:
    """What a segment must keep within."""

    trim_airspeed_mps: float
    airspeed_range: tuple[float, float] = AIRSPEED_RANGE
    max_bank_rad: float = math.radians(FilterTuning.bank_limit_deg)
    """Bank beyond which a frame is left out: the run's [filter] bank_limit_deg (the
    filters' own limit, decision 0048), so a segment ends where the filters stop taking
    frames in their update."""
    min_segment_s: float = MIN_SEGMENT_S
    windows: tuple[Window, ...] = ()
    """--window FROM:TO (seconds after the flight's first frame); empty: the whole flight."""

    @property
    def airspeed_mps(self) -> tuple[float, float]:
        lo, hi = self.airspeed_range
        return lo * self.trim_airspeed_mps, hi * self.trim_airspeed_mps


@dataclass(frozen=True)
class Segment:
    """Frames first..stop-1 of a flight, times t0..t1 [s] on the record's clock."""

    first: int
    stop: int
    t0: float
    t1: float
    flight: int = 0

    @property
    def frames(self) -> int:
        return self.stop - self.first

    @property
    def duration_s(self) -> float:
        return self.t1 - self.t0


@dataclass(frozen=True)
class Plan:
    """A record's segments and what was left out of them."""

    frames: int
    """Frames in the record."""
    segments: tuple[Segment, ...]
    left_out: Mapping[str, int] = field(default_factory=dict)
    """Frames left out per reason (REASONS; each frame counted once, by its first)."""
    left_out_s: Mapping[str, float] = field(default_factory=dict)
    """Their time per reason [s] (each frame standing for its interval to the next)."""

    @property
    def used(self) -> int:
        return sum(s.frames for s in self.segments)

    def mask(self) -> BoolArray:
        """[frames] True on the frames of a segment."""
        out = np.zeros(self.frames, bool)
        for s in self.segments:
            out[s.first : s.stop] = True
        return out

    def starts(self) -> BoolArray:
        """[frames] True on each segment's first frame."""
        out = np.zeros(self.frames, bool)
        for s in self.segments:
            out[s.first] = True
        return out

    def summary(self) -> str:
        """One line: the segments used and why the rest was left out."""
        secs = sum(s.duration_s for s in self.segments)
        text = (
            f"segments: {len(self.segments)} used, {self.used} of {self.frames} frames "
            f"({secs:.1f} s)"
        )
        why = [
            f"{r} {self.left_out[r]} ({self.left_out_s[r]:.1f} s)"
            for r in REASONS
            if self.left_out.get(r)
        ]
        return text + ("; left out: " + ", ".join(why) if why else "")

    def as_json(self) -> dict[str, Any]:
        return {
            "frames": self.frames,
            "frames_used": self.used,
            "segments": [
                {
                    "flight": s.flight,
                    "first_frame": s.first,
                    "frames": s.frames,
                    "t0_s": s.t0,
                    "t1_s": s.t1,
                }
                for s in self.segments
            ],
            "left_out_frames": {r: int(self.left_out.get(r, 0)) for r in REASONS},
            "left_out_s": {r: round(float(self.left_out_s.get(r, 0.0)), 3) for r in REASONS},
        }


def parse_window(text: str) -> Window:
    """`FROM:TO` in seconds, either side may be empty (ConfigError naming the option)."""
    lo, sep, hi = text.partition(":")
    try:
        if not sep:
            raise ValueError(text)
        start = float(lo) if lo.strip() else None
        end = float(hi) if hi.strip() else None
    except ValueError:
        raise ConfigError(f"--window {text!r}: expected FROM:TO in seconds, e.g. 0:60") from None
    if start is not None and end is not None and not start < end:
        raise ConfigError(f"--window {text!r}: FROM must come before TO, e.g. 0:60")
    return start, end


def parse_windows(texts: str | Sequence[str] | None) -> tuple[Window, ...]:
    """Every --window given (none: the whole flight)."""
    if not texts:
        return ()
    if isinstance(texts, str):
        texts = [texts]
    return tuple(parse_window(t) for t in texts if t)


def excluding(windows: Sequence[Window], held: Window) -> tuple[Window, ...]:
    """The windows (none: the whole flight) with the held-out window `held` taken out."""
    h_lo = -math.inf if held[0] is None else held[0]
    h_hi = math.inf if held[1] is None else held[1]
    out: list[Window] = []
    for lo, hi in windows or [(None, None)]:
        a = -math.inf if lo is None else lo
        b = math.inf if hi is None else hi
        if a < min(b, h_lo):
            out.append((lo, hi if b <= h_lo else held[0]))
        if max(a, h_hi) < b:
            out.append((lo if a >= h_hi else held[1], hi))
    return tuple(out)


def in_windows(t: FloatArray, windows: Sequence[Window]) -> BoolArray:
    """[N] whether each time (seconds after the flight's first frame) lies in some window
    (every time, with none)."""
    if not windows:
        return np.ones(len(t), bool)
    out = np.zeros(len(t), bool)
    for lo, hi in windows:
        a = -math.inf if lo is None else lo
        b = math.inf if hi is None else hi
        out |= (t >= a) & (t <= b)
    return out


def held(x: FloatArray) -> FloatArray:
    """A sampled signal at every frame: each NaN replaced by the latest value before it
    (the first value before the first sample); all NaN where it has none."""
    finite = np.isfinite(x)
    if not finite.any():
        return np.full(len(x), np.nan)
    idx = np.where(finite, np.arange(len(x)), 0)
    np.maximum.accumulate(idx, out=idx)
    out = x[idx]
    out[: int(np.argmax(finite))] = x[int(np.argmax(finite))]
    return np.asarray(out, float)


def reasons(
    t_s: FloatArray,
    airspeed: FloatArray,
    aux: Mapping[str, FloatArray],
    limits: Limits,
) -> list[str | None]:
    """Each frame's reason to be left out (REASONS' first that applies), None where the
    model covers it. aux: "airborne" (1 in the air, 0 on the ground) and "hover" (1 while
    a VTOL hovers) where the log says, "phi" [rad] where it has the bank angle."""
    n = len(t_s)
    rel = t_s - t_s[0] if n else t_s
    v = held(np.asarray(airspeed, float))
    lo, hi = limits.airspeed_mps
    checks: list[tuple[str, BoolArray]] = [("window", ~in_windows(rel, limits.windows))]
    if "airborne" in aux:
        checks.append(("ground", held(np.asarray(aux["airborne"], float)) == 0.0))
    if "hover" in aux:
        checks.append(("hover", held(np.asarray(aux["hover"], float)) > 0.0))
    checks.append(("airspeed", np.isfinite(v) & ((v < lo) | (v > hi))))
    if "phi" in aux:
        phi = held(np.asarray(aux["phi"], float))
        checks.append(("bank", np.isfinite(phi) & (np.abs(phi) > limits.max_bank_rad)))
    out: list[str | None] = [None] * n
    for name, bad in reversed(checks):  # the first reason in REASONS' order wins
        for i in np.flatnonzero(bad):
            out[i] = name
    return out


def find(
    t_s: FloatArray,
    airspeed: FloatArray,
    aux: Mapping[str, FloatArray],
    limits: Limits,
    flight: int = 0,
) -> Plan:
    """The segments of one flight's frames (t_s increasing [s], the measured airspeed
    [m/s], NaN where not sampled) and what was left out (module docstring)."""
    t = np.asarray(t_s, float)
    why = reasons(t, airspeed, aux, limits)
    segments: list[Segment] = []
    first: int | None = None
    for i in range(len(t) + 1):
        ok = i < len(t) and why[i] is None
        if ok and first is not None and t[i] - t[i - 1] > MAX_GAP_S:
            segments.append(Segment(first, i, float(t[first]), float(t[i - 1]), flight))
            first = None
        if ok and first is None:
            first = i
        elif not ok and first is not None:
            segments.append(Segment(first, i, float(t[first]), float(t[i - 1]), flight))
            first = None
    kept: list[Segment] = []
    for s in segments:
        if s.duration_s < limits.min_segment_s:
            for i in range(s.first, s.stop):
                why[i] = "short"
        else:
            kept.append(s)
    return Plan(len(t), tuple(kept), *_counted(t, why))


def _counted(t: FloatArray, why: Sequence[str | None]) -> tuple[dict[str, int], dict[str, float]]:
    """Frames and seconds left out per reason (each frame standing for the interval to the
    next, the last for the median interval; no interval longer than MAX_GAP_S)."""
    step = np.diff(t) if len(t) > 1 else np.zeros(0)
    last = float(np.median(step)) if len(step) else 0.0
    dt = np.minimum(np.append(step, last), MAX_GAP_S)
    frames = dict.fromkeys(REASONS, 0)
    secs = dict.fromkeys(REASONS, 0.0)
    for i, r in enumerate(why):
        if r is not None:
            frames[r] += 1
            secs[r] += float(dt[i])
    return frames, secs


def merged(plans: Sequence[Plan], offsets: Sequence[int]) -> Plan:
    """Several flights' plans as one over their frames in a row (the flights' frames
    starting at `offsets`), each segment keeping its flight."""
    segments = tuple(
        Segment(s.first + o, s.stop + o, s.t0, s.t1, s.flight)
        for p, o in zip(plans, offsets, strict=True)
        for s in p.segments
    )
    frames = {r: sum(p.left_out.get(r, 0) for p in plans) for r in REASONS}
    secs = {r: sum(p.left_out_s.get(r, 0.0) for p in plans) for r in REASONS}
    return Plan(sum(p.frames for p in plans), segments, frames, secs)


class Gate:
    """The segments' judgement live, frame by frame: a frame outside every --window (from
    the first frame seen), or whose latest airspeed (or bank, where frames carry it) is
    beyond the limits, is left out and counted; the next frame within them begins a new
    segment (the flight states start afresh there). A segment's length is not known while
    it lasts: live, no run is left out as short."""

    def __init__(self, limits: Limits) -> None:
        self.limits = limits
        self.left_out = dict.fromkeys(REASONS, 0)
        self.segments = 0
        self._airspeed = math.nan
        self._t0 = math.nan
        self._outside = False

    def _reason(self, t: float, airspeed: float, phi: float) -> str | None:
        if math.isnan(self._t0):
            self._t0 = t
        if math.isfinite(airspeed):
            self._airspeed = airspeed
        if not in_windows(np.array([t - self._t0]), self.limits.windows)[0]:
            return "window"
        lo, hi = self.limits.airspeed_mps
        if math.isfinite(self._airspeed) and not lo <= self._airspeed <= hi:
            return "airspeed"
        if math.isfinite(phi) and abs(phi) > self.limits.max_bank_rad:
            return "bank"
        return None

    def admit(self, t: float, airspeed: float, phi: float = math.nan) -> tuple[bool, bool]:
        """(whether the frame at time t [s] is used, whether it begins a segment after
        frames left out)."""
        reason = self._reason(t, airspeed, phi)
        if reason is not None:
            self.left_out[reason] += 1
            self._outside = True
            return False, False
        fresh = self._outside
        if fresh or self.segments == 0:
            self.segments += 1
        self._outside = False
        return True, fresh


def describe(report: Mapping[str, Any] | None) -> str:
    """A run's segments in one line, from EstimatorResult.segments ("" where every frame
    was used)."""
    if not report:
        return ""
    left = report.get("left_out_frames", {})
    why = ", ".join(f"{r} {left[r]}" for r in REASONS if left.get(r))
    if "segments" in report:
        spans = [f"{s['t0_s']:.1f}-{s['t1_s']:.1f} s" for s in report["segments"]]
        more = "" if len(spans) <= 6 else f" and {len(spans) - 6} more"
        used = f"{len(spans)} segment(s) used ({', '.join(spans[:6])}{more})"
    else:
        used = f"{report.get('segments_begun', 0)} segment(s) begun live"
    text = f"segments: {used}, {report['frames_used']} of {report['frames']} frames"
    return text + (f"; frames left out: {why}" if why else "")


def describe_flights(flights: Sequence[Mapping[str, Any]], kind: str = "IEKF") -> list[str]:
    """Each flight's part (Estimator.flight_parts), a line each: for filter `kind`, the
    share of each coefficient's variance the flight removed."""
    out = []
    for part in flights:
        removed = part["filters"].get(kind, {}).get("variance_removed", {})
        shares = ", ".join(f"{n} {100 * v:.0f} %" for n, v in removed.items())
        out.append(
            f"flight {part['flight']} ({part['frames']} frames): the {kind}'s variance it "
            f"removed: {shares}"
        )
    return out


class Pieces:
    """Where a run's frames start afresh (segments.py's module docstring): one vehicle's
    segments and flights as its estimator meets them, and what it reports of them."""

    def __init__(self, gate: Limits | None = None) -> None:
        self.gate = None if gate is None else Gate(gate)
        """The segments' limits judged frame by frame (live); None: every frame admitted
        is used (a recording's segments are chosen before its frames come)."""
        self.plan: Plan | None = None
        """The recording's segments, where they were chosen before the run (find)."""
        self.fresh_frames: list[int] = []
        """The frames (stepped, in order) that began a segment or flight after frames left
        out: the flight states started afresh there from the measurements."""
        self.flights: list[tuple[str, int]] = []
        """Each flight's name and first frame (stepped), where a run holds several."""
        self.pending = False
        """The next frame stepped begins a segment."""

    def admit(self, t: float, airspeed: float, stepped: int, phi: float = math.nan) -> bool:
        """Whether the gate (live) uses the frame (bank phi [rad], NaN where unknown); one
        that begins a segment after frames left out is marked pending (not the run's
        first: that one starts anyway)."""
        if self.gate is None:
            return True
        use, fresh = self.gate.admit(t, airspeed, phi)
        self.pending = self.pending or (fresh and stepped > 0)
        return use

    def take(self, stepped: int) -> bool:
        """Whether frame `stepped`, now stepped, starts afresh (recorded)."""
        if not self.pending:
            return False
        self.pending = False
        self.fresh_frames.append(stepped)
        return True

    def report(self, stepped: int) -> dict[str, Any] | None:
        """The segments used and the frames left out (EstimatorResult.segments)."""
        if self.plan is not None:
            return self.plan.as_json()
        if self.gate is not None:
            return {
                "frames": stepped + sum(self.gate.left_out.values()),
                "frames_used": stepped,
                "segments_begun": self.gate.segments,
                "left_out_frames": dict(self.gate.left_out),
            }
        return None
