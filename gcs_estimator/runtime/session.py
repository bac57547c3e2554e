"""The one loop: frames from a source, both filters per vehicle, outputs to sinks.

    source (UDP, tlog, data file, simulator) -> frames -> Estimator per vehicle -> sinks
    (the Rerun view, the results writer, the status line or progress bar)

A Session drives every command and benchmark alike and owns the shutdown: whatever ends
the run (end of data, a signal, an error in the source), the sinks get the results of
what was processed.
"""

from __future__ import annotations

import gc
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any, Protocol

import numpy as np

from gcs_estimator.arrays import BoolArray, FloatArray
from gcs_estimator.config import AircraftConfig
from gcs_estimator.estimation.estimator import (
    Backend,
    Estimator,
    FilterKind,
    StepOutput,
)
from gcs_estimator.estimation.segments import Limits, Plan
from gcs_estimator.frames import Frame
from gcs_estimator.ingest import compat
from gcs_estimator.model.channels import bank_of
from gcs_estimator.stop import Stop
from gcs_estimator.uncertainty import weighting
from gcs_estimator.uncertainty.metrics import summarise
from gcs_estimator.uncertainty.result import VehicleResult
from gcs_estimator.uncertainty.weighting import StructureCheck

WORK_AHEAD_S = 0.002
"""Restart work done each time the source had nothing ready [s]: small enough that a
packet arriving meanwhile waits little for it."""
BATCH_BLOCK_FRAMES = 256
"""Frames a session without a live view hands an estimator at a time (Session's
block_frames; decision 0065): a few seconds of flight, the Python around each compiled
call shared by that many frames."""
WORK_AHEAD_FRAMES = 5
"""Frames of one vehicle's re-run at a time before the next vehicle's turn."""


@dataclass(frozen=True)
class SegmentFrame(Frame):
    """A recording's frame that begins a segment after frames left out (segments.py), or
    a new flight of several of one airframe: the flight states start afresh there."""

    segment_start: bool = False
    flight: str | None = None
    """The flight this frame begins (its file's name), where a run holds several."""


Hold = Callable[[int, float, float, FloatArray, FloatArray], None]
"""Where a session or a recording gives each frame it is offered, before the gate: (system
id, seconds since the flight's first frame, time, inputs, measurements)."""


class Source(Protocol):
    """Where frames come from."""

    def frames(self, stop: Stop) -> Iterator[Frame | None]:
        """Frames in arrival order; None when time passed without one (sinks may refresh)."""
        ...

    def link_stats(self) -> dict[str, Any] | None:
        """Counters of the link the frames came over (None for a data file)."""
        ...

    def close(self) -> None: ...


class Sink(Protocol):
    """Where the estimates go."""

    def on_frame(self, frame: Frame, outs: Mapping[FilterKind, StepOutput]) -> None: ...

    def tick(self) -> None:
        """Time passed (called after every frame and when the source is idle)."""
        ...

    def finish(self, results: Mapping[int, VehicleResult], link: Mapping[str, Any] | None) -> None:
        """The run ended: final results per vehicle, link counters (None offline)."""
        ...


def config_truth(config: AircraftConfig) -> FloatArray | None:
    return None if config.truth is None else np.array(config.truth, float)


def truth_of(
    config: AircraftConfig,
    truths: Mapping[int, Sequence[float]] | None,
    heard: Mapping[int, Any],
    system_id: int,
) -> FloatArray | None:
    """What a vehicle is scored against: its entry of the truth file; without one, the
    config's [truth] for the first vehicle heard only (`heard`: the vehicles in the order
    heard)."""
    if truths is not None:
        values = truths.get(system_id)
        return None if values is None else np.array(values, float)
    first = next(iter(heard), system_id)
    return config_truth(config) if system_id == first else None


FRAMES_CHECK_MAX = 5_000
"""Frames the data compatibility check of a link's frames takes at the end of a run, over
all its vehicles, each vehicle's last ones (Session.frames_checked): 100 s at 50 Hz, about
0.3 s on one core (a sensor's bias and scale do not change within a flight; 15,000 frames
added 1.5 s to the stop of ten vehicles after an hour, against a target of 2 s in all:
benchmarks/stop.py)."""
FRAMES_CHECK_MIN = 500
"""Fewest frames the check is made on where the budget is nearly spent."""


