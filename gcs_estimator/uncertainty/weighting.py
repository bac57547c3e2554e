"""The structure check: how far each coefficient depends on how much each channel is
trusted, as an uncertainty the covariance does not hold (docs/decisions/0017).

A filter weighs every channel by the inverse of its measurement noise. Where the model
holds, the channels agree on the coefficients: trusting one of them less loses some of
its information and moves the estimates only as far as that lost information allows,
which the covariance predicts (the variance of the move is the variance gained; Hausman
1978). Where the model's structure misses something the aircraft does, the channels
pull towards different values, and the estimate is a compromise set by the weights: it
moves further than the covariance predicts, and no data from the same manoeuvre can say
which weighting is right.

So, at the end of a run, its final pass is replayed through both filters over the run's
history, once as it ran and once per channel the data carry with that channel's
measurement variance doubled (its weight halved): d_i, the move of the estimates in
replay i, beyond the variance the covariance predicts for it, is the estimate's
sensitivity to that channel's weight. Each weight is taken as
known within a factor of 2 either way (log-uniform: Var(ln w) = (ln 2)^2 / 3), so to
first order the estimate's variance from the weights is

    sum_i max(0, d_i^2 - |sigma_i^2 - sigma^2|) / 3,

the structure sigma. The sigma to trust (sigma.trusted_sigma) adds it in quadrature to
the covariance's sigma widened by how the estimates moved over the run (0008): that
correction sees drift and colour, this one a bias that the channels' disagreement sets
and the estimates settle on.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numpy as np

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import AircraftConfig
from gcs_estimator.estimation.estimator import FILTER_KINDS, Estimator, FilterKind
from gcs_estimator.model.channels import N_OBS, OBS_NAMES

VARIANCE_FACTOR = 2.0
"""A channel's measurement variance is multiplied by this in its run (its weight
halved)."""
WEIGHT_SHARE = 1.0 / 3.0
"""Var(ln w) / (ln VARIANCE_FACTOR)^2 for a weight known within VARIANCE_FACTOR either
way (log-uniform)."""


class StructureCheck(NamedTuple):
    """The check's outcome for one vehicle."""

    sigma: dict[FilterKind, FloatArray]
    """Per filter, per coefficient: the structure sigma (empty when skipped)."""
    moves: dict[FilterKind, FloatArray]
    """Per filter, [channels x coefficients]: how far each estimate moved with that
    channel's weight halved."""
    channels: tuple[str, ...] = ()
    """The channels re-weighted (those the data carry)."""
    skipped: str = ""
    """Why the check was not made ("" when it was)."""


def skipped(reason: str) -> StructureCheck:
    return StructureCheck({}, {}, (), reason)


def why_not(config: AircraftConfig, frames: int, history: bool, checked: int = 0) -> str:
    """Why the check is not made for a vehicle's run of `frames` frames, `checked` frames
    of the session's other vehicles having been checked before it ("" when it is)."""
    mode = config.filter.structure_check
    if mode == "off":
        return "filter.structure_check is off"
    if not history:
        return "the run kept no history to replay"
    if frames < 2:
        return "too few frames"
    limit = config.filter.structure_check_max_frames
    if mode == "auto" and checked + frames > limit:
        others = f" (with the {checked} of the vehicles checked before it)" if checked else ""
        return (
            f"{frames} frames{others}, more than filter.structure_check_max_frames = "
            f'{limit} (set it higher, or filter.structure_check = "on")'
        )
    return ""


def _final(
    est: Estimator, t: FloatArray, u: FloatArray, y: FloatArray, scale: FloatArray | None
) -> dict[FilterKind, tuple[FloatArray, FloatArray]]:
    """Each filter's final coefficients and their covariance sigma with the run's final
    pass replayed over the record, the measurement variances times scale."""
    again = Estimator(est.config, backend=est.backend, keep_history=False, noise_scale=scale)
    again.replay_final_pass(est, t, u, y)
    coef = again.model.coefficients
    out: dict[FilterKind, tuple[FloatArray, FloatArray]] = {}
    for kind, state in again.states.items():
        if state is not None:
            out[kind] = (state.x[coef].copy(), np.sqrt(np.diag(state.P))[coef])
    return out


def structure_check(est: Estimator, t: FloatArray, u: FloatArray, y: FloatArray) -> StructureCheck:
    """The check of a finished run (est) over its frames (t [N], u [N x 3] as the
    equations take them, y [N x 7]: its history): its final pass replayed as it ran, then
    once per channel with data, that channel's weight halved."""
    if np.any(np.diff(t) <= 0.0):
        return skipped("the vehicle clock restarted during the run (its frames are not one record)")
    channels = _with_data(y)
    if not channels:
        return skipped("no channel has data")
    scales: list[FloatArray | None] = [None]
    for ch in channels:
        scale = np.ones(N_OBS)
        scale[ch] = VARIANCE_FACTOR
        scales.append(scale)
    # The replays are independent and spend most of their time in compiled steps that
    # release the GIL: threads run them side by side on the machine's cores.
    with ThreadPoolExecutor(max_workers=min(len(scales), os.cpu_count() or 1)) as pool:
        base, *finals = pool.map(lambda sc: _final(est, t, u, y, sc), scales)
    if set(base) != set(FILTER_KINDS):
        return skipped("no frame reached the filters")
    p = base[FILTER_KINDS[0]][0].shape[0]
    moves = {k: np.zeros((len(channels), p)) for k in FILTER_KINDS}
    excess = {k: np.zeros(p) for k in FILTER_KINDS}
    for a, run in enumerate(finals):
        for kind in FILTER_KINDS:
            (b, s), (v, vs) = base[kind], run[kind]
            d = v - b
            moves[kind][a] = d
            excess[kind] += np.maximum(0.0, d * d - np.abs(vs * vs - s * s))
    sigma = {k: np.sqrt(WEIGHT_SHARE * excess[k]) for k in FILTER_KINDS}
    return StructureCheck(sigma, moves, tuple(OBS_NAMES[i] for i in channels))


def _with_data(y: FloatArray) -> list[int]:
    """The channels the check re-weights: those with data."""
    return [i for i in range(N_OBS) if np.isfinite(y[:, i]).any()]


def runs(y: FloatArray) -> int:
    """How many replays of the final pass the check takes."""
    return 1 + len(_with_data(y))
