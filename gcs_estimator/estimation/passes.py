"""Frames through both filters of a pass: the one place the estimator's lanes are stepped,
frame by frame, or a re-run's runs of frames in one compiled call each (the same steps,
bit for bit: docs/decisions/0013).

A pass is a dict of lanes, one per filter kind (None before its first frame), and the
settings it steps with; a frame is (vehicle time [s], inputs as the equations take them,
observations [7], whether the inputs are known)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from gcs_estimator.arrays import FloatArray
from gcs_estimator.estimation.filters import core
from gcs_estimator.estimation.filters.core import FILTER_KINDS, Backend, FilterKind, Tuning
from gcs_estimator.estimation.filters.lane import Lane
from gcs_estimator.estimation.history import StepOutput
from gcs_estimator.estimation.results import Health
from gcs_estimator.model.aircraft import Model
from gcs_estimator.model.channels import N_OBS

BLOCK_MIN_FRAMES = 4
"""Re-run frames worth one compiled call per filter (fewer: a call per frame)."""
ROWS_FRAMES = 4096
"""Most frames a compiled call that keeps every frame's row (Runner.rows) takes at once:
a long replay's rows never all in memory (4096 rows of a few hundred bytes)."""

Lanes = dict[FilterKind, Lane | None]
Tunings = dict[FilterKind, Tuning]
Frame = tuple[float, FloatArray, FloatArray, bool]


class Start(NamedTuple):
    """How a filter's pass starts: coefficient mean and sigma, gust variance (None: the
    configured ones)."""

    coefficients: FloatArray | None = None
    sigma: FloatArray | None = None
    gust_var: float | None = None


NO_UPDATE_PENALTY = 1e3
"""What a step without an update adds to a pass's -2 log likelihood: a frame without
data adds it to every replay alike, a filter that failed or diverged on replayed inputs
many times (far beyond a chi-square's spread), so it is not the likelier for having
skipped its data."""


def _log_likelihoods(rows: FloatArray, n: int) -> list[float]:
    """_log_likelihood of each row, by the same numpy operations on the same values: the
    rows grouped by the channels they used, each group's logs taken and summed over
    those channels as one array (a row's sum in the same order as its own)."""
    o = 2 * n
    nis = rows[:, o]
    sigma = rows[:, o + 4 + N_OBS : o + 4 + 2 * N_OBS]
    used = np.isfinite(sigma) & (sigma > 0.0)
    logs = np.zeros(rows.shape[0])
    patterns, which = np.unique(used, axis=0, return_inverse=True)
    which = which.reshape(-1)
    for j, mask in enumerate(patterns):
        if mask.any():
            group = which == j
            # C-contiguous: numpy sums each row with the loop it sums one row's array with
            # (a strided view takes another order: the last bit differs).
            logs[group] = np.sum(np.ascontiguousarray(np.log(sigma[group][:, mask])), axis=1)
    out = nis + 2.0 * logs
    penalty = ~np.isfinite(nis) | ~used.any(axis=1)
    out[penalty] = NO_UPDATE_PENALTY
    values: list[float] = out.tolist()
    return values


def _log_likelihood(row: FloatArray, n: int) -> float:
    """-2 log likelihood of one step's innovations (its NIS plus the log of each used
    channel's innovation variance; the innovations' correlation left out);
    NO_UPDATE_PENALTY where the step made no update."""
    info = core.info_of_row(row, n)
    used = np.isfinite(info.innovation_sigma) & (info.innovation_sigma > 0.0)
    if not math.isfinite(info.nis) or not used.any():
        return NO_UPDATE_PENALTY
    return info.nis + 2.0 * float(np.sum(np.log(info.innovation_sigma[used])))