# Over 200 lines: the one loop (run, its shutdown and idle work) with what it hands each
# frame to (process, or take and flush where a batch's frames go in blocks) and the run's
# results; the estimation itself lives in Estimator, the sinks in outputs.
class Session:
    """Estimators per vehicle between one source and its sinks."""

    def __init__(
        self,
        config: AircraftConfig,
        sinks: Sequence[Sink] = (),
        backend: Backend = "fast",
        keep_history: bool = True,
        truths: Mapping[int, Sequence[float]] | None = None,
        truth_for_first: bool = True,
        gate: Limits | None = None,
        hold: Hold | None = None,
        block_frames: int = 0,
        check_frames: bool = False,
    ) -> None:
        """block_frames: a batch's session (no live view) hands each vehicle's frames to
        its estimator up to this many at a time (Estimator.steps: the same estimates, bit
        for bit), and the sinks see each block's last frame only (on_frame); 0: frame by
        frame. check_frames: the results carry the data compatibility check of each
        vehicle's frames (a link's: no reader checked them; VehicleResult.compatibility)."""
        self.config = config
        self.check_frames = check_frames
        self.block_frames = block_frames
        self._block: list[Frame] = []
        """Frames given to the session and not yet to the estimator (block_frames)."""
        self.hold = hold
        """Given every frame before the gate, with its time since its vehicle's first
        frame (outputs.checks.Checks.hold: the held-out window's frames kept aside)."""
        self._first_t: dict[int, float] = {}
        self.gate = gate
        """The segments' limits judged live, frame by frame (segments.Gate); None: every
        frame is used (a recording's segments are chosen before its frames come)."""
        self.truths = truths
        """Each vehicle's true coefficients by system id (a truth file); None: the
        config's [truth] describes one vehicle, the first heard (see truth_of)."""
        self.truth_for_first = truth_for_first
        """Whether the config's [truth] scores the session's first vehicle (a filter
        worker's first is the station's first in worker 0 only)."""
        self.sinks = list(sinks)
        self.backend = backend
        self.keep_history = keep_history
        self.estimators: dict[int, Estimator] = {}
        self.started = time.perf_counter()
        self.elapsed_s = 0.0
        """Wall-clock duration of the last run [s]."""
        self._results: dict[int, VehicleResult] | None = None
        self._ahead_turn = -1
        """The system id whose restart work work_ahead did last (the next turn is the
        following one)."""

    def estimator(self, system_id: int) -> Estimator:
        est = self.estimators.get(system_id)
        if est is None:
            est = self.estimators[system_id] = Estimator(
                self.config,
                backend=self.backend,
                keep_history=self.keep_history,
                peers_restarting=lambda: self._restarting(but=system_id),
                gate=self.gate,
            )
        return est

    def _restarting(self, but: int) -> int:
        """How many vehicles other than `but` have a restart under way: each adds
        restarts.GRACE_PER_PEER frames to the grace of a restart that begins now, so
        vehicles restarting together take turns on the receive path. It counts from the
        frames the session was given, in their order, so a replay of the link's recording
        counts as the live run did."""
        return sum(e.restarts.under_way for sid, e in self.estimators.items() if sid != but)

    def restart_under_way(self) -> bool:
        """Whether any vehicle has a restart under way (work that idle time can do)."""
        return any(e.restarts.under_way for e in self.estimators.values())

    def add_sink(self, sink: Sink) -> None:
        self.sinks.append(sink)

    def run(self, source: Source, stop: Stop | None = None) -> dict[int, VehicleResult]:
        """Process every frame of the source until it ends or stop is requested; then
        finish the sinks (always, with what was processed) and close the source."""
        stop = stop if stop is not None else Stop()
        self.started = time.perf_counter()
        self._results = None
        plan: Plan | None = getattr(source, "plan", None)
        try:
            try:
                self._frames_of(source, stop)
            finally:
                self.flush()  # the frames kept for a block: processed as frame by frame had
        finally:
            for est in self.estimators.values():
                est.finish_restarts()
                est.pieces.plan = plan if plan is not None else est.pieces.plan
            self.elapsed_s = time.perf_counter() - self.started
            try:
                results = self._results = self.results()
                link = source.link_stats()
                for sink in self.sinks:
                    sink.finish(results, link)
            finally:
                source.close()
        return results

    def _frames_of(self, source: Source, stop: Stop) -> None:
        """Every frame of the source to the estimators (frame by frame, or kept for
        blocks), idle time to the restarts' work, a tick to the sinks after each."""
        for frame in source.frames(stop):
            if frame is None:
                self.flush()
                if getattr(source, "idle", False):
                    self.work_ahead(WORK_AHEAD_S)
            elif self.block_frames > 0:
                self.take(frame)
            else:
                self.process(frame)
            for sink in self.sinks:
                sink.tick()

    def work_ahead(self, budget_s: float) -> None:
        """Restart work from idle time (the source had nothing ready): the vehicles'
        re-runs in turn, one unit at a time (a warm start's fit, or WORK_AHEAD_FRAMES
        frames), until about budget_s has passed. The budget is checked after every
        unit, not after a round of every vehicle: with many vehicles restarting together,
        a round is many fits, and a packet arriving meanwhile would wait for all of them.
        The turn goes on where the last call stopped, so every vehicle's work advances."""
        end = time.perf_counter() + budget_s
        busy = [sid for sid, e in self.estimators.items() if e.restarts.under_way]
        if not busy:
            return
        later = [sid for sid in busy if sid > self._ahead_turn]
        order = later + [sid for sid in busy if sid <= self._ahead_turn]
        while order:
            for sid in list(order):
                self._ahead_turn = sid
                if self.estimators[sid].restarts.work_ahead(WORK_AHEAD_FRAMES) == 0:
                    order.remove(sid)
                if time.perf_counter() >= end:
                    return

    def take(self, frame: Frame) -> None:
        """A frame of a session in blocks (block_frames): kept for its vehicle's block, or,
        where it must be taken alone (a clock reset, a segment's or flight's start, a guessed
        input, the live gate), processed after the block before it. A block holds one
        vehicle's consecutive frames only: every estimator sees the same calls in the same
        order as frame by frame (a restart's grace counts the other vehicles' restarts)."""
        alone = (
            frame.clock_reset
            or not frame.inputs_known
            or self.gate is not None
            or (
                isinstance(frame, SegmentFrame)
                and (frame.segment_start or frame.flight is not None)
            )
        )
        if self._block and (alone or self._block[0].system_id != frame.system_id):
            self.flush()
        if alone:
            self.process(frame)
            return
        self._hold(frame)
        self._block.append(frame)
        if len(self._block) >= self.block_frames:
            self.flush()

    def flush(self) -> None:
        """The frames kept for a block through their vehicle's estimator (Estimator.steps),
        the sinks given the last of them with the outputs there."""
        frames, self._block = self._block, []
        if not frames:
            return
        est = self.estimator(frames[0].system_id)
        t = np.array([f.t_vehicle_s for f in frames], float)
        try:
            u = np.array([f.inputs for f in frames], float)
            y = np.array([f.y for f in frames], float)
        except ValueError:  # frames of different widths (not one source's): one by one
            for frame in frames:
                self._step(est, frame)
            return
        outs = est.steps(t, u, y)
        if outs:
            for sink in self.sinks:
                sink.on_frame(frames[-1], outs)

    def process(self, frame: Frame) -> dict[FilterKind, StepOutput]:
        self._hold(frame)
        return self._step(self.estimator(frame.system_id), frame)

    def _hold(self, frame: Frame) -> None:
        """The frame to hold (before the gate), with its time since its vehicle's first."""
        if self.hold is not None:
            t0 = self._first_t.setdefault(frame.system_id, frame.t_vehicle_s)
            self.hold(
                frame.system_id, frame.t_vehicle_s - t0, frame.t_vehicle_s, frame.inputs, frame.y
            )

    def _step(self, est: Estimator, frame: Frame) -> dict[FilterKind, StepOutput]:
        """A frame through its vehicle's estimator (marks, the gate, the filters), and to
        the sinks."""
        if frame.clock_reset:
            est.rebase(frame.t_vehicle_s, frame.y)
        if isinstance(frame, SegmentFrame):
            if frame.flight is not None:
                est.begin_flight(frame.flight)
            elif frame.segment_start:
                est.start_segment()
        if not est.admit(frame.t_vehicle_s, frame.y, bank_of(frame.inputs)):
            return {}
        outs = est.step(frame.t_vehicle_s, frame.inputs, frame.y, frame.inputs_known)
        for sink in self.sinks:
            sink.on_frame(frame, outs)
        return outs

    def results(self) -> dict[int, VehicleResult]:
        """Each vehicle's result and summaries: those the last run ended with, else as
        things stand now (reads every history: not for every frame)."""
        if self._results is not None:
            return self._results
        out = {}
        checked = 0
        kinematics = FRAMES_CHECK_MAX
        for sid, est in self.estimators.items():
            result = est.result()
            truth = self.truth_of(sid)
            check = self.structure_check(sid, est, checked)
            if not check.skipped:
                checked += est.history_rows
            summaries = summarise(result, truth, check.sigma if not check.skipped else None)
            found = self.frames_checked(est, kinematics)
            if found is not None:
                kinematics -= found["frames_checked"]
            out[sid] = VehicleResult(sid, result, summaries, truth, check, compatibility=found)
        return out

    def frames_checked(
        self, est: Estimator, budget: int = FRAMES_CHECK_MAX
    ) -> dict[str, Any] | None:
        """The data compatibility check of a vehicle's last frames (at most `budget`),
        reported only, where the session checks them, keeps their history, [data]
        compatibility_check is not "off" and the budget leaves FRAMES_CHECK_MIN
        (decision 0084). The dict says how many frames it took, of how many."""
        if not (self.check_frames and est.keep_history and est.history_rows):
            return None
        if self.config.data.compatibility_check == "off" or budget < FRAMES_CHECK_MIN:
            return None
        t, u, y = est.frame_history.arrays()
        take = slice(max(0, len(t) - budget), len(t))
        found = compat.of_frames(t[take], u[take], y[take], self.config.sensors).as_dict()
        return {"frames_checked": len(t[take]), "frames": len(t), **found}

    def structure_check(self, system_id: int, est: Estimator, checked: int = 0) -> StructureCheck:
        """The structure check of one vehicle's run (weighting.py), or why it was not
        made; `checked`: the frames of the session's vehicles checked before it (with
        structure_check = auto, filter.structure_check_max_frames bounds their sum, so a
        station with many vehicles still stops in seconds). It replays the run's final
        pass several times: a line on stderr says so."""
        reason = weighting.why_not(self.config, est.history_rows, est.keep_history, checked)
        if reason:
            return weighting.skipped(reason)
        t, u, y = est.frame_history.arrays()
        print(
            f"vehicle {system_id}: structure check, {weighting.runs(y)} replays of the final "
            f"pass over its {len(t)} frames (filter.structure_check)",
            file=sys.stderr,
        )
        return weighting.structure_check(est, t, u, y)

    def truth_of(self, system_id: int) -> FloatArray | None:
        """What a vehicle is scored against: its entry of the truth file; without one,
        the config's [truth] for the first vehicle heard only (a config describes one
        aircraft: a second vehicle on the link is another, whose values it does not
        know)."""
        if not self.truth_for_first and self.truths is None:
            return None
        return truth_of(self.config, self.truths, self.estimators, system_id)


