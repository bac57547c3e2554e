"""Online estimation of one aircraft: EKF and IEKF side by side over synchronised frames.

A frame is (vehicle time [s], inputs [de rad, throttle or thrust N], observations [7],
NaN where a channel is missing). Each filter's belief is kept in a lane (filters.Lane),
stepped by the runner (passes.py); the restarts that make the zero start work re-run the
frames from a better linearisation point (restarts.py); the time histories are kept as
the run goes (history.py); the result is the narrow record the view, the report and the
metrics read (results.py). This module is the estimation package's face: the names the
rest of the package uses are exported here.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from gcs_estimator.arrays import BoolArray, FloatArray
from gcs_estimator.config import AircraftConfig
from gcs_estimator.estimation.delay import InputDelay
from gcs_estimator.estimation.filters import core
from gcs_estimator.estimation.filters.core import FILTER_KINDS, Backend, FilterKind
from gcs_estimator.estimation.history import Histories, StepOutput, Track
from gcs_estimator.estimation.noise import NoiseReading, scaled
from gcs_estimator.estimation.passes import ROWS_FRAMES, Lanes, Runner, Tunings
from gcs_estimator.estimation.restarts import Restarts, Swap
from gcs_estimator.estimation.results import EstimatorResult, FilterResult, Snapshot
from gcs_estimator.estimation.segments import Limits, Pieces
from gcs_estimator.model.aircraft import build_model
from gcs_estimator.model.channels import BANK_INPUT, bank_of, pad_observations

__all__ = [
    "FILTER_KINDS",
    "Backend",
    "Estimator",
    "EstimatorResult",
    "FilterKind",
    "FilterResult",
    "NoiseReading",
    "Snapshot",
    "StepOutput",
    "Track",
]


def observed(u: FloatArray, y: FloatArray, bank_limit_deg: float) -> tuple[FloatArray, bool]:
    """A frame's observations as the filters take them: N_OBS wide (pad_observations),
    and none where the bank is beyond bank_limit_deg (decision 0048); and whether it
    was."""
    y = pad_observations(np.array(y, float))
    beyond = abs(u[BANK_INPUT]) > math.radians(bank_limit_deg)
    if beyond:
        y[:] = np.nan
    return y, bool(beyond)


def observed_rows(
    u: FloatArray, y: FloatArray, bank_limit_deg: float
) -> tuple[FloatArray, BoolArray]:
    """observed() of each frame (rows of u and y) at once: the observations, and which
    frames were beyond the bank limit."""
    y = pad_observations(np.array(y, float))
    beyond = np.abs(u[:, BANK_INPUT]) > math.radians(bank_limit_deg)
    y[beyond] = np.nan
    return y, beyond


# Over 200 lines: the estimation package's one face to the session (admit, step, the
# restarts' swap, segments and flights, the counters: gaps, out of order, banked out,
# results); each part's work lives in its own module (passes, restarts, segments,
# history, results) and is only delegated to here.
class Estimator:
    """EKF and IEKF side by side for one vehicle: the live pass, the restarts that replace
    it, and its history."""

    def __init__(
        self,
        config: AircraftConfig,
        backend: Backend = "fast",
        keep_history: bool = True,
        noise_scale: FloatArray | None = None,
        peers_restarting: Callable[[], int] | None = None,
        gate: Limits | None = None,
    ) -> None:
        """noise_scale: each channel's measurement variance multiplied by this in every
        pass, after the noise is read from the data (the structure check's re-runs:
        weighting.py); None: as configured and read. peers_restarting: how many other
        vehicles of the station have a restart under way (restarts.GRACE_PER_PEER).
        gate: the segments' limits judged frame by frame (live: segments.Gate); None:
        every frame admitted is used (a recording's segments are chosen before)."""
        self.config = config
        self.model = build_model(config)
        self.keep_history = keep_history
        self.backend: Backend = backend
        self.noise_scale = None if noise_scale is None else np.asarray(noise_scale, float)
        self.tunings: Tunings = scaled(
            {k: core.tuning_of(config, self.model, k) for k in FILTER_KINDS}, self.noise_scale
        )
        """The live pass's settings."""
        self.states: Lanes = dict.fromkeys(FILTER_KINDS)
        """The live pass."""
        self.runner = Runner(self.model, backend)
        self.health = self.runner.health
        self.restarts = Restarts(
            config.filter, self.runner, self.tunings, self.noise_scale, peers_restarting
        )
        self.delay = InputDelay(config.data.input_delay_s)
        """The inputs taken [data] input_delay_s later (decision 0044)."""
        self.history = Histories(self.model.n, keep_history)
        self.frame_history = self.history.frames
        self.frames = 0
        self._t0 = math.nan
        self._t_last = -math.inf
        self.gaps = 0
        """Frames after more than core.MAX_GAP_S without one: the flight states
        started afresh there."""
        self.out_of_order = 0
        """Frames at or before the previous frame's time: skipped."""
        self.banked_out = 0  # frames beyond the bank limit: not in the update (0048)
        self.final_pass_from = 0
        """The frame at which the pass now running took over (its history row is that
        pass's output)."""
        self.pieces = Pieces(gate)
        """Where the flight states start afresh: segments, flights (decision 0050)."""

    @property
    def names(self) -> tuple[str, ...]:
        return self.model.names

    def replay_final_pass(
        self,
        source: Estimator,
        t: FloatArray,
        u: FloatArray,
        y: FloatArray,
        kinds: Sequence[FilterKind] = FILTER_KINDS,
    ) -> None:
        """The final pass of `source` (the pass that ran to its end) again, over its frames
        (t, u, y as its history holds them), with this estimator's noise_scale on that
        pass's settings: from the same start, the flight states started afresh after every
        gap longer than core.MAX_GAP_S as the run did (Runner.replay). With no
        noise_scale it ends where source did. Keeps no history of its own. Both filters,
        or only those in `kinds` (the others' states left as they are)."""
        self.runner.starts = dict(source.runner.starts)
        self.tunings = scaled(dict(source.tunings), self.noise_scale)
        self.runner.replay(
            self.states, t, u, y, self.tunings, core.MAX_GAP_S, source.pieces.fresh_frames, kinds
        )
        self.frames += len(t)

    def admit(self, t: float, y: FloatArray, phi: float = math.nan) -> bool:
        """Whether a frame at vehicle time t (bank phi [rad] where the frame carries it)
        can be processed next. A frame not after the last one is skipped; one the live
        gate leaves out (segments.Gate) too; one after a gap longer than core.MAX_GAP_S
        rebases the flight states there, so no prediction spans more than MAX_GAP_S (a
        far-future time never makes the filters integrate for hours)."""
        if not t > self._t_last:
            self.out_of_order += 1
            return False
        if not self.pieces.admit(t, float(y[0]), self.frames, phi):
            return False
        if self.frames and t - self._t_last > core.MAX_GAP_S and not self.pieces.pending:
            self.gaps += 1
            self.rebase(t, y)
        return True

    def start_segment(self) -> None:
        """The next frame begins a segment after frames left out (segments.py): the flight
        states start afresh from its measurements, as at a frame whose input is a guess,
        the coefficients and their covariance carried; the restarts under way keep their
        frames (their re-run starts afresh there too) and the time between is no gap."""
        self.pieces.pending = self.frames > 0

    def begin_flight(self, name: str) -> None:
        """The next frame is a new flight's first (several logs of one airframe): its flight
        states start afresh, the coefficients carried, as at a segment (start_segment)."""
        self.pieces.flights.append((name, self.frames))
        self.start_segment()

    def step(
        self, t: float, u: FloatArray, y: FloatArray, inputs_known: bool = True
    ) -> dict[FilterKind, StepOutput]:
        """Advance both filters to vehicle time t [s] with inputs u and observations y.

        inputs_known=False: the input of this frame (or of the one before) is a guess (its
        sample was lost while the input changed). The state predicted with it is not
        trusted: the flight states start again from this frame's measurements, the
        coefficients and their uncertainty are kept, and the observations are not used
        for an update (they already gave the flight states).

        At each configured restart time both filters begin a re-run of the buffered frames
        (restarts.py), which takes the live pass's place once it has caught up: the
        outputs returned are then those of the re-run at this frame. Every step is the
        same as a re-run done at once would make, so the estimates are too. The history
        keeps what was known live at each time but for the frame of the swap.
        """
        if self.frames == 0:
            self._t0 = t
        self._t_last = t
        if self.pieces.take(self.frames):
            inputs_known = False
            self.delay.restart()
        u = self.delay.at(t, self.model.inputs(u))
        y, beyond = observed(u, y, self.config.filter.bank_limit_deg)
        self.banked_out += beyond
        self.restarts.keep((t, u, y, inputs_known))
        outs = self.runner.frame(self.states, t, u, y, inputs_known, self.tunings)
        self.frames += 1
        self.history.append(t, u, y, outs)
        swap = self.restarts.after_frame(t - self._t0, self.states)
        if swap is not None:
            outs = self._take(swap)
        return outs

    def steps(self, t: FloatArray, u: FloatArray, y: FloatArray) -> dict[FilterKind, StepOutput]:
        """Frames in order (t [m], u [m x k] as a frame's inputs, y [m x 7]), each with its
        inputs known and none a clock reset or a segment's or flight's start (a session's
        frames between such marks), as admit and step would take them one by one: each
        run of frames at which those would do nothing but step the filters (plain_run) in
        one compiled call per filter, every other frame through admit and step. The
        outputs at the last frame stepped (empty if none)."""
        outs: dict[FilterKind, StepOutput] = {}
        i, m = 0, len(t)
        while i < m:
            end = i + self.plain_run(t[i : i + ROWS_FRAMES])
            if end > i:
                outs = self._run(t[i:end], u[i:end], y[i:end])
                i = end
                continue
            ti = float(t[i])
            if self.admit(ti, y[i], bank_of(u[i])):
                outs = self.step(ti, u[i], y[i])
            i += 1
        return outs

    def plain_run(self, t: FloatArray) -> int:
        """How many of the frames at times t, from the first, admit and step would take
        with nothing to do but step the filters: the live gate off, no segment pending, both
        lanes begun, no restart under way or due at them, each frame after the one before
        and within core.MAX_GAP_S of it (admit's and after_frame's own tests, on the same
        values)."""
        if self.pieces.gate is not None or self.pieces.pending or self.restarts.under_way:
            return 0
        if any(lane is None for lane in self.states.values()):
            return 0
        before = np.empty(len(t))
        before[0] = self._t_last
        before[1:] = t[:-1]
        plain = (t > before) & ~(t - before > core.MAX_GAP_S)
        if self.restarts.pending:
            due = self.config.filter.restart_times_s[self.restarts.done]
            plain &= ~(t - self._t0 >= due)
        if plain.all():
            return len(t)
        return int(np.argmin(plain))

    def _run(self, t: FloatArray, u: FloatArray, y: FloatArray) -> dict[FilterKind, StepOutput]:
        """A plain run of frames (plain_run) through both filters: what step does frame by
        frame, on all of them at once (the inputs and observations as the filters take
        them, the restarts' buffer, each filter's steps in one compiled call keeping every
        frame's outputs, the history)."""
        inputs = self.model.inputs_of(u)
        if self.delay.delay_s > 0.0:
            inputs = np.array(
                [self.delay.at(float(tk), uk) for tk, uk in zip(t, inputs, strict=True)]
            )
        obs, beyond = observed_rows(inputs, y, self.config.filter.bank_limit_deg)
        self.banked_out += int(np.count_nonzero(beyond))
        if self.restarts.pending:
            times = t.tolist()
            for k in range(len(times)):
                self.restarts.keep((times[k], inputs[k], obs[k], True))
        rows = {
            kind: self.runner.rows(kind, self.states, t, inputs, obs, self.tunings[kind])
            for kind in FILTER_KINDS
        }
        self.frames += len(t)
        self._t_last = float(t[-1])
        self.history.extend(t, inputs, obs, rows)
        return {kind: StepOutput(r[-1].copy(), self.model.n) for kind, r in rows.items()}

    def finish_restarts(self) -> None:
        """Complete a re-run still under way (the end of the data came first)."""
        swap = self.restarts.finish()
        if swap is not None:
            self._take(swap)

    def _take(self, swap: Swap) -> dict[FilterKind, StepOutput]:
        """The re-run becomes the live pass at the newest frame, whose history row
        becomes the re-run's: its outputs there."""
        self.states = swap.lanes
        self.tunings = swap.tunings
        self.final_pass_from = max(self.frames - 1, 0)
        self.history.set_last(swap.outs)
        return swap.outs

    def rebase(self, t: float, y: FloatArray) -> None:
        """The vehicle clock restarted: continue the coefficient estimates on a new time
        base. Restarts still pending are dropped (their frames span two time bases)."""
        self._t_last = -math.inf
        for kind, lane in self.states.items():
            if lane is not None:
                lane.load(core.rebase(lane.state, self.model, self.tunings[kind], t, y))
        self.restarts.drop()
        self.delay.restart()

    def snapshot(self) -> dict[FilterKind, Snapshot]:
        """Current coefficient estimates and sigmas per filter (empty before data)."""
        coef = self.model.coefficients
        out: dict[FilterKind, Snapshot] = {}
        for kind, s in self.states.items():
            if s is not None:
                gust = self.gust_level(kind)
                out[kind] = Snapshot(s.x[coef].copy(), np.sqrt(np.diag(s.P))[coef], gust)
        return out

    def gust_level(self, kind: FilterKind) -> float:
        """The turbulence level a filter applies now [m/s] (NaN before data)."""
        s = self.states.get(kind)
        if s is None:
            return math.nan
        tn = self.tunings[kind]
        return math.sqrt(s.gust.applied(tn.detection2))

    @property
    def history_rows(self) -> int:
        """Frames in the history (0 when none is kept)."""
        return self.history.rows

    def tracks(self) -> dict[FilterKind, Track]:
        """Each filter's history so far (mapped from disk, not copied, once it is long;
        empty when none is kept). Every row but the newest is final: only the newest is
        replaced, when a re-run takes over at the end of the data (finish_restarts)."""
        kinds = [kind for kind, s in self.states.items() if s is not None]
        return self.history.tracks(kinds, self.model)

    def result(self) -> EstimatorResult:
        """The run so far, tracks included (reads the whole history: call it once)."""
        tracks = self.tracks()
        filters = {
            # lane.state: arrays of its own (the lane moves on with the next frame)
            kind: FilterResult.of(
                kind,
                lane.state,
                self.tunings[kind],
                self.model,
                self.health[kind],
                tracks.get(kind),
            )
            for kind, lane in self.states.items()
            if lane is not None
        }
        warm = self.restarts.warm_start
        return EstimatorResult(
            config=self.config,
            names=self.names,
            frames=self.frames,
            restarts_done=self.restarts.done,
            warm_start=None if warm is None else warm.beta,
            filters=filters,
            bias_names=self.model.bias_names,
            warm_start_samples=None if warm is None else warm.samples,
            warm_start_frames=0 if warm is None else warm.frames,
            gaps=self.gaps,
            frames_out_of_order=self.out_of_order,
            frames_banked_out=self.banked_out,
            final_pass_from=self.final_pass_from,
            state_names=self.model.layout.names,
            measurement_sigma=tuple(float(v) for v in np.sqrt(np.diag(self.tunings["EKF"].R))),
            noise_reading=self.restarts.noise_reading,
            segments=self.pieces.report(self.frames),
            fresh_frames=tuple(self.pieces.fresh_frames),
            flights=flight_parts(self),
        )


def flight_parts(est: Estimator) -> tuple[dict[str, Any], ...]:
    """Each flight's part in the estimate, where the run held several: the final pass
    replayed flight by flight from its start (Runner.replay, the flight states afresh
    at every flight and segment), the coefficients and their sigma after each, and the
    share of each coefficient's variance the flight removed (1 - after^2 / before^2,
    before: the sigma the pass started from, then the previous flight's). Empty with
    one flight, or without a history."""
    flights = est.pieces.flights
    if len(flights) < 2 or not est.history_rows:
        return ()
    t, u, y = est.frame_history.arrays()
    runner = Runner(est.model, est.backend)
    runner.starts = dict(est.runner.starts)
    lanes: Lanes = dict.fromkeys(FILTER_KINDS)
    coef = est.model.coefficients
    before = {k: _start_sigma(est, k) for k in FILTER_KINDS}
    bounds = [first for _, first in flights] + [len(t)]
    out: list[dict[str, Any]] = []
    for j, (name, first) in enumerate(flights):
        end = bounds[j + 1]
        fresh = [i - first for i in est.pieces.fresh_frames if first <= i < end]
        part = slice(first, end)
        runner.replay(lanes, t[part], u[part], y[part], est.tunings, core.MAX_GAP_S, fresh)
        filters: dict[str, Any] = {}
        for kind, lane in lanes.items():
            if lane is None:
                continue
            sigma = np.sqrt(np.diag(lane.P))[coef]
            removed = 1.0 - sigma**2 / np.maximum(before[kind], 1e-300) ** 2
            filters[kind] = {
                "coefficients": dict(zip(est.names, lane.x[coef].tolist(), strict=True)),
                "sigma": dict(zip(est.names, sigma.tolist(), strict=True)),
                "variance_removed": dict(zip(est.names, removed.tolist(), strict=True)),
            }
            before[kind] = sigma
        out.append({"flight": name, "frames": end - first, "filters": filters})
    return tuple(out)


def _start_sigma(est: Estimator, kind: FilterKind) -> FloatArray:
    """The coefficients' sigma the final pass of filter `kind` started from."""
    start = est.runner.starts[kind].sigma
    if start is not None:
        return np.asarray(start, float)
    return np.asarray(est.tunings[kind].prior_sigma[est.model.coefficients], float)
