"""Online estimation of one aircraft: EKF and IEKF side by side over synchronised frames.

A frame is (vehicle time [s], inputs [de rad, throttle or thrust N], observations [7],
NaN where a channel is missing). Each filter's belief is kept in a lane (filters.Lane)
and advanced by the step contract; this module adds what makes the zero start work (restarts
from a better linearisation point), the time histories, and the narrow result type that
the view, the report and the metrics read.
"""

from __future__ import annotations

import math
import os
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, BinaryIO, NamedTuple

import numpy as np

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import AircraftConfig
from gcs_estimator.estimation.filters import core
from gcs_estimator.estimation.filters.core import (
    FILTER_KINDS,
    Backend,
    FilterKind,
    StepInfo,
    Tuning,
)
from gcs_estimator.estimation.filters.lane import Lane
from gcs_estimator.model.aircraft import Model, build_model
from gcs_estimator.model.channels import N_INPUTS, N_OBS

if TYPE_CHECKING:
    from gcs_estimator.runtime.session import VehicleResult

__all__ = ["FILTER_KINDS", "Backend", "Estimator", "EstimatorResult", "FilterKind", "StepOutput"]


class StepOutput:
    """One filter's output at one frame: the augmented state estimate and the step's
    report (sigma, NIS, innovations, gust level), held as the row the step wrote
    (filters.core.output_row's layout), its parts read from it when asked."""

    __slots__ = ("_info", "n", "row")

    def __init__(self, row: FloatArray, n: int) -> None:
        self.row = row
        """The outputs as one row (nobody writes to it after the step)."""
        self.n = n
        self._info: StepInfo | None = None

    @staticmethod
    def of(x: FloatArray, info: StepInfo) -> StepOutput:
        return StepOutput(core.output_row(x, info), x.shape[0])

    @property
    def x(self) -> FloatArray:
        return self.row[: self.n]

    @property
    def info(self) -> StepInfo:
        if self._info is None:
            self._info = core.info_of_row(self.row, self.n)
        return self._info


class Snapshot(NamedTuple):
    """A filter's current coefficient estimates (cheap: no history is read)."""

    coefficients: FloatArray
    sigma: FloatArray
    gust_sigma: float


@dataclass
class Health:
    """What went wrong in one filter over all passes (each step reports it)."""

    failed_updates: int = 0
    """Updates skipped because an innovation covariance was not positive definite."""
    covariance_repairs: int = 0
    """Times P lost positive definiteness to rounding and was repaired."""
    divergences: int = 0
    """Times the belief went non-finite and the filter started again from its prior."""

    def add(self, failed: int, repaired: int, diverged: int) -> None:
        self.failed_updates += failed
        self.covariance_repairs += repaired
        self.divergences += diverged


