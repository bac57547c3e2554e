"""A filter's belief kept in one buffer and stepped by the chosen backend (the compiled
kernel or the numpy reference), and the step function of a backend. Apart from core so
that the contract (core) sits below both backends and this module above them."""

from __future__ import annotations

import numpy as np

from gcs_estimator.arrays import FloatArray, IntArray
from gcs_estimator.estimation.filters import reference
from gcs_estimator.estimation.filters.core import (
    Backend,
    FilterState,
    GustState,
    StepFn,
    Tuning,
    flags_of_row,
    guarded,
    info_of_row,
    output_row,
    recover,
)
from gcs_estimator.model.aircraft import Model
from gcs_estimator.model.channels import N_OBS


class Lane:
    """One filter's belief as the estimator's runner keeps it from frame to frame, and
    its step there: the step contract (guarded) with the same results bit for bit, each
    step's outputs handed back as one row (output_row's layout).

    With the compiled backend the belief lives in one buffer that the kernel updates
    where it lies (filters.fast.belief_buffer), so that a frame's step hands the kernel
    seven values and gets back one status, instead of a FilterState's fields and a new
    belief and report built around its results (more than a third of a step). `state`
    reads the belief out as a FilterState of its own; `load` puts one in. `x`, `P` and
    `gust` read it where it lies: valid until the next step."""

    def __init__(self, state: FilterState, backend: Backend) -> None:
        self.backend: Backend = backend
        self._compiled = backend == "fast"
        self.n = state.x.shape[0]
        self._tuning: Tuning | None = None
        self._model: Model | None = None
        self._packed: tuple[FloatArray, IntArray] = (np.empty(0), np.empty(0, np.int64))
        """The settings as the kernel takes them, for _tuning and _model (_pack)."""
        self._state: FilterState
        """The belief, with the reference backend (the compiled one keeps _buf)."""
        self._buf = np.empty(0)
        if self._compiled:
            # Imported here: the reference backend runs without the compiler installed.
            from gcs_estimator.estimation.filters import fast

            self._fast = fast
            self._kernel = fast.lane_kernel
            self._width = fast.output_width(self.n)
        self._step_ref = stepper("reference") if backend == "reference" else None
        self.load(state)

    def load(self, state: FilterState) -> None:
        """Make `state` the belief."""
        if self._compiled:
            self._buf = self._fast.belief_buffer(state)
        else:
            self._state = state

    @property
    def state(self) -> FilterState:
        """The belief, as a FilterState whose arrays stay as they are."""
        if self._compiled:
            return self._fast.belief_of(self._buf, self.n)
        return self._state

    @property
    def x(self) -> FloatArray:
        """The state estimate, where it lies (changes with the next step)."""
        if self._compiled:
            o = self._fast.BELIEF_HEAD
            return self._buf[o : o + self.n]
        return self._state.x

    @property
    def P(self) -> FloatArray:
        """Its covariance, where it lies (changes with the next step)."""
        if self._compiled:
            o, n = self._fast.BELIEF_HEAD + self.n, self.n
            return self._buf[o : o + n * n].reshape(n, n)
        return self._state.P

    @property
    def gust(self) -> GustState:
        return self.state.gust

    def _pack(self, tuning: Tuning, model: Model) -> tuple[FloatArray, IntArray]:
        """The settings as the kernel takes them (filters.fast.pack), kept while the same
        tuning and model come."""
        if tuning is not self._tuning or model is not self._model:
            self._packed = self._fast._packed(tuning, model)
            self._tuning, self._model = tuning, model
        return self._packed

    def step(
        self, t: float, u: FloatArray, y: FloatArray, tuning: Tuning, model: Model
    ) -> tuple[FloatArray, int]:
        """One frame (the step contract's): (the step's outputs as a new row, status: 0
        nothing to report, else the row's failed, repaired or diverged flag is set)."""
        if not self._compiled:
            assert self._step_ref is not None
            self._state, info = self._step_ref(self._state, t, u, y, tuning, model)
            row = output_row(self._state.x, info)
            return row, int(info.failed or info.repaired or info.diverged)
        if tuning is not self._tuning or model is not self._model:
            self._pack(tuning, model)
        tf, ti = self._packed
        row = np.empty(self._width)
        status = self._kernel(self._buf, t, u, y, tf, ti, row)
        if status == 2:
            return self._recover(t, u, y, tuning, model, row), 1
        return row, status

    def block(
        self, ts: FloatArray, us: FloatArray, ys: FloatArray, tuning: Tuning, model: Model
    ) -> tuple[FloatArray, tuple[int, int, int]]:
        """The frames (rows of ts, us, ys) in order, with the compiled backend one call for
        each run of healthy steps: (the last step's outputs, and the failed updates,
        covariance repairs and restarts among the steps); the same steps as `step` frame
        by frame, bit for bit."""
        counts = np.zeros(3, dtype=np.int64)
        row = np.empty(0)
        if not self._compiled:
            for i in range(ts.shape[0]):
                row, status = self.step(float(ts[i]), us[i], ys[i], tuning, model)
                if status:
                    counts += flags_of_row(row, self.n)
            return row, (int(counts[0]), int(counts[1]), int(counts[2]))
        tf, ti = self._pack(tuning, model)
        ts = np.ascontiguousarray(ts, dtype=np.float64)
        us = np.ascontiguousarray(us, dtype=np.float64)
        ys = np.ascontiguousarray(ys, dtype=np.float64)
        row = np.empty(self._width)
        i = 0
        while i < ts.shape[0]:
            done, failed, healthy = self._fast.lane_block_kernel(
                self._buf, ts[i:], us[i:], ys[i:], tf, ti, row
            )
            counts[0] += failed
            i += done
            if not healthy:
                j = i - 1
                row = self._recover(float(ts[j]), us[j], ys[j], tuning, model, row)
                counts += flags_of_row(row, self.n)
        return row, (int(counts[0]), int(counts[1]), int(counts[2]))

    def rows(
        self, ts: FloatArray, us: FloatArray, ys: FloatArray, tuning: Tuning, model: Model
    ) -> tuple[FloatArray, tuple[int, int, int]]:
        """`block` keeping every frame's outputs: (a row per frame, output_row's layout;
        the failed updates, covariance repairs and restarts among the steps); the same
        steps as `step` frame by frame, bit for bit."""
        counts = np.zeros(3, dtype=np.int64)
        m = ts.shape[0]
        if not self._compiled:
            out = np.empty((m, self._width_of()))
            for i in range(m):
                out[i], status = self.step(float(ts[i]), us[i], ys[i], tuning, model)
                if status:
                    counts += flags_of_row(out[i], self.n)
            return out, (int(counts[0]), int(counts[1]), int(counts[2]))
        tf, ti = self._pack(tuning, model)
        ts = np.ascontiguousarray(ts, dtype=np.float64)
        us = np.ascontiguousarray(us, dtype=np.float64)
        ys = np.ascontiguousarray(ys, dtype=np.float64)
        out = np.empty((m, self._width))
        i = 0
        while i < m:
            done, failed, healthy = self._fast.lane_rows_kernel(
                self._buf, ts[i:], us[i:], ys[i:], tf, ti, out[i:]
            )
            counts[0] += failed
            i += done
            if not healthy:
                j = i - 1
                out[j] = self._recover(float(ts[j]), us[j], ys[j], tuning, model, out[j])
                counts += flags_of_row(out[j], self.n)
        return out, (int(counts[0]), int(counts[1]), int(counts[2]))

    def _width_of(self) -> int:
        """Floats of a step's output row (filters.fast.output_width, without the compiler)."""
        return int(2 * self.n + 4 + 2 * N_OBS + 4)

    def _recover(
        self, t: float, u: FloatArray, y: FloatArray, tuning: Tuning, model: Model, row: FloatArray
    ) -> FloatArray:
        """The contract's answer to an unhealthy step (guarded): the belief repaired or
        started again, and its outputs."""
        state, info = recover(self.state, info_of_row(row, self.n), t, u, y, tuning, model)
        self.load(state)
        return output_row(state.x, info)


def stepper(backend: Backend) -> StepFn:
    """The step of the chosen backend: "fast" (compiled) or "reference" (numpy)."""
    if backend == "fast":
        from gcs_estimator.estimation.filters import fast

        return guarded(fast.kernel_step)
    return guarded(reference.kernel_step)