class RecordingSource:
    """The frames of a recording held in arrays (a data file, a simulated flight), or of
    several flights of one airframe in a row; with a plan (segments.find), only the
    frames of its segments, each segment's first starting the flight states afresh."""

    SYSTEM_ID = 1

    def __init__(
        self,
        t_s: FloatArray,
        inputs: FloatArray,
        measurements: FloatArray,
        inputs_known: BoolArray | None = None,
        plan: Plan | None = None,
        flights: Sequence[tuple[str, int]] = (),
    ) -> None:
        """flights: each flight's name and first frame, where the arrays hold several
        (their times increasing from flight to flight)."""
        self.t_s = np.asarray(t_s, float)
        self.inputs = np.asarray(inputs, float)
        self.measurements = np.asarray(measurements, float)
        self.inputs_known = inputs_known
        """False where a frame's input is a guess (Frame.inputs_known); None: all known."""
        self.plan = plan
        self.flights = list(flights)
        self.done = 0
        self.hold: Hold | None = None
        """Given every frame, the plan's or not, with its time since its flight's first
        frame (Session.hold's, for a recording whose plan leaves frames out)."""

    def _marks(self) -> tuple[BoolArray, BoolArray, dict[int, str]]:
        """Which frames are used, which begin a segment, and which begin a flight (its
        first frame used)."""
        n = len(self.t_s)
        use = np.ones(n, bool) if self.plan is None else self.plan.mask()
        starts = np.zeros(n, bool) if self.plan is None else self.plan.starts()
        begins: dict[int, str] = {}
        bounds = [first for _, first in self.flights] + [n]
        for j, (name, first) in enumerate(self.flights):
            used = np.flatnonzero(use[first : bounds[j + 1]])
            if used.size:
                begins[first + int(used[0])] = name
        return use, starts, begins

    def frames(self, stop: Stop) -> Iterator[Frame | None]:
        use, starts, begins = self._marks()
        firsts = self._flight_starts()
        for i in range(len(self.t_s)):
            if stop.requested:
                return
            self.done = i + 1
            t = float(self.t_s[i])
            if self.hold is not None:
                t_rel = t - float(self.t_s[firsts[i]])
                self.hold(self.SYSTEM_ID, t_rel, t, self.inputs[i], self.measurements[i])
            if not use[i]:
                continue
            known = True if self.inputs_known is None else bool(self.inputs_known[i])
            yield SegmentFrame(
                self.SYSTEM_ID,
                t,
                t,
                self.inputs[i],
                self.measurements[i],
                inputs_known=known,
                segment_start=bool(starts[i]),
                flight=begins.get(i),
            )

    def _flight_starts(self) -> list[int]:
        """Each frame's flight's first frame."""
        firsts = [0] * len(self.t_s)
        bounds = [*(first for _, first in self.flights), len(self.t_s)]
        for j in range(len(self.flights)):
            firsts[bounds[j] : bounds[j + 1]] = [bounds[j]] * (bounds[j + 1] - bounds[j])
        return firsts

    def progress(self) -> tuple[int, int]:
        """(frames done, frames in all)."""
        return self.done, len(self.t_s)

    def link_stats(self) -> dict[str, Any] | None:
        return None

    def close(self) -> None:
        pass


