"""The checks a finished vehicle gets before its table: the held-out check where
--validate asked for one (decision 0051), the marks it drops, and what to fly next
(decision 0052)."""

from __future__ import annotations

import sys
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from gcs_estimator.arrays import FloatArray
from gcs_estimator.estimation.segments import Window
from gcs_estimator.outputs.table import LiveEstimate
from gcs_estimator.uncertainty.advice import advice_of, live_advice
from gcs_estimator.uncertainty.holdout import Holdout, dropped_marks, dropped_summary
from gcs_estimator.uncertainty.result import VehicleResult

if TYPE_CHECKING:
    from gcs_estimator.refine import Refined


def _window_text(w: Window) -> str:
    lo = "start" if w[0] is None else f"{w[0]:g} s"
    hi = "end" if w[1] is None else f"{w[1]:g} s"
    return f"the window {lo} to {hi} of the record"


def _overlap(a: Window, b: Window) -> bool:
    lo = max(-np.inf if a[0] is None else a[0], -np.inf if b[0] is None else b[0])
    hi = min(np.inf if a[1] is None else a[1], np.inf if b[1] is None else b[1])
    return bool(lo < hi)


HELD_MIN_FRAMES = 10
"""Frames of the held-out window the run's history must hold for the check to take them
from it (refine.holdout.MIN_FRAMES); fewer: the frames kept aside (HeldFrames)."""


