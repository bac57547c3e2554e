"""An autopilot's log as a Recording: `read_log(path, config) -> (Recording, account)`.

The frames are the samples of the fastest attitude-rate channel (q, else theta), thinned
to at most [link] rate_hz, over the time the vehicle flew on its wing (the autopilot's
own airborne flag, hover removed). A channel about as fast as the frames (FAST_ENOUGH) is
interpolated to them; a slower one gives a measurement only at the frame nearest each of
its samples, its value interpolated to that frame's time (no sample is made up between
samples, nor repeated as if it were new: decision 0045). Inputs never hold NaN: they are
interpolated (or held, [data] input_hold) and held beyond their first and last samples.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import AircraftConfig
from gcs_estimator.ingest import compat
from gcs_estimator.ingest.flightdata import (
    FlightDataError,
    Recording,
    data_file,
    load_csv,
    load_hfb320,
)
from gcs_estimator.ingest.logs import dataflash, detect, presets, ulog
from gcs_estimator.ingest.logs.content import AUX, MEASURED, LogContent, Signal, Span

MIN_AIRBORNE_S = 5.0
"""Less time than this on the wing is no flight to identify anything from [s]."""
GAP_STEPS = 3.0
"""An interpolated channel is missing across a gap of more than this many of its steps."""
FAST_ENOUGH = 1.25
"""A channel whose step is at most this many frame steps is interpolated to every frame
(at most one value in five made up); a slower one is not: a 25 Hz ATT interpolated to
50 Hz frames doubled the pitch angle's samples, half of them made up, and its noise read
five times too low from the smoothed record (decision 0045)."""

Progress = Callable[[float], None]


class LogError(FlightDataError):
    """A log was read but cannot be estimated from as it is (an elevator output without
    its travel, no input at all); its account says what the log holds."""

    def __init__(self, message: str, account: str) -> None:
        super().__init__(message)
        self.account = account


class NotAFlightError(LogError):
    """The log is read, but holds no fixed-wing flight: a multirotor, a VTOL that only
    hovered, a vehicle that never left the ground (exit 1: nothing to estimate)."""


def stderr_progress(label: str) -> Progress:
    """A progress report on stderr: `label: NN%` rewritten in place, a line end at 100 %."""
    shown = [-1]

    def report(fraction: float) -> None:
        pct = int(100 * min(max(fraction, 0.0), 1.0))
        if pct != shown[0]:
            shown[0] = pct
            end = "\n" if pct == 100 else ""
            print(f"\r{label}: {pct:3d}%", end=end, file=sys.stderr, flush=True)

    return report


def load_content(path: str | Path, progress: Progress | None = None) -> LogContent:
    """A log's content as its autopilot's preset reads it."""
    kind = detect.kind(path)
    if kind == "dataflash":
        return presets.arduplane(dataflash.read_bin(path, progress))
    if kind == "dataflash-text":
        return presets.arduplane(dataflash.read_text(path, progress))
    if kind == "ulog":
        return presets.px4(ulog.read(path, presets.PX4_TOPICS, progress))
    raise FlightDataError(f"{path}: a {kind} file, not an autopilot's log")


def read_log(
    path: str | Path, config: AircraftConfig, progress: Progress | None = None
) -> tuple[Recording, str]:
    """The log's flight as a Recording, and a one-line account of what the log holds.
    A log with no fixed-wing flight raises NotAFlightError, one that cannot be estimated
    from as it is (an elevator output without [airframe] elevator_travel_deg) LogError,
    each with the account."""
    content = load_content(path, progress)
    window = flight_window(content)
    text = account(Path(path).name, content, window)
    why = not_a_flight(content, window)
    if why:
        raise NotAFlightError(f"{path}: {why}: nothing to estimate", text)
    assert window is not None
    try:
        return to_recording(Path(path), content, window, config), text
    except LogError:
        raise
    except FlightDataError as exc:
        raise LogError(str(exc), text) from exc


def _total(spans: list[Span]) -> float:
    return float(sum(b - a for a, b in spans))


def _minus(spans: list[Span], cut: list[Span]) -> list[Span]:
    """The parts of spans outside every interval of cut."""
    out = list(spans)
    for c0, c1 in cut:
        nxt: list[Span] = []
        for a, b in out:
            if c1 <= a or c0 >= b:
                nxt.append((a, b))
                continue
            if a < c0:
                nxt.append((a, c0))
            if c1 < b:
                nxt.append((c1, b))
        out = nxt
    return out


def wing_spans(content: LogContent) -> list[Span] | None:
    """When the vehicle flew on its wing (None: the log does not say when it flew)."""
    if content.airborne is None:
        return None
    return [s for s in _minus(content.airborne, content.hover) if s[1] > s[0]]


def flight_window(content: LogContent) -> Span | None:
    """From the first take-off on the wing to the last landing (the whole log where it does
    not say when it flew); None where it never flew on its wing."""
    spans = wing_spans(content)
    if spans is None:
        return content.span_s
    if _total(spans) < MIN_AIRBORNE_S:
        return None
    return spans[0][0], spans[-1][1]


def not_a_flight(content: LogContent, window: Span | None) -> str:
    """Why the log holds nothing to estimate from ("" where it does)."""
    if not content.fixed_wing:
        return (
            f"the vehicle is a {content.vehicle} ({content.autopilot}), not a fixed-wing aircraft"
        )
    if window is not None:
        return ""
    airborne = _total(content.airborne or [])
    if airborne == 0:
        return f"the vehicle never flew ({content.airborne_source} never says airborne)"
    wing = _total(wing_spans(content) or [])
    if content.hover and wing < MIN_AIRBORNE_S:
        return (
            f"the {content.vehicle} hovered as a multirotor for {airborne - wing:.1f} s of its "
            f"{airborne:.1f} s airborne, on its wing for {wing:.1f} s (less than "
            f"{MIN_AIRBORNE_S:g} s)"
        )
    return f"airborne for {airborne:.1f} s only, less than the {MIN_AIRBORNE_S:g} s a fit needs"


def _hovering(content: LogContent) -> float:
    """Airborne time spent hovering [s]."""
    air = content.airborne or []
    return _total(air) - _total(_minus(air, content.hover))


def account(name: str, content: LogContent, window: Span | None) -> str:
    """One line: autopilot, vehicle, duration, airborne time, each channel's rate and source."""
    dur = content.span_s[1] - content.span_s[0]
    air = (
        "airborne: the log does not say"
        if content.airborne is None
        else (
            f"airborne {_total(content.airborne):.1f} s"
            + (f" ({_hovering(content):.1f} s hovering)" if content.hover else "")
        )
    )
    parts = []
    for ch in (*MEASURED, "elevator", "throttle", "rho"):
        sig = content.signals.get(ch)
        if sig is None or not len(sig.t_s):
            parts.append(f"{ch} -")
        else:
            parts.append(f"{ch} {sig.rate_hz(window):.0f} Hz ({sig.source})")
    return f"log {name}: {content.autopilot}, {content.vehicle}, {dur:.1f} s, {air}; " + ", ".join(
        parts
    )


