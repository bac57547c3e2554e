"""The rows the filters write per frame: one step's output (StepOutput), a run's rows kept
on disk as they come (Rows, FrameHistory, History, Histories), and their frozen arrays
(Track)."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import BinaryIO

import numpy as np

from gcs_estimator.arrays import FloatArray
from gcs_estimator.estimation.filters import core
from gcs_estimator.estimation.filters.core import FILTER_KINDS, FilterKind, StepInfo
from gcs_estimator.model.aircraft import Model
from gcs_estimator.model.channels import N_INPUTS, N_OBS

HISTORY_CHUNK = 4096
"""Rows of a history kept in memory before they go to disk."""

HISTORY_DTYPE = np.float32
"""A filter's per-frame outputs are kept to 7 significant digits: they are for plots,
convergence times and the history file, never fed back (the filter's own state is
float64). Half the disk, and half the pages the end of a run maps to summarise them."""


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

    def claim_many(self, m: int) -> Iterator[np.ndarray]:
        """m new rows at the end, as blocks of consecutive rows in memory, each to be
        filled in place before the next is asked for (a block ends where claim() would
        write the rows before it to disk: the files hold the same rows either way)."""
        while m > 0:
            if self._nbuf == HISTORY_CHUNK:
                self._write(self._nbuf)
                self._flushed += self._nbuf
                self._nbuf = 0
            k = min(m, HISTORY_CHUNK - self._nbuf)
            self._nbuf += k
            m -= k
            yield self._buf[self._nbuf - k : self._nbuf]

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

    def extend(self, t: FloatArray, u: FloatArray, y: FloatArray) -> None:
        """append() of each frame (rows of t, u, y) at once."""
        done = 0
        for block in self.rows.claim_many(len(t)):
            part = slice(done, done + block.shape[0])
            block[:, 0] = t[part]
            block[:, 1 : 1 + N_INPUTS] = u[part]
            block[:, 1 + N_INPUTS :] = y[part]
            done += block.shape[0]

    def arrays(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(t [N], u [N x N_INPUTS], y [N x N_OBS])."""
        t, u, y = self.rows.arrays()
        return t[:, 0], u, y


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

    def extend(self, rows: FloatArray) -> None:
        """append() of each step's output row (rows of `rows`) at once."""
        done = 0
        for block in self.rows.claim_many(rows.shape[0]):
            block[:] = rows[done : done + block.shape[0], : block.shape[1]]
            done += block.shape[0]

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


class Histories:
    """Both filters' per-frame outputs and the frames they share, kept as the run goes
    (keep=False: none kept)."""

    def __init__(self, n: int, keep: bool) -> None:
        self.keep = keep
        self.frames = FrameHistory()
        self.filters = {k: History(n) for k in FILTER_KINDS}

    @property
    def rows(self) -> int:
        """Frames in the history (0 when none is kept)."""
        return self.frames.rows.n if self.keep else 0

    def append(
        self, t: float, u: FloatArray, y: FloatArray, outs: dict[FilterKind, StepOutput]
    ) -> None:
        if self.keep:
            self.frames.append(t, u, y)
            for kind, out in outs.items():
                self.filters[kind].append(out)

    def extend(
        self, t: FloatArray, u: FloatArray, y: FloatArray, rows: dict[FilterKind, FloatArray]
    ) -> None:
        """append() of each frame at once: its time, inputs and observations (rows of t,
        u, y) and each filter's output rows (rows[kind])."""
        if self.keep:
            self.frames.extend(t, u, y)
            for kind, out in rows.items():
                self.filters[kind].extend(out)

    def set_last(self, outs: dict[FilterKind, StepOutput]) -> None:
        """The newest frame's rows replaced (a re-run took over there)."""
        if self.keep:
            for kind, out in outs.items():
                self.filters[kind].set_last(out)

    def tracks(self, kinds: Iterable[FilterKind], model: Model) -> dict[FilterKind, Track]:
        """The filters' histories so far (empty when none is kept)."""
        if not self.keep:
            return {}
        return {kind: Track.of(self.filters[kind], self.frames, model) for kind in kinds}


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