@dataclass
class HeldFrames:
    """A vehicle's frames in the held-out window as they came, before the segments' gate
    (which leaves the window out of the filters, and with it out of their history)."""

    t: list[float] = field(default_factory=list)
    u: list[FloatArray] = field(default_factory=list)
    y: list[FloatArray] = field(default_factory=list)
    t_rel: float = -np.inf
    """The last frame's time after its flight's first frame: one not after it is a later
    flight's (several of one aircraft), whose window is not the one held out."""

    def arrays(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        return np.array(self.t, float), np.array(self.u, float), np.array(self.y, float)


@dataclass(frozen=True)
class Checks:
    """The held-out check and the advice, as a results sink's `checks` (a value, so a
    filter worker can be given it). validate: a window of the record (seconds after its
    first frame) or another log of the same aircraft; fitted: the windows the filters and
    the whole-record fit took (none: the whole flight), to tell whether the held-out
    window was fitted too."""

    window: Window | None = None
    log: str | None = None
    advise: bool = True
    fitted: tuple[Window, ...] = ()
    failures: list[str] = field(default_factory=list, compare=False, repr=False)
    done: dict[int, VehicleResult] = field(default_factory=dict, compare=False, repr=False)
    """Each vehicle as checked (the view's final panels read it)."""
    held: dict[int, HeldFrames] = field(default_factory=dict, compare=False, repr=False)
    """Each vehicle's frames of the held-out window, kept aside as they came (hold)."""

    def hold(
        self, system_id: int, t_rel: float, t: float, inputs: FloatArray, y: FloatArray
    ) -> None:
        """Keep a frame that is in the held-out window (t_rel: seconds after the flight's
        first frame; the first flight's, where a run has several), whether the filters
        take it or not: with --window or the segments' gate, they leave the held-out window
        out, and their history has none of it."""
        w = self.window
        if w is None or (w[0] is not None and t_rel < w[0]) or (w[1] is not None and t_rel > w[1]):
            return
        kept = self.held.setdefault(system_id, HeldFrames())
        if t_rel <= kept.t_rel:
            return
        kept.t_rel = t_rel
        kept.t.append(t)
        kept.u.append(np.array(inputs, float))
        kept.y.append(np.array(y, float))

    def __call__(
        self, vehicle: VehicleResult, refined: Refined | None
    ) -> tuple[VehicleResult, Refined | None]:
        if self.window is not None or self.log is not None:
            try:
                holdout = self._holdout(vehicle, refined)
            except (ValueError, OSError) as exc:
                print(f"validate: {exc}", file=sys.stderr)
                self.failures.append(f"vehicle {vehicle.system_id}: {exc}")
            else:
                vehicle, refined = _drop(vehicle, refined, holdout)
        if self.advise:
            summary = vehicle.summaries.get("IEKF")
            vehicle = replace(vehicle, advice=advice_of(vehicle.result, summary))
        self.done[vehicle.system_id] = vehicle
        return vehicle, refined

    def _estimates(
        self, vehicle: VehicleResult, refined: Refined | None
    ) -> tuple[FloatArray, FloatArray, str]:
        if refined is not None:
            return refined.coefficients, refined.biases, f"the {refined.method} fit's estimates"
        fr = vehicle.result.filters["IEKF"]
        return fr.coefficients, fr.biases, "the IEKF's final estimates"

    def _holdout(self, vehicle: VehicleResult, refined: Refined | None) -> Holdout:
        from gcs_estimator.refine.holdout import check

        result = vehicle.result
        config = result.config
        coefficients, biases, whose = self._estimates(vehicle, refined)
        noise = np.asarray(result.measurement_sigma or config.filter.measurement_sigma, float)
        if self.log is not None:
            from gcs_estimator.ingest.logs.reader import load_flight

            path, rec, _ = load_flight(self.log, config)
            return check(
                config,
                coefficients,
                biases,
                np.asarray(rec.t_s, float),
                np.asarray(rec.inputs, float),
                np.asarray(rec.measurements, float),
                noise,
                f"log {Path(path).name}",
                whose,
            )
        assert self.window is not None
        fr = result.filters["IEKF"]
        track = fr.track
        if track is None or len(track.t) == 0:
            raise ValueError("the run kept no history to take a window of")
        rel = track.t - track.t[0]
        lo = -np.inf if self.window[0] is None else self.window[0]
        hi = np.inf if self.window[1] is None else self.window[1]
        idx = np.flatnonzero((rel >= lo) & (rel <= hi))
        window = self.window
        in_sample = not self.fitted or any(_overlap(window, w) for w in self.fitted)
        kept = self.held.get(vehicle.system_id)
        if len(idx) < HELD_MIN_FRAMES and kept is not None:  # the filters left it out
            t, u, y = kept.arrays()
            return check(
                config, coefficients, biases, t, u, y, noise, _window_text(window), whose,
                in_sample=in_sample,
            )  # fmt: skip
        return check(
            config,
            coefficients,
            biases,
            track.t[idx],
            track.u[idx],
            track.y[idx],
            noise,
            _window_text(self.window),
            whose,
            states=track.x[idx],
            in_sample=in_sample,
        )


def _drop(
    vehicle: VehicleResult, refined: Refined | None, holdout: Holdout
) -> tuple[VehicleResult, Refined | None]:
    """The vehicle with the held-out check, and the marks of the coefficients whose
    channels it missed dropped to weak (each filter's and the fit's)."""
    config = vehicle.result.config
    names = config.coefficient_names
    drops = holdout.drops(names, config.structure.axes)
    summaries = {k: dropped_summary(s, drops) for k, s in vehicle.summaries.items()}
    vehicle = replace(vehicle, summaries=summaries, holdout=holdout, holdout_drops=drops)
    if refined is not None and drops:
        refined = replace(
            refined, identifiability=dropped_marks(refined.identifiability, names, drops)
        )
    return vehicle, refined


LIVE_MIN_FRAMES = 100
"""Frames a vehicle's filters have seen before the live advice is worked out."""


def live_advice_text(estimate: LiveEstimate, airspeed_mps: float) -> str:
    """What to fly next as the live view shows it (Markdown), from the IEKF's current
    estimate and sigma (advice.live_advice)."""
    if estimate.frames < LIVE_MIN_FRAMES:
        return f"what to fly next: after {LIVE_MIN_FRAMES} frames ({estimate.frames} so far)"
    snap = estimate.snapshot().get("IEKF")
    if snap is None:
        return "what to fly next: no IEKF estimate yet"
    advice = live_advice(estimate.config, snap.coefficients, snap.sigma, airspeed_mps)
    return "```\n" + "\n".join(advice.lines()) + "\n```\n"