class Rows:
    """Rows appended to a 2-D array kept on disk: the newest HISTORY_CHUNK rows in memory,
    the rest written to unnamed temporary files (gone with the process), so a long
    flight's history costs disk, not memory.

    A row may be made of column groups (widths): in memory a frame's row is one row, so
    appending it is one write; on disk each group has its own file, so reading one group
    back (arrays(), mapped read-only) touches only its own pages."""

    def __init__(self, width: int | Sequence[int], dtype: type = np.float64) -> None:
        widths = (width,) if isinstance(width, int) else tuple(width)
        self._edges = np.concatenate([[0], np.cumsum(widths)]).astype(int).tolist()
        self._buf: np.ndarray = np.empty((HISTORY_CHUNK, self._edges[-1]), dtype)
        self._nbuf = 0
        self._flushed = 0
        self._files: list[BinaryIO] = []

    @property
    def n(self) -> int:
        return self._flushed + self._nbuf

    def append(self, row: FloatArray | Sequence[float]) -> None:
        self.claim()[:] = row

    def claim(self) -> np.ndarray:
        """A new row at the end, to be filled in place (its values undefined until then)."""
        if self._nbuf == HISTORY_CHUNK:
            self._write(self._nbuf)
            self._flushed += self._nbuf
            self._nbuf = 0
        self._nbuf += 1
        row: np.ndarray = self._buf[self._nbuf - 1]
        return row

    def last(self) -> np.ndarray:
        """The newest row (always still in memory), to be replaced in place."""
        row: np.ndarray = self._buf[self._nbuf - 1]
        return row

    def _groups(self) -> list[tuple[int, int]]:
        return list(zip(self._edges[:-1], self._edges[1:], strict=True))

    def _write(self, rows: int) -> None:
        """The rows in memory to the files, after the rows already there."""
        if not self._files:
            self._files = [
                tempfile.TemporaryFile(prefix="gcs-history-")  # noqa: SIM115
                for _ in self._groups()
            ]
        item = self._buf.itemsize
        for f, (a, b) in zip(self._files, self._groups(), strict=True):
            block = np.ascontiguousarray(self._buf[:rows, a:b])
            os.pwrite(f.fileno(), block.tobytes(), self._flushed * (b - a) * item)

    def arrays(self) -> list[np.ndarray]:
        """The rows so far, one array per column group: copies while they fit in memory,
        else the files mapped read-only (the rows in memory written to them first)."""
        if self._flushed == 0:
            return [self._buf[: self._nbuf, a:b].copy() for a, b in self._groups()]
        self._write(self._nbuf)
        return [
            np.memmap(f, self._buf.dtype, mode="r", shape=(self.n, b - a))
            for f, (a, b) in zip(self._files, self._groups(), strict=True)
        ]

    def array(self) -> np.ndarray:
        """arrays() of a single group."""
        (out,) = self.arrays()
        return out


BLOCK_MIN_FRAMES = 4
"""Re-run frames worth one compiled call per filter (fewer: a call per frame)."""

HISTORY_CHUNK = 4096
"""Rows of a history kept in memory before they go to disk."""


