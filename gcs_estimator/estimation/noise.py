"""Each sensor's noise level from the record itself (`[filter] measurement_noise = "auto"`),
and the measurement noise the filters' settings carry.

A channel sampled fast against the aircraft's motion is a smooth signal plus white noise.
The fourth difference y[k] - 4 y[k+1] + 6 y[k+2] - 4 y[k+3] + y[k+4] of the smooth part
is of order h^4 times the signal's fourth derivative, small at the sample interval h; of
white noise of sigma s it has variance 70 s^2. So sigma = MAD(fourth differences) *
1.4826 / sqrt(70): the median absolute deviation keeps the estimate from the few large
differences at an elevator step (difference-based variance estimators: Rice 1984;
Gasser, Sroka and Jennen-Steinmetz 1986). The fourth order, not the second, because the
simulator's short-period pitch response at 50 Hz is not smooth enough for the second: it
read the pitch-rate noise 1.5 times too high over the first 10 s, the fourth 1.17 times.

A log or a link sends each channel at its own rate and with its own jitter, so each
channel is read from its own samples, five in a row, with the weights of the fourth
divided difference at their times (w_i = 1 / prod_{j != i} (t_i - t_j), which take a
cubic to zero at any spacing) scaled to unit length, so that white noise of sigma s
gives s whatever the spacing; on an even grid they are the weights above over sqrt(70).
Five samples that span more than differences.GAP_RATIO times the channel's usual span (a
lost stretch, a pause) give none (decision 0078; gcs_estimator/differences.py, which the
data compatibility check reads its channels' noise with too).

What it cannot tell from noise is motion that is itself rough at the sample rate:
turbulence with a short scale length moves pitch acceleration (and so qdot and q) sample
to sample, and that motion is counted as noise. docs/decisions/0011 says what it gives on
the simulator and the validation set.

So a reading can only err high: motion adds to the differences, never takes away. The
default, "auto", takes the reading only where it is below the configured sigma by more
than CLEARLY of its standard errors (the sensor is clearly better than configured), and
keeps the configured sigma elsewhere (docs/decisions/0014); "config" reads nothing.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from gcs_estimator.arrays import FloatArray
from gcs_estimator.differences import channel_differences, mad_sigma
from gcs_estimator.estimation.filters.core import FilterKind, Tuning

MIN_DIFFERENCES = 30
"""Differences a channel needs for its own estimate (fewer: the fallback)."""
FLOOR_RATIO = 0.1
"""An estimate never goes below this share of the fallback (a quantised or constant
channel would otherwise get no noise at all, and a filter that trusts it without bound)."""
READING_SPREAD = 1.59
"""A reading from m differences of white noise has a relative standard deviation of
READING_SPREAD / sqrt(m) (the median absolute deviation's, widened by the overlap of
neighbouring fourth differences): 1.57-1.60 measured over 3000 records of white noise at
each of 50 to 3000 samples; tests/test_noise.py checks it on 600 records of 250."""
CLEARLY = 3.0
"""Standard errors by which a reading must fall below the configured sigma to replace it
("auto"); above 3 a record of configured noise is read that low about once in a
thousand channels."""


def noise_from_differences(
    t: FloatArray, y: FloatArray, fallback: FloatArray
) -> tuple[FloatArray, np.ndarray]:
    """(sigma per channel [c], differences used per channel [c]) of observations y
    [N x c] at times t [N], NaN where missing: each channel from its own samples
    (differences.channel_differences). A
    channel with fewer than MIN_DIFFERENCES keeps its fallback sigma; none goes below
    FLOOR_RATIO of it."""
    t = np.asarray(t, float)
    y = np.asarray(y, float)
    fallback = np.asarray(fallback, float)
    sigma = fallback.copy()
    used = np.zeros(y.shape[1], dtype=int)
    for c in range(y.shape[1]):
        d, _ = channel_differences(t, y[:, c])
        used[c] = d.shape[0]
        if used[c] < MIN_DIFFERENCES:
            continue
        sigma[c] = max(mad_sigma(d), FLOOR_RATIO * fallback[c])
    return sigma, used


def reading_z(sigma: FloatArray, used: np.ndarray, configured: FloatArray) -> FloatArray:
    """How far each channel's reading (sigma [c], from `used` differences each) lies from
    the configured sigma, in the reading's standard errors: below -CLEARLY the sensor is
    clearly better than configured; above CLEARLY it is noisier, or the motion is as rough
    as noise. NaN for a channel without a reading of its own."""
    m = np.asarray(used, float)
    spread = READING_SPREAD / np.sqrt(np.maximum(m, 1.0))
    z = (np.asarray(sigma, float) / np.asarray(configured, float) - 1.0) / spread
    return np.where(m >= MIN_DIFFERENCES, z, np.nan)


class NoiseReading(NamedTuple):
    """Each channel's noise as a restart read it from the data."""

    sigma: tuple[float, ...]
    differences: tuple[int, ...]
    """Differences each channel's reading took (below MIN_DIFFERENCES: none of its own,
    the configured sigma)."""


def sigma_to_use(
    t: FloatArray, y: FloatArray, configured: FloatArray
) -> tuple[FloatArray, NoiseReading]:
    """("auto") Each channel's measurement sigma for a re-run over observations y [N x c]
    at times t [N]: the data's reading where it is clearly below the configured sigma
    (reading_z < -CLEARLY), else the configured one; and the reading itself."""
    sigma, used = noise_from_differences(t, y, configured)
    reading = NoiseReading(tuple(float(v) for v in sigma), tuple(int(n) for n in used))
    taken = np.where(reading_z(sigma, used, configured) < -CLEARLY, sigma, configured)
    return taken, reading


def scaled(
    tunings: dict[FilterKind, Tuning], noise_scale: FloatArray | None
) -> dict[FilterKind, Tuning]:
    """The tunings with each channel's measurement variance times noise_scale [c] (None:
    as they are)."""
    if noise_scale is None:
        return tunings
    n = next(iter(tunings.values())).R.shape[0]
    root = np.ones(n)  # channels a shorter scale does not name (h_dot) as they are
    root[: len(noise_scale)] = np.sqrt(noise_scale)
    return {k: tn._replace(R=tn.R * np.outer(root, root)) for k, tn in tunings.items()}