def _frames(content: LogContent, window: Span, max_hz: float) -> FloatArray:
    """The frame times: the fastest attitude-rate channel's samples in the window, thinned
    to at most max_hz."""
    for ch in ("q", "theta", "airspeed"):
        sig = content.signals.get(ch)
        if sig is not None and len(sig.t_s) > 1:
            t = sig.t_s[(sig.t_s >= window[0]) & (sig.t_s <= window[1])]
            if len(t) < 2:
                continue
            rate = sig.rate_hz(window)
            step = max(1, math.ceil(rate / max_hz)) if max_hz > 0 else 1
            return t[::step]
    raise FlightDataError(
        f"{content.autopilot} log: no pitch rate, pitch angle or airspeed in the flight "
        "(messages IMU/ATT/ARSP or vehicle_angular_velocity/vehicle_attitude): nothing to "
        "make frames of"
    )


LATERAL = ("phi", "p", "r")
"""The turn's inputs (model.channels Channel.PHI ..), from the log's attitude and gyros."""


def _lateral(frames: FloatArray, content: LogContent) -> list[FloatArray]:
    """Bank angle, roll and yaw rate at the frame times (interpolated, as inputs are;
    NaN outside their samples, which the model takes as wings level): none where the log
    gives no bank angle."""
    if "phi" not in content.signals:
        return []
    out = []
    for name in LATERAL:
        sig = content.signals.get(name)
        col = np.full(len(frames), np.nan)
        if sig is not None and len(sig.t_s):
            inside = (frames >= sig.t_s[0]) & (frames <= sig.t_s[-1])
            col[inside] = np.interp(frames[inside], sig.t_s, sig.values)
        out.append(col)
    return out


def on_frames(frames: FloatArray, sig: Signal) -> FloatArray:
    """A channel at the frame times: interpolated where it is about as fast as the frames
    (missing across its gaps and outside its samples), else each sample at the frame
    nearest it, its value interpolated to that frame's time, and missing elsewhere."""
    out = np.full(len(frames), np.nan)
    t, v = sig.t_s, sig.values
    if len(t) == 0 or len(frames) == 0:
        return out
    if len(t) == len(frames) and np.array_equal(t, frames):  # the frames' own source
        return v.copy()
    frame_dt = float(np.median(np.diff(frames))) if len(frames) > 1 else 1.0
    step = float(np.median(np.diff(t))) if len(t) > 1 else math.inf
    if step <= FAST_ENOUGH * frame_dt:
        out = np.interp(frames, t, v)
        i = np.clip(np.searchsorted(t, frames), 1, len(t) - 1)
        gap = (t[i] - t[i - 1]) > GAP_STEPS * step
        out[gap | (frames < t[0]) | (frames > t[-1])] = np.nan
        return out
    inside = (t >= frames[0] - frame_dt / 2) & (t <= frames[-1] + frame_dt / 2)
    j = np.clip(np.searchsorted(frames, t[inside]), 1, len(frames) - 1)
    nearer = np.where(np.abs(frames[j - 1] - t[inside]) <= np.abs(frames[j] - t[inside]), j - 1, j)
    out[nearer] = np.interp(frames[nearer], t, v)
    return out