class FrameHistory:
    """Per-frame times, inputs and observations, shared by both filters: one row of
    [t, u, y] per frame."""

    def __init__(self) -> None:
        self.rows = Rows((1, N_INPUTS, N_OBS))

    def append(self, t: float, u: FloatArray, y: FloatArray) -> None:
        row = self.rows.claim()
        row[0] = t
        row[1 : 1 + N_INPUTS] = u
        row[1 + N_INPUTS :] = y

    def arrays(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(t [N], u [N x N_INPUTS], y [N x N_OBS])."""
        t, u, y = self.rows.arrays()
        return t[:, 0], u, y


HISTORY_DTYPE = np.float32
"""A filter's per-frame outputs are kept to 7 significant digits: they are for plots,
convergence times and the history file, never fed back (the filter's own state is
float64). Half the disk, and half the pages the end of a run maps to summarise them."""


class History:
    """Per-frame outputs of one filter, in frame order: one row per frame of
    [x (n), sigma (n), NIS, channels used, gust sigma, its average over the pass,
    innovations (7), their sigmas (7)],
    so that a frame costs one row, not one per quantity (on disk, one file per group)."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.rows = Rows((n, n, 4, N_OBS, N_OBS), HISTORY_DTYPE)

    def _fill(self, row: np.ndarray, out: StepOutput) -> None:
        # The step's row begins with these columns in this order (core.output_row).
        row[:] = out.row[: row.shape[0]]

    def append(self, out: StepOutput) -> None:
        self._fill(self.rows.claim(), out)

    def set_last(self, out: StepOutput) -> None:
        self._fill(self.rows.last(), out)

    def columns(self) -> dict[str, np.ndarray]:
        """The rows so far as named views: x, sigma, nis, n_used, gust_sigma,
        gust_pass_sigma, innovation, innovation_sigma."""
        x, sigma, scalars, innovation, innovation_sigma = self.rows.arrays()
        return {
            "x": x,
            "sigma": sigma,
            "nis": scalars[:, 0],
            "n_used": scalars[:, 1],
            "gust_sigma": scalars[:, 2],
            "gust_pass_sigma": scalars[:, 3],
            "innovation": innovation,
            "innovation_sigma": innovation_sigma,
        }


@dataclass(frozen=True)
class Track:
    """Frozen arrays of one filter's run: N frames, n augmented states, p coefficients."""

    t: FloatArray
    x: FloatArray
    """[N x n]."""
    sigma: FloatArray
    """[N x n]."""
    coefficients: FloatArray
    """[N x p], a view of x."""
    coefficient_sigma: FloatArray
    """[N x p], a view of sigma."""
    nis: FloatArray
    n_used: FloatArray
    innovation: FloatArray
    """[N x 7]."""
    innovation_sigma: FloatArray
    gust_sigma: FloatArray
    """Gust intensity the process noise assumed per frame [N], m/s."""
    gust_pass_sigma: FloatArray
    """Its average over the pass so far per frame [N], m/s (StepInfo.gust_pass_sigma)."""
    u: FloatArray
    """Inputs per frame [N x 3]: elevator, throttle or thrust, air density."""
    y: FloatArray
    """Observations per frame [N x 7], NaN where missing."""

    @staticmethod
    def of(h: History, frames: FrameHistory, model: Model) -> Track:
        c = h.columns()
        t, u, y = frames.arrays()
        x, sigma = c["x"], c["sigma"]
        return Track(
            t=t,
            x=x,
            sigma=sigma,
            coefficients=x[:, model.coefficients],
            coefficient_sigma=sigma[:, model.coefficients],
            nis=c["nis"],
            n_used=c["n_used"],
            innovation=c["innovation"],
            innovation_sigma=c["innovation_sigma"],
            gust_sigma=c["gust_sigma"],
            gust_pass_sigma=c["gust_pass_sigma"],
            u=u,
            y=y,
        )


class FilterResult(NamedTuple):
    """The end of one filter's run."""

    kind: FilterKind
    coefficients: FloatArray
    sigma: FloatArray
    covariance: FloatArray
    """Coefficient covariance [p x p]."""
    gust_sigma: float
    """Turbulence level (vertical gust sigma) the filter ended with [m/s]."""
    biases: FloatArray
    """Estimated sensor biases ([sensors] bias_states; empty when none) [SI]."""
    bias_sigma: FloatArray
    health: Health
    track: Track | None
    """Time histories (None when the estimator keeps none)."""
    gust_pass_sigma: float = 0.0
    """Turbulence level averaged over the final pass, information-weighted [m/s]
    (GustState.pass_average)."""
    gust_pass_z: float = math.nan
    """That average in its standard errors (GustState.pass_z; NaN: nothing measured, as
    with [filter.turbulence] adaptive = false)."""


class EstimatorResult(NamedTuple):
    """What a run produced: all the view, the report and the metrics need."""

    config: AircraftConfig
    names: tuple[str, ...]
    frames: int
    restarts_done: int
    warm_start: FloatArray | None
    """Equation-error coefficients of the first restart, when that is the warm start."""
    filters: dict[FilterKind, FilterResult]
    bias_names: tuple[str, ...] = ()
    """Names of the estimated sensor biases, e.g. ("q_bias",)."""
    warm_start_samples: tuple[int, int, int] | None = None
    """Frames the warm start fitted per axis (CD, CL, Cm), of `warm_start_frames`."""
    warm_start_frames: int = 0
    gaps: int = 0
    """Frames after which the flight states started afresh (filter.max_gap_s)."""
    frames_out_of_order: int = 0
    """Frames skipped because they were not after the previous one."""
    final_pass_from: int = 0
    """First frame whose history row is the final pass's (after the last restart's swap)."""
    state_names: tuple[str, ...] = ()
    """Every element of the augmented state, in order (flight states, gust states where
    modelled, coefficients, biases): the columns of a track's x and sigma."""
    measurement_sigma: tuple[float, ...] = ()
    """Measurement noise sigma per channel the final pass used (the config's, or the
    data's: [filter] measurement_noise)."""
    noise_reading: NoiseReading | None = None
    """Each channel's noise as read from the data (None: none read); with
    measurement_noise = "auto" the final pass used it only where it was clearly below the
    configured sigma (noise.reading_z)."""


class NoiseReading(NamedTuple):
    """Each channel's noise as a restart read it from the data
    (gcs_estimator/estimation/noise.py)."""

    sigma: tuple[float, ...]
    differences: tuple[int, ...]
    """Differences each channel's reading took (below noise.MIN_DIFFERENCES: none of its
    own, the configured sigma)."""


class _Start(NamedTuple):
    """How a filter's pass starts: coefficient mean and sigma, gust variance (None: the
    configured ones)."""

    coefficients: FloatArray | None = None
    sigma: FloatArray | None = None
    gust_var: float | None = None


class _Pending(NamedTuple):
    """A restart begun whose re-run has not started."""

    frames: int
    """Frames buffered when it began (the warm start fits those)."""
    means: dict[FilterKind, tuple[FloatArray, FloatArray]] | None
    """Each filter's coefficients and sigma to start from; None: the warm start's."""
    gust: dict[FilterKind, float | None]
    """Each filter's gust variance to start from (None: the configured)."""


class Estimator:
    """EKF and IEKF side by side for one vehicle; the place that owns the filter passes."""

    def __init__(
        self,
        config: AircraftConfig,
        backend: Backend = "fast",
        keep_history: bool = True,
        noise_scale: FloatArray | None = None,
        peers_restarting: Callable[[], int] | None = None,
    ) -> None:
        self.config = config
        self.peers_restarting = peers_restarting
        """How many other vehicles of the station have a restart under way (Session);
        each adds filter.restart_grace_per_peer frames to a restart's grace. None: a
        vehicle on its own."""
        self.model = build_model(config)
        self.keep_history = keep_history
        self.backend: Backend = backend
        self._blocks = backend == "fast"
        """Many frames of a re-run in one compiled call (Lane.block); else one at a
        time (the reference backend has no compiled calls)."""
        self.noise_scale = None if noise_scale is None else np.asarray(noise_scale, float)
        """Each channel's measurement variance multiplied by this in every pass, after
        the noise is read from the data (the structure check's re-runs: weighting.py);
        None: as configured and read."""
        self.tunings: dict[FilterKind, Tuning] = self._scaled(
            {k: core.tuning_of(config, self.model, k) for k in FILTER_KINDS}
        )
        self._rerun_tunings = self.tunings
        """The settings of the re-run under way (measurement noise from the data)."""
        self.noise_reading: NoiseReading | None = None
        """Each channel's noise as read from the data (None: none read)."""
        self.states: dict[FilterKind, Lane | None] = dict.fromkeys(FILTER_KINDS)
        self.health = {k: Health() for k in FILTER_KINDS}
        self.histories = {k: History(self.model.n) for k in FILTER_KINDS}
        self.frame_history = FrameHistory()
        self._starts = {k: _Start() for k in FILTER_KINDS}
        self.frames = 0
        self.restarts_done = 0
        self.warm_start: FloatArray | None = None
        self._warm_samples: tuple[int, int, int] | None = None
        self._warm_frames = 0
        self._buffer: list[tuple[float, FloatArray, FloatArray, bool]] = []
        self._t0 = math.nan
        self._t_last = -math.inf
        self._pending: _Pending | None = None
        """A restart begun whose re-run has not started yet (its warm start not fitted)."""
        self._since_begin = 0
        """Frames since the restart under way began, that one included."""
        self._grace = 0
        """Frames of grace of the restart under way (set where it began)."""
        self.worked_ahead = 0
        """Restart work done in idle time (work_ahead): frames, and 1 per warm start."""
        self._rerun: dict[FilterKind, Lane | None] | None = None
        """The re-run of a restart while it catches up (None: none under way)."""
        self._rerun_pos = 0
        self.gaps = 0
        """Frames after more than filter.max_gap_s without one: the flight states
        started afresh there."""
        self.out_of_order = 0
        """Frames at or before the previous frame's time: skipped."""
        self.final_pass_from = 0
        """The frame at which the pass now running took over (its history row is that
        pass's output)."""

    @property
    def names(self) -> tuple[str, ...]:
        return self.model.names

    def _scaled(self, tunings: dict[FilterKind, Tuning]) -> dict[FilterKind, Tuning]:
        """The tunings with each channel's measurement variance times noise_scale."""
        if self.noise_scale is None:
            return tunings
        root = np.sqrt(self.noise_scale)
        return {k: tn._replace(R=tn.R * np.outer(root, root)) for k, tn in tunings.items()}

    def replay_final_pass(
        self, source: Estimator, t: FloatArray, u: FloatArray, y: FloatArray
    ) -> None:
        """The final pass of `source` (the pass that ran to its end) again, over its frames
        (t, u, y as its history holds them), with this estimator's noise_scale on that
        pass's settings: from the same start, the flight states started afresh after every
        gap longer than filter.max_gap_s as the run did, each run of frames in one compiled
        call per filter where the backend has blocks (the same steps as frame by frame, bit
        for bit: docs/decisions/0013). With no noise_scale it ends where source did. Keeps
        no history of its own."""
        self._starts = dict(source._starts)
        self.tunings = self._scaled(dict(source.tunings))
        gap = self.config.filter.max_gap_s
        i, n = 0, len(t)
        while i < n:
            end = i + 1
            while end < n and t[end] - t[end - 1] <= gap:
                end += 1
            frames = [
                (float(t[j]), self.model.inputs(u[j]), np.array(y[j], float), True)
                for j in range(i, end)
            ]
            for kind in FILTER_KINDS:
                lane = self.states[kind]
                if lane is not None:
                    lane.load(
                        core.rebase(
                            lane.state, self.model, self.tunings[kind], frames[0][0], frames[0][2]
                        )
                    )
                if not self._blocks:  # a backend without blocks: frame by frame
                    for frame in frames:
                        self._advance_one(kind, self.states, *frame, self.tunings[kind])
                else:
                    self._advance_block(kind, self.states, frames, self.tunings[kind])
            self.frames += end - i
            i = end

    @property
    def restarts_pending(self) -> bool:
        return self.restarts_done < len(self.config.filter.restart_times_s)

    def admit(self, t: float, y: FloatArray) -> bool:
        """Whether a frame at vehicle time t can be processed next. A frame not after the
        last one is skipped; one after a gap longer than filter.max_gap_s rebases the
        flight states there, so no prediction spans more than max_gap_s (a far-future
        time never makes the filters integrate for hours)."""
        if not t > self._t_last:
            self.out_of_order += 1
            return False
        if self.frames and t - self._t_last > self.config.filter.max_gap_s:
            self.gaps += 1
            self.rebase(t, y)
        return True

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
        from the start (_begin_restart). The re-run goes on beside the live pass, at
        least filter.restart_frames_per_step frames per new frame after
        restart_grace_frames (more when work_ahead runs it in idle time), so that no
        frame's call waits for the whole re-run; when the schedule has caught up, it
        takes the live pass's place, and the outputs returned are those of the re-run at
        this frame. Every step is the same as a re-run done at once would make, so the
        estimates are too. The history keeps what was known live at each time but for
        the frame of the swap.
        """
        if self.frames == 0:
            self._t0 = t
        self._t_last = t
        u = self.model.inputs(u)
        y = np.array(y, float)
        if self.restarts_pending:
            self._buffer.append((t, u, y, inputs_known))
        outs = self._advance(self.states, t, u, y, inputs_known)
        self.frames += 1
        if self.keep_history:
            self.frame_history.append(t, u, y)
            for kind, out in outs.items():
                self.histories[kind].append(out)
        restarts = self.config.filter.restart_times_s
        if (
            not self.restart_under_way
            and self.restarts_pending
            and t - self._t0 >= restarts[self.restarts_done]
        ):
            self._begin_restart()
        if self.restart_under_way:
            self._since_begin += 1
            swapped = self._follow_schedule()
            if swapped is not None:
                outs = swapped
                if self.keep_history:
                    for kind, out in outs.items():
                        self.histories[kind].set_last(out)
        return outs

    @property
    def restart_under_way(self) -> bool:
        return self._pending is not None or self._rerun is not None

    def _follow_schedule(self) -> dict[FilterKind, StepOutput] | None:
        """The re-run's progress this frame must have made, whatever was done ahead in
        idle time (work_ahead): restart_frames_per_step frames per frame once the grace
        has passed (restart_grace_frames, plus restart_grace_per_peer for each other
        vehicle restarting when this restart began; 0: all of it now). When that reaches
        the newest frame the re-run takes over: at a frame fixed by the data (the link's,
        every vehicle's, in the order they came) and the settings alone, never by how
        busy the machine was, so a replay swaps where the live run did."""
        ft = self.config.filter
        n = len(self._buffer)
        per = ft.restart_frames_per_step
        due = n if per <= 0 else min(n, max(0, self._since_begin - self._grace) * per)
        if due == 0:
            return None
        outs = self._advance_rerun(due)
        if due < n:
            return None
        return self._swap(outs)

    def work_ahead(self, max_frames: int) -> int:
        """Do some of a restart's work before the schedule asks for it (from idle time):
        the warm start's fit, then up to max_frames buffered frames of the re-run. Never
        takes over (see _follow_schedule). Returns the work done (frames; the fit counts
        one); 0: nothing to do."""
        if self._pending is not None:
            self._start_rerun()
            self.worked_ahead += 1
            return 1
        if self._rerun is None:
            return 0
        pos = self._rerun_pos
        self._advance_rerun(min(len(self._buffer), pos + max_frames))
        self.worked_ahead += self._rerun_pos - pos
        return self._rerun_pos - pos

    def finish_restarts(self) -> None:
        """Complete a re-run still under way (the end of the data came first)."""
        if self.restart_under_way:
            swapped = self._swap(self._advance_rerun(len(self._buffer)))
            if swapped and self.keep_history:
                for kind, out in swapped.items():
                    self.histories[kind].set_last(out)

    def _advance(
        self,
        states: dict[FilterKind, Lane | None],
        t: float,
        u: FloatArray,
        y: FloatArray,
        inputs_known: bool = True,
        tunings: dict[FilterKind, Tuning] | None = None,
    ) -> dict[FilterKind, StepOutput]:
        """One frame through both filters of a pass (the live pass's settings unless
        given)."""
        tunings = self.tunings if tunings is None else tunings
        return {
            kind: self._advance_one(kind, states, t, u, y, inputs_known, tunings[kind])
            for kind in FILTER_KINDS
        }

    def _advance_one(
        self,
        kind: FilterKind,
        states: dict[FilterKind, Lane | None],
        t: float,
        u: FloatArray,
        y: FloatArray,
        inputs_known: bool,
        tuning: Tuning,
    ) -> StepOutput:
        """One frame through one filter of a pass."""
        lane = states[kind]
        if lane is None:
            start = core.initial_state(self.model, tuning, t, u, y, *self._starts[kind])
            lane = states[kind] = Lane(start, self.backend)
        elif not inputs_known:
            lane.load(core.rebase(lane.state, self.model, tuning, t, y))
        y_used = y if inputs_known else np.full_like(y, np.nan)
        row, status = lane.step(t, u, y_used, tuning, self.model)
        if status:
            self.health[kind].add(*core.flags_of_row(row, lane.n).tolist())
        return StepOutput(row, lane.n)

    def _advance_block(
        self,
        kind: FilterKind,
        states: dict[FilterKind, Lane | None],
        frames: Sequence[tuple[float, FloatArray, FloatArray, bool]],
        tuning: Tuning,
    ) -> StepOutput | None:
        """Frames through one filter of a pass, runs of them in one compiled call each
        (the same steps as _advance_one's, bit for bit): the output at the last frame.
        A pass's first frame and a frame whose inputs are a guess go through
        _advance_one; a step the contract must repair or restart is answered where it
        falls, as _advance_one's would be (Lane.block; docs/decisions/0013)."""
        ts = np.array([f[0] for f in frames])
        us = np.array([f[1] for f in frames])
        ys = np.array([f[2] for f in frames])
        known = [f[3] for f in frames]
        out: StepOutput | None = None
        i = 0
        while i < len(frames):
            lane = states[kind]
            end = i
            while end < len(frames) and known[end]:
                end += 1
            if lane is not None and end > i:
                row, counts = lane.block(ts[i:end], us[i:end], ys[i:end], tuning, self.model)
                self.health[kind].add(*counts)
                out = StepOutput(row, lane.n)
                i = end
                continue
            t, u, y, inputs_known = frames[i]
            out = self._advance_one(kind, states, t, u, y, inputs_known, tuning)
            i += 1
        return out

    def rebase(self, t: float, y: FloatArray) -> None:
        """The vehicle clock restarted: continue the coefficient estimates on a new time
        base. Restarts still pending are dropped (their frames span two time bases)."""
        self._t_last = -math.inf
        for kind, lane in self.states.items():
            if lane is not None:
                lane.load(core.rebase(lane.state, self.model, self.tunings[kind], t, y))
        if self.restarts_pending:
            self.restarts_done = len(self.config.filter.restart_times_s)
            self._buffer = []
            self._rerun = None
            self._pending = None

    def _advance_rerun(self, end: int) -> dict[FilterKind, StepOutput]:
        """Step the re-run through the buffered frames up to `end` (exclusive); its
        outputs at the last frame stepped (empty if none)."""
        if self._pending is not None:
            self._start_rerun()
        rerun = self._rerun
        assert rerun is not None
        outs: dict[FilterKind, StepOutput] = {}
        frames = self._buffer[self._rerun_pos : end]
        if not self._blocks or len(frames) < BLOCK_MIN_FRAMES:
            for t, u, y, known in frames:
                outs = self._advance(rerun, t, u, y, known, self._rerun_tunings)
        else:
            for kind in FILTER_KINDS:
                out = self._advance_block(kind, rerun, frames, self._rerun_tunings[kind])
                if out is not None:
                    outs[kind] = out
        self._rerun_pos = max(self._rerun_pos, end)
        return outs

    def _swap(self, outs: dict[FilterKind, StepOutput]) -> dict[FilterKind, StepOutput]:
        """The re-run, caught up with the newest frame, becomes the live pass; its
        outputs there."""
        assert self._rerun is not None and self._rerun_pos == len(self._buffer)
        self.states = self._rerun
        self.tunings = self._rerun_tunings
        self._rerun = None
        self.restarts_done += 1
        self.final_pass_from = max(self.frames - 1, 0)
        if not self.restarts_pending:
            self._buffer = []
        return outs

    def _begin_restart(self) -> None:
        """Begin a re-run of the buffered frames from a new linearisation point (see
        FilterTuning): take from the live pass what the re-run starts from, now; the
        warm start's fit, when there is one, waits for _start_rerun (idle time first)."""
        tuning = self.config.filter
        coef = self.model.coefficients
        warm = self.restarts_done == 0 and tuning.warm_start == "equation-error"
        means: dict[FilterKind, tuple[FloatArray, FloatArray]] | None = None
        if not warm:
            means = {
                k: (s.x[coef].copy(), np.sqrt(np.diag(s.P))[coef])
                for k, s in self.states.items()
                if s is not None
            }
        gust: dict[FilterKind, float | None] = {}
        for kind, state in self.states.items():
            assert state is not None
            # The first re-run starts at the turbulence level the zero-start pass ended
            # with: its average over the pass can come out near calm (early innovations
            # are smaller than the unknown coefficients make it predict), and a re-run
            # that starts as calm air in turbulence can lock onto wrong coefficients
            # (docs/decisions). Later re-runs start at the average of the pass before.
            gust[kind] = None
            if tuning.turbulence.adaptive:
                first = self.restarts_done == 0
                gust[kind] = max(state.gust.var, 0.0) if first else state.gust.pass_average()
        self._pending = _Pending(len(self._buffer), means, gust)
        self._since_begin = 0
        peers = self.peers_restarting() if self.peers_restarting is not None else 0
        self._grace = tuning.restart_grace_frames + tuning.restart_grace_per_peer * peers

    def _start_rerun(self) -> None:
        """The re-run's first states: from the warm start's fit to the frames buffered
        when the restart began, or from the live pass's estimates then."""
        pending = self._pending
        assert pending is not None
        tuning = self.config.filter
        self._rerun_tunings = self._noise_from_data(pending.frames)
        means = pending.means
        if means is None:
            from gcs_estimator.estimation.warmstart import equation_error

            frames = self._buffer[: pending.frames]
            t_b, u_b, y_b, _ = (np.array(col) for col in zip(*frames, strict=True))
            ws = equation_error(
                self.model,
                t_b,
                u_b,
                y_b,
                np.array(tuning.initial_coefficients),
                np.array(tuning.initial_sigma.coefficients),
            )
            self.warm_start = ws.beta
            self._warm_samples, self._warm_frames = ws.samples, len(t_b)
            means = {k: (ws.beta, ws.sigma) for k in FILTER_KINDS}
        p0 = np.array(tuning.initial_sigma.coefficients)
        for kind, (beta, sigma) in means.items():
            # A data-derived prior, widened so that reusing the early data in it weighs
            # little next to the data themselves; never wider than P0.
            self._starts[kind] = _Start(
                beta, np.minimum(p0, tuning.restart_sigma_inflation * sigma), pending.gust[kind]
            )
        self._pending = None
        self._rerun = dict.fromkeys(FILTER_KINDS)
        self._rerun_pos = 0

    def _noise_from_data(self, frames: int) -> dict[FilterKind, Tuning]:
        """The re-run's settings: each channel's noise read from the first `frames`
        buffered frames (gcs_estimator/estimation/noise.py), the configured sigma the fallback; with
        `measurement_noise = "data"` the reading throughout, with "auto" only where it is
        clearly below the configured sigma; with "config" the live pass's settings."""
        policy = self.config.filter.measurement_noise
        if policy == "config":
            return self.tunings
        from gcs_estimator.estimation.noise import CLEARLY, noise_from_differences, reading_z

        buffered = self._buffer[:frames]
        t = np.array([row[0] for row in buffered])
        y = np.array([row[2] for row in buffered]).reshape(len(buffered), -1)
        configured = np.array(self.config.filter.measurement_sigma, float)
        sigma, used = noise_from_differences(t, y, configured)
        self.noise_reading = NoiseReading(
            tuple(float(v) for v in sigma), tuple(int(n) for n in used)
        )
        if policy == "auto":
            sigma = np.where(reading_z(sigma, used, configured) < -CLEARLY, sigma, configured)
        R = np.diag(sigma**2)
        return self._scaled({k: tn._replace(R=R) for k, tn in self.tunings.items()})

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
        return self.frame_history.rows.n if self.keep_history else 0

    def tracks(self) -> dict[FilterKind, Track]:
        """Each filter's history so far (mapped from disk, not copied, once it is long;
        empty when none is kept). Every row but the newest is final: only the newest is
        replaced, when a re-run takes over at the end of the data (finish_restarts)."""
        if not self.keep_history:
            return {}
        return {
            kind: Track.of(self.histories[kind], self.frame_history, self.model)
            for kind, s in self.states.items()
            if s is not None
        }

    def result(self) -> EstimatorResult:
        """The run so far, tracks included (reads the whole history: call it once)."""
        coef = self.model.coefficients
        filters: dict[FilterKind, FilterResult] = {}
        tracks = self.tracks()
        for kind, lane in self.states.items():
            if lane is None:
                continue
            s = lane.state  # arrays of its own: the lane moves on with the next frame
            cov = s.P[coef, coef]
            biases = self.model.biases
            tn = self.tunings[kind]
            gust = s.gust.applied(tn.detection2)
            filters[kind] = FilterResult(
                kind,
                s.x[coef].copy(),
                np.sqrt(np.diag(cov)),
                cov,
                math.sqrt(gust),
                s.x[biases].copy(),
                np.sqrt(np.diag(s.P))[biases],
                self.health[kind],
                tracks.get(kind),
                math.sqrt(s.gust.pass_average()),
                s.gust.pass_z(),
            )
        return EstimatorResult(
            self.config,
            self.names,
            self.frames,
            self.restarts_done,
            self.warm_start,
            filters,
            self.model.bias_names,
            self._warm_samples,
            self._warm_frames,
            self.gaps,
            self.out_of_order,
            self.final_pass_from,
            self.model.layout.names,
            tuple(float(v) for v in np.sqrt(np.diag(self.tunings["EKF"].R))),
            self.noise_reading,
        )


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
    from gcs_estimator.runtime.session import RecordingSource, Session

    session = Session(config, backend=backend, keep_history=keep_history)
    session.run(RecordingSource(np.asarray(t_s, float), inputs, measurements))
    return session.results()[RecordingSource.SYSTEM_ID]
