"""The inputs as the aircraft feels them: each frame's logged inputs taken
`[data] input_delay_s` later (decision 0044).

A servo command logged at the sample time moves the surface tens of milliseconds later;
a log's input channel can be skewed against its responses. The filters predict with the
input of time t - delay, linearly interpolated between the frames that bracket it (held
at the first frame before the record reaches back that far). Live, the past frames are
all there is, so only delays (not leads) are possible; `refine` estimates the delay that
remains on top of this one, of either sign.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from gcs_estimator.arrays import FloatArray, IntArray

MAX_DELAY_S = 0.5
"""The largest input delay (either sign) a fit considers [s]: beyond it the shifted
input is held at the record's end, and no response in a record of manoeuvres is that
late."""


def delayed_inputs(
    t: FloatArray, u: FloatArray, delayed: IntArray, delays: FloatArray
) -> FloatArray:
    """The inputs u [N x m] with column delayed[j] late by delays[j] [s] (clipped to
    +-MAX_DELAY_S): its value at t_i is the record's, linearly interpolated, at t_i -
    delay (held at the record's first or last sample beyond it). Under either input hold
    the shifted samples carry each interval's mean of the shifted signal to first order,
    and the result moves continuously with the delay (decision 0044)."""
    out = u.copy()
    for col, tau in zip(delayed, delays, strict=True):
        tau = min(max(float(tau), -MAX_DELAY_S), MAX_DELAY_S)
        if tau != 0.0:
            out[:, col] = np.interp(t - tau, t, u[:, col])
    return np.ascontiguousarray(out)


class InputDelay:
    """A delay line of the model's inputs: `at(t, u)` takes frame t's inputs u and
    returns the inputs of time t - delay_s."""

    def __init__(self, delay_s: float) -> None:
        self.delay_s = delay_s
        self._frames: deque[tuple[float, FloatArray]] = deque()

    def at(self, t: float, u: FloatArray) -> FloatArray:
        """The inputs of time t - delay_s from the frames so far and this one (frames in
        increasing time; a missing input (NaN) is carried from the sample that has it)."""
        if self.delay_s <= 0.0:
            return u
        self._frames.append((t, u))
        target = t - self.delay_s
        # Keep one frame at or before the target: the next frames' targets lie later.
        while len(self._frames) > 2 and self._frames[1][0] <= target:
            self._frames.popleft()
        t0, u0 = self._frames[0]
        if target <= t0 or len(self._frames) < 2:
            return u0.copy()
        t1, u1 = self._frames[1]
        w = (target - t0) / (t1 - t0)
        lo = np.where(np.isfinite(u0), u0, u1)
        hi = np.where(np.isfinite(u1), u1, lo)
        out: FloatArray = lo + w * (hi - lo)
        return out

    def restart(self) -> None:
        """Forget the frames (the flight states start afresh after a gap)."""
        self._frames.clear()