def _input(frames: FloatArray, sig: Signal, hold: str) -> FloatArray:
    """An input at the frame times, never NaN: linear or held between samples, the first
    and last held beyond them."""
    if hold == "previous":
        i = np.clip(np.searchsorted(sig.t_s, frames, side="right") - 1, 0, len(sig.t_s) - 1)
        return np.asarray(sig.values[i], float)
    return np.interp(frames, sig.t_s, sig.values)


def _within(t: FloatArray, spans: list[Span]) -> FloatArray:
    """1.0 at the times within some span, else 0.0."""
    out = np.zeros(len(t))
    for a, b in spans:
        out[(t >= a) & (t <= b)] = 1.0
    return out


def flight_flags(frames: FloatArray, content: LogContent) -> dict[str, FloatArray]:
    """The autopilot's judgement at the frames, for the segments (estimation/segments.py):
    "airborne" (1 in the air, 0 on the ground: a touch-and-go between flights) and "hover"
    (1 while a VTOL flew as a multirotor); none where the log does not say when it flew."""
    if content.airborne is None:
        return {}
    return {"airborne": _within(frames, content.airborne), "hover": _within(frames, content.hover)}


def _need(path: Path, content: LogContent, ch: str, what: str) -> Signal:
    sig = content.signals.get(ch)
    if sig is None or not len(sig.t_s):
        raise FlightDataError(
            f"{path}: no {ch} in the log ({what}): the filters need it as an input"
        )
    return sig


def to_recording(
    path: Path, content: LogContent, window: Span, config: AircraftConfig
) -> Recording:
    """The flight in the window as a Recording on the frame grid (module docstring)."""
    frames = _frames(content, window, config.link.rate_hz)
    elevator = _need(
        path,
        content,
        "elevator",
        "the elevator's output: RCOU with SERVOn_FUNCTION 19, AETR, or actuator_servos",
    )
    throttle = _need(
        path,
        content,
        "throttle",
        "the throttle output: RCOU with SERVOn_FUNCTION 70, AETR, CTUN, actuator_controls or "
        "actuator_motors",
    )
    travel = config.airframe.elevator_travel_deg
    if content.elevator_normalised and travel <= 0:
        raise FlightDataError(
            f"{path}: the log gives the elevator as the autopilot's output ({elevator.source}): "
            f"set [airframe] elevator_travel_deg in {config.source} to the surface's "
            "deflection in degrees at full output (the end of its PWM range), e.g. 20"
        )
    hold = config.data.input_hold
    # the autopilot's command is positive nose-up; the model's elevator positive
    # trailing-edge down (nose-down moment): docs/model.md
    scale = -math.radians(travel) if content.elevator_normalised else -1.0
    de = _input(frames, elevator, hold) * scale
    thr = _input(frames, throttle, hold)
    rho_sig = content.signals.get("rho")  # NaN where the log has none: the airframe's
    rho = np.full(len(frames), np.nan)
    if rho_sig is not None and len(rho_sig.t_s):
        rho = np.interp(frames, rho_sig.t_s, rho_sig.values)
    measured = np.column_stack(
        [
            on_frames(frames, content.signals[c])
            if c in content.signals
            else np.full(len(frames), np.nan)
            for c in MEASURED
        ]
    )
    aux = {c: on_frames(frames, content.signals[c]) for c in AUX if c in content.signals}
    # The climb rate channel (h_dot, up positive) from the log's vertical speed (down
    # positive); missing where the log has none (decision 0049).
    climb = -aux["vz"] if "vz" in aux else np.full(len(frames), np.nan)
    measured = np.column_stack([measured, climb])
    aux.update(flight_flags(frames, content))
    notes = list(content.notes)
    for c in MEASURED:
        if c not in content.signals:
            notes.append(f"{path}: no {c} in the log: the filters go without that channel")
    rec = Recording(
        t_s=frames.copy(),
        inputs=np.column_stack([de, thr, rho, *_lateral(frames, content)]),
        measurements=measured,
        power="throttle",
        notes=tuple(notes),
    )
    return replace(rec, aux=aux)


def load_flight(
    path: str | Path, config: AircraftConfig, progress: Progress | None = None
) -> tuple[Path, Recording, str | None]:
    """Any flight file but a tlog, by its content (detect.kind): (the file, its
    Recording, the log's account or None for a CSV or the HFB-320 record). A folder or a
    bundled record's name stands for its file (flightdata.data_file). The Recording has
    been through the data compatibility check ([data] compatibility_check, compat.py)."""
    file = data_file(path)
    kind = detect.kind(file)
    if kind in detect.LOGS:
        rec, text = read_log(file, config, progress)
        return file, compat.checked(rec, config), text
    if kind == "tlog":
        raise FlightDataError(f"{file}: a MAVLink .tlog: estimate from it with `replay`")
    rec = (
        load_csv(file, config.data, config.airframe.elevator_travel_deg)
        if kind == "csv"
        else load_hfb320(file)
    )
    return file, compat.checked(rec, config), None
