"""Restarts: re-runs of the frames so far from a better linearisation point
(docs/decisions/0001), scheduled against the receive path.

At each of filter.restart_times_s both filters begin a re-run of the buffered frames from
the start: the first from the equation-error warm start's fit to those frames, later ones
from the live pass's estimates, the coefficient prior widened by SIGMA_INFLATION
(never wider than P0), the measurement noise read from the frames where
measurement_noise = "auto" (noise.py). The re-run goes on beside the live pass, at least
filter.restart_frames_per_step frames per new frame once its grace has passed (more
when idle time runs it: work_ahead), so that no frame's call waits for the whole re-run.
When the schedule has caught up with the newest frame, the re-run takes the live pass's
place (a Swap). The swap's frame is fixed by the data and the settings alone, never by how
busy the machine was, so a replay swaps where the live run did (docs/decisions/0013).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import FilterTuning
from gcs_estimator.estimation import noise
from gcs_estimator.estimation.filters.core import FILTER_KINDS, FilterKind
from gcs_estimator.estimation.history import StepOutput
from gcs_estimator.estimation.noise import NoiseReading
from gcs_estimator.estimation.passes import Frame, Lanes, Runner, Start, Tunings
from gcs_estimator.model.aircraft import Model

SIGMA_INFLATION = 10.0
"""A restart's prior sigma of each coefficient over the sigma of the estimate it starts
from: wide enough that re-using the early data in that prior weighs little next to the
data themselves (docs/decisions/0001)."""

GRACE_PER_PEER = 5
"""Frames a restart waits before the receive path must do its work, for each other
vehicle of the station whose restart is under way when it begins: vehicles restarting
together take turns, and 50 of them no longer stall the station (docs/decisions/0018)."""


class Swap(NamedTuple):
    """A re-run caught up with the newest frame: the pass that becomes the live one."""

    lanes: Lanes
    tunings: Tunings
    outs: dict[FilterKind, StepOutput]
    """Its outputs at the newest frame."""


class WarmStart(NamedTuple):
    """The equation-error fit the first restart started from (warmstart.py)."""

    beta: FloatArray
    samples: tuple[int, int, int]
    """Frames fitted per axis (CD, CL, Cm)."""
    frames: int
    """Frames offered to the fit."""


class _Pending(NamedTuple):
    """A restart begun whose re-run has not started."""

    frames: int
    """Frames buffered when it began (the warm start fits those)."""
    means: dict[FilterKind, tuple[FloatArray, FloatArray]] | None
    """Each filter's coefficients and sigma to start from; None: the warm start's."""
    gust: dict[FilterKind, float | None]
    """Each filter's gust variance to start from (None: the configured)."""


