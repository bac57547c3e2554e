"""Differences of one channel's samples at any spacing, and the white noise they show:
what the filters' noise reading (estimation/noise.py, decision 0078) and the data
compatibility check (ingest/compat.py) read each channel's noise with.

The fourth divided difference of five consecutive samples (weights w_i = 1 / prod_{j != i}
(t_i - t_j), which take a cubic to zero at any spacing), scaled to unit length, so that
white noise of sigma s gives s whatever the spacing; on an even grid the weights are
y[k] - 4 y[k+1] + 6 y[k+2] - 4 y[k+3] + y[k+4] over sqrt(70). The median absolute
deviation turns them into a sigma that the few large differences at a manoeuvre's step
leave alone (difference-based variance estimators: Rice 1984; Gasser, Sroka and
Jennen-Steinmetz 1986).
"""

from __future__ import annotations

import numpy as np

from gcs_estimator.arrays import FloatArray

ORDER = 4
"""The differences' order: each takes ORDER + 1 samples of one channel."""
GAP_RATIO = 2.0
"""Five samples of a channel give a difference only where they span at most this times
the median span of the channel's fives (a sample lost here and there still does)."""
MAD_TO_SIGMA = 1.4826
"""sigma over the median absolute deviation, for Gaussian noise."""


def divided_differences(t: FloatArray, y: FloatArray) -> FloatArray:
    """The fourth divided differences of one channel's samples y at times t, each scaled
    to unit weight length (white noise of sigma s gives differences of sigma s), from
    every ORDER + 1 consecutive samples whose times rise and whose span is at most
    GAP_RATIO times the median span."""
    k = ORDER + 1
    if t.shape[0] < k:
        return np.empty(0)
    tw = np.lib.stride_tricks.sliding_window_view(t, k)
    yw = np.lib.stride_tricks.sliding_window_view(y, k)
    rising = np.all(np.diff(tw, axis=1) > 0.0, axis=1)  # none across a clock reset
    if not rising.any():
        return np.empty(0)
    tw, yw = tw[rising], yw[rising]
    gaps = tw[:, :, None] - tw[:, None, :]  # t_i - t_j
    np.einsum("nii->ni", gaps)[:] = 1.0
    w = 1.0 / np.prod(gaps, axis=2)
    w /= np.sqrt(np.sum(w * w, axis=1, keepdims=True))
    span = tw[:, -1] - tw[:, 0]
    d: FloatArray = np.sum(w * yw, axis=1)
    return d[span <= GAP_RATIO * float(np.median(span))]


def channel_differences(t: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray]:
    """One channel's divided differences (finite ones) from its own samples, y at times t
    (NaN where a frame lacks it; a time that does not follow the one before it dropped),
    and the times of those samples."""
    present = np.isfinite(y) & np.isfinite(t)
    tc, yc = t[present], y[present]
    later = np.concatenate(([True], np.diff(tc) > 0.0)) if tc.shape[0] else present[:0]
    tc, yc = tc[later], yc[later]
    d = divided_differences(tc, yc)
    return d[np.isfinite(d)], tc


def mad_sigma(d: FloatArray) -> float:
    """White noise's sigma from differences d by their median absolute deviation (a few
    sharp changes, a manoeuvre's, left out)."""
    return MAD_TO_SIGMA * float(np.median(np.abs(d - np.median(d))))