class Runner:
    """Steps the lanes of a pass; counts what the steps report (health) and keeps where
    the newest pass starts (starts)."""

    def __init__(self, model: Model, backend: Backend) -> None:
        self.model = model
        self.backend: Backend = backend
        self.blocks = backend == "fast"
        self.likelihood: dict[FilterKind, float] | None = None
        """Where a dict (the structure check's profile replays): each filter's -2 log
        likelihood of its innovations summed frame by frame (NIS plus the log of the
        innovations' variances), from the rows of compiled blocks (Runner.rows) where the
        backend has them."""
        """Many frames of a re-run in one compiled call (Lane.block); else one at a
        time (the reference backend has no compiled calls)."""
        self.health = {k: Health() for k in FILTER_KINDS}
        self.starts = {k: Start() for k in FILTER_KINDS}
        """Each filter's start at a pass's first frame (the newest pass's)."""

    def frame(
        self,
        lanes: Lanes,
        t: float,
        u: FloatArray,
        y: FloatArray,
        inputs_known: bool,
        tunings: Tunings,
    ) -> dict[FilterKind, StepOutput]:
        """One frame through both filters of a pass."""
        return {
            kind: self.one(kind, lanes, t, u, y, inputs_known, tunings[kind])
            for kind in FILTER_KINDS
        }

    def one(
        self,
        kind: FilterKind,
        lanes: Lanes,
        t: float,
        u: FloatArray,
        y: FloatArray,
        inputs_known: bool,
        tuning: Tuning,
    ) -> StepOutput:
        """One frame through one filter of a pass."""
        lane = lanes[kind]
        if lane is None:
            start = core.initial_state(self.model, tuning, t, u, y, *self.starts[kind])
            lane = lanes[kind] = Lane(start, self.backend)
        elif not inputs_known:
            lane.load(core.rebase(lane.state, self.model, tuning, t, y))
        y_used = y if inputs_known else np.full_like(y, np.nan)
        row, status = lane.step(t, u, y_used, tuning, self.model)
        if self.likelihood is not None:
            self.likelihood[kind] = self.likelihood.get(kind, 0.0) + _log_likelihood(row, lane.n)
        if status:
            self.health[kind].add(*core.flags_of_row(row, lane.n).tolist())
        return StepOutput(row, lane.n)

    def block(
        self, kind: FilterKind, lanes: Lanes, frames: Sequence[Frame], tuning: Tuning
    ) -> StepOutput | None:
        """Frames through one filter of a pass, runs of them in one compiled call each
        (the same steps as one()'s, bit for bit): the output at the last frame.
        A pass's first frame and a frame whose inputs are a guess go through
        one(); a step the contract must repair or restart is answered where it
        falls, as one()'s would be (Lane.block; docs/decisions/0013)."""
        ts = np.array([f[0] for f in frames])
        us = np.array([f[1] for f in frames])
        ys = np.array([f[2] for f in frames])
        known = [f[3] for f in frames]
        out: StepOutput | None = None
        i = 0
        while i < len(frames):
            lane = lanes[kind]
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
            out = self.one(kind, lanes, t, u, y, inputs_known, tuning)
            i += 1
        return out

    def rows(
        self,
        kind: FilterKind,
        lanes: Lanes,
        ts: FloatArray,
        us: FloatArray,
        ys: FloatArray,
        tuning: Tuning,
    ) -> FloatArray:
        """Frames whose inputs are known through one filter of a pass under way (its lane
        begun), every frame's outputs kept: a row each (Lane.rows: the same steps as
        one()'s, bit for bit), the health counted and the likelihood summed as one()
        does frame by frame."""
        lane = lanes[kind]
        assert lane is not None
        rows, counts = lane.rows(ts, us, ys, tuning, self.model)
        self.health[kind].add(*counts)
        if self.likelihood is not None:
            total = self.likelihood.get(kind, 0.0)
            for value in _log_likelihoods(rows, lane.n):
                total = total + value
            self.likelihood[kind] = total
        return rows

    def frames(
        self, lanes: Lanes, frames: Sequence[Frame], tunings: Tunings
    ) -> dict[FilterKind, StepOutput]:
        """Frames through both filters of a pass, in blocks where they are worth it: the
        outputs at the last frame (empty if none)."""
        outs: dict[FilterKind, StepOutput] = {}
        if not self.blocks or len(frames) < BLOCK_MIN_FRAMES:
            for t, u, y, known in frames:
                outs = self.frame(lanes, t, u, y, known, tunings)
        else:
            for kind in FILTER_KINDS:
                out = self.block(kind, lanes, frames, tunings[kind])
                if out is not None:
                    outs[kind] = out
        return outs

    def replay(
        self,
        lanes: Lanes,
        t: FloatArray,
        u: FloatArray,
        y: FloatArray,
        tunings: Tunings,
        max_gap_s: float,
        fresh: Sequence[int] = (),
        kinds: Sequence[FilterKind] = FILTER_KINDS,
    ) -> None:
        """A record (t, u, y as a history holds them) through both filters of a pass (or
        those in `kinds`), the flight states started afresh after every gap longer than
        max_gap_s as a run does, and at each frame in `fresh` as a segment's first frame
        is (stepped as a frame whose input is a guess: afresh, no update; segments.py),
        each run of frames in one compiled call per filter where the backend has blocks."""
        starts = set(fresh)
        u = self.model.inputs_of(u)
        y = np.asarray(y, float)
        i, n = 0, len(t)
        while i < n:
            end = i + 1
            while end < n and t[end] - t[end - 1] <= max_gap_s and end not in starts:
                end += 1
            for kind in kinds:
                self._replay_run(
                    kind, lanes, t[i:end], u[i:end], y[i:end], tunings[kind], i in starts
                )
            i = end

    def _replay_run(
        self,
        kind: FilterKind,
        lanes: Lanes,
        t: FloatArray,
        u: FloatArray,
        y: FloatArray,
        tuning: Tuning,
        fresh: bool,
    ) -> None:
        """One run of a replay (no gap, no segment's start after its first frame) through
        one filter: its first frame begins the lane, or starts afresh (fresh: as a frame
        whose input is a guess), or the flight states are rebased there (after a gap);
        then the rest in one compiled call where the backend has them (every frame's
        row kept where the likelihood is summed), else frame by frame."""
        lane = lanes[kind]
        t0, y0 = float(t[0]), y[0]
        first = 0
        if lane is None or fresh:
            self.one(kind, lanes, t0, u[0], y0, not fresh, tuning)
            first = 1
        else:
            lane.load(core.rebase(lane.state, self.model, tuning, t0, y0))
        lane = lanes[kind]
        assert lane is not None
        if self.backend != "fast" or not (self.blocks or self.likelihood is not None):
            for j in range(first, len(t)):
                self.one(kind, lanes, float(t[j]), u[j], y[j], True, tuning)
        elif self.likelihood is None:  # only the last row is wanted
            if len(t) > first:
                _, counts = lane.block(t[first:], u[first:], y[first:], tuning, self.model)
                self.health[kind].add(*counts)
        else:
            for a in range(first, len(t), ROWS_FRAMES):
                part = slice(a, min(a + ROWS_FRAMES, len(t)))
                self.rows(kind, lanes, t[part], u[part], y[part], tuning)