class Restarts:
    """One vehicle's restarts: the frames they re-run, the re-run under way and when it
    must progress and take over."""

    def __init__(
        self,
        settings: FilterTuning,
        runner: Runner,
        tunings: Tunings,
        noise_scale: FloatArray | None = None,
        peers_restarting: Callable[[], int] | None = None,
    ) -> None:
        self.settings = settings
        self.runner = runner
        self.tunings = tunings
        """The live pass's settings before any restart (measurement noise configured)."""
        self.noise_scale = noise_scale
        self.peers_restarting = peers_restarting
        """How many other vehicles of the station have a restart under way (the
        session's count); None: a vehicle on its own."""
        self.done = 0
        self.buffer: list[Frame] = []
        self._pending: _Pending | None = None
        """A restart begun whose re-run has not started yet (its warm start not fitted)."""
        self._rerun: Lanes | None = None
        """The re-run of a restart while it catches up (None: none under way)."""
        self._rerun_pos = 0
        self._rerun_tunings = tunings
        self._since_begin = 0
        """Frames since the restart under way began, that one included."""
        self._grace = 0
        """Frames of grace of the restart under way (set where it began)."""
        self.worked_ahead = 0
        """Work done in idle time (work_ahead): frames, and 1 per warm start."""
        self.warm_start: WarmStart | None = None
        self.noise_reading: NoiseReading | None = None
        """Each channel's noise as read from the data (None: none read)."""

    @property
    def pending(self) -> bool:
        """Whether restarts remain to be done."""
        return self.done < len(self.settings.restart_times_s)

    @property
    def under_way(self) -> bool:
        return self._pending is not None or self._rerun is not None

    def keep(self, frame: Frame) -> None:
        """A new frame, buffered while restarts remain that will re-run it."""
        if self.pending:
            self.buffer.append(frame)

    def after_frame(self, since_first_s: float, lanes: Lanes) -> Swap | None:
        """After the live pass (lanes) stepped a frame `since_first_s` after the first:
        begin the restart due, and make the re-run's progress the schedule asks for; the
        swap when the re-run takes over at this frame."""
        times = self.settings.restart_times_s
        if not self.under_way and self.pending and since_first_s >= times[self.done]:
            self._begin(lanes)
        if not self.under_way:
            return None
        self._since_begin += 1
        return self._follow_schedule()

    def _follow_schedule(self) -> Swap | None:
        """The re-run's progress this frame must have made, whatever was done ahead in
        idle time (work_ahead): restart_frames_per_step frames per frame once the grace
        has passed (GRACE_PER_PEER for each other vehicle restarting when this restart
        began; 0: all of it now). When that reaches the newest frame the re-run takes
        over: at a frame fixed by the data (the link's, every vehicle's, in the order
        they came) and the settings alone."""
        n = len(self.buffer)
        per = self.settings.restart_frames_per_step
        due = n if per <= 0 else min(n, max(0, self._since_begin - self._grace) * per)
        if due == 0:
            return None
        outs = self._advance(due)
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
        self._advance(min(len(self.buffer), pos + max_frames))
        self.worked_ahead += self._rerun_pos - pos
        return self._rerun_pos - pos

    def finish(self) -> Swap | None:
        """Complete a re-run still under way (the end of the data came first)."""
        if not self.under_way:
            return None
        return self._swap(self._advance(len(self.buffer)))

    def drop(self) -> None:
        """The vehicle clock restarted: the restarts still to do are dropped (their frames
        would span two time bases)."""
        if self.pending:
            self.done = len(self.settings.restart_times_s)
            self.buffer = []
            self._rerun = None
            self._pending = None

    def _advance(self, end: int) -> dict[FilterKind, StepOutput]:
        """Step the re-run through the buffered frames up to `end` (exclusive); its
        outputs at the last frame stepped (empty if none)."""
        if self._pending is not None:
            self._start_rerun()
        assert self._rerun is not None
        frames = self.buffer[self._rerun_pos : end]
        outs = self.runner.frames(self._rerun, frames, self._rerun_tunings)
        self._rerun_pos = max(self._rerun_pos, end)
        return outs

    def _swap(self, outs: dict[FilterKind, StepOutput]) -> Swap:
        """The re-run, caught up with the newest frame, becomes the live pass."""
        assert self._rerun is not None and self._rerun_pos == len(self.buffer)
        swap = Swap(self._rerun, self._rerun_tunings, outs)
        self._rerun = None
        self.done += 1
        if not self.pending:
            self.buffer = []
        return swap

    def _begin(self, lanes: Lanes) -> None:
        """Begin a re-run of the buffered frames: take from the live pass (lanes) what the
        re-run starts from, now; the warm start's fit, at the first restart, waits for
        _start_rerun (idle time first)."""
        coef = self.runner.model.coefficients
        means: dict[FilterKind, tuple[FloatArray, FloatArray]] | None = None
        if self.done > 0:
            means = {
                k: (s.x[coef].copy(), np.sqrt(np.diag(s.P))[coef])
                for k, s in lanes.items()
                if s is not None
            }
        gust: dict[FilterKind, float | None] = {}
        for kind, state in lanes.items():
            assert state is not None
            # The first re-run starts at the turbulence level the zero-start pass ended
            # with: its average over the pass can come out near calm (early innovations
            # are smaller than the unknown coefficients make it predict), and a re-run
            # that starts as calm air in turbulence can lock onto wrong coefficients
            # (docs/decisions/0005). Later re-runs start at the average of the pass before.
            gust[kind] = None
            if self.settings.turbulence.adaptive:
                first = self.done == 0
                gust[kind] = max(state.gust.var, 0.0) if first else state.gust.pass_average()
        self._pending = _Pending(len(self.buffer), means, gust)
        self._since_begin = 0
        peers = self.peers_restarting() if self.peers_restarting is not None else 0
        self._grace = GRACE_PER_PEER * peers

    def _start_rerun(self) -> None:
        """The re-run's first states: from the warm start's fit to the frames buffered
        when the restart began, or from the live pass's estimates then."""
        pending = self._pending
        assert pending is not None
        ft = self.settings
        buffered = self.buffer[: pending.frames]
        self._rerun_tunings, reading = _noise_from_data(
            ft, buffered, self.tunings, self.noise_scale
        )
        if reading is not None:
            self.noise_reading = reading
        means = pending.means
        if means is None:
            self.warm_start, sigma = _fit(ft, self.runner.model, buffered)
            means = dict.fromkeys(FILTER_KINDS, (self.warm_start.beta, sigma))
        p0 = np.array(ft.initial_sigma.coefficients)
        for kind, (beta, sigma) in means.items():
            # A data-derived prior, widened so that reusing the early data in it weighs
            # little next to the data themselves; never wider than P0.
            self.runner.starts[kind] = Start(
                beta, np.minimum(p0, SIGMA_INFLATION * sigma), pending.gust[kind]
            )
        self._pending = None
        self._rerun = dict.fromkeys(FILTER_KINDS)
        self._rerun_pos = 0


def _fit(settings: FilterTuning, model: Model, frames: list[Frame]) -> tuple[WarmStart, FloatArray]:
    """The equation-error warm start's fit to the frames (warmstart.py), and the sigma of
    its coefficients."""
    from gcs_estimator.estimation.warmstart import equation_error

    t_b, u_b, y_b, _ = (np.array(col) for col in zip(*frames, strict=True))
    ws = equation_error(
        model,
        t_b,
        u_b,
        y_b,
        np.zeros(model.n_coefficients),  # the filters' prior: the paper's zero start
        np.array(settings.initial_sigma.coefficients),
    )
    return WarmStart(ws.beta, ws.samples, len(t_b)), ws.sigma


def _noise_from_data(
    settings: FilterTuning, frames: list[Frame], tunings: Tunings, noise_scale: FloatArray | None
) -> tuple[Tunings, NoiseReading | None]:
    """A re-run's settings: with measurement_noise = "auto" each channel's noise read from
    the frames (noise.py) where clearly below the configured sigma, and the reading; with
    "config" the live pass's settings (tunings), and no reading."""
    if settings.measurement_noise == "config":
        return tunings, None
    t = np.array([row[0] for row in frames])
    y = np.array([row[2] for row in frames]).reshape(len(frames), -1)
    configured = np.array(settings.measurement_sigma, float)
    sigma, reading = noise.sigma_to_use(t, y, configured)
    R = np.diag(sigma**2)
    return noise.scaled({k: tn._replace(R=R) for k, tn in tunings.items()}, noise_scale), reading