def run_recording(
    config: AircraftConfig,
    t_s: Sequence[float] | FloatArray,
    inputs: FloatArray,
    measurements: FloatArray,
    backend: Backend = "fast",
    keep_history: bool = True,
) -> VehicleResult:
    """Both filters over a whole recording (frames in time order): the result and its
    summaries against the config's truth."""
    session = Session(
        config, backend=backend, keep_history=keep_history, block_frames=BATCH_BLOCK_FRAMES
    )
    session.run(RecordingSource(np.asarray(t_s, float), inputs, measurements))
    return session.results()[RecordingSource.SYSTEM_ID]


def warm_up(
    config: AircraftConfig, backend: Backend = "fast", compile_kernels: bool = True
) -> None:
    """Compile (or load) the filter kernels and import what a restart needs (the
    equation-error warm start, first used at the first restart: over half a second in a
    fresh process) now, not while packets queue up. Then the objects of start-up
    (modules, compiled kernels, the config) are frozen out of the garbage collector: its
    first full collection over them, early in a run, stalled every vehicle's packets at
    once (`bench live` prints where in the flights its slow frames were)."""
    if backend == "fast" and compile_kernels:
        _compile(config)
    gc.collect()
    gc.freeze()


def _compile(config: AircraftConfig) -> None:

    from gcs_estimator.model.aircraft import trim

    filt = replace(config.filter, restart_times_s=(0.1,), restart_frames_per_step=0)
    est = Estimator(replace(config, filter=filt), keep_history=False)
    t = trim(est.model, np.zeros(est.model.n_coefficients) + 0.1)
    y = np.concatenate([t.state, np.zeros(3)])
    for k in range(12):
        u = t.inputs + np.array([0.01 * (k % 3), 0.0])  # a little excitation
        est.step(0.02 * k, u, y)
