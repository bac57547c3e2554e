"""Summaries of a finished run: accuracy, consistency and convergence per filter."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from gcs_estimator.arrays import FloatArray
from gcs_estimator.estimator import EstimatorResult, FilterKind

CONVERGENCE_BAND = 0.05
"""Convergence: the estimate stays within 5 % (docs/model.md)."""


@dataclass(frozen=True)
class CoefficientSummary:
    """Final figures of one coefficient in one filter."""

    name: str
    estimate: float
    sigma: float
    truth: float | None
    error_pct: float | None
    """100 * (estimate - truth) / |truth|."""
    z: float | None
    """(estimate - truth) / sigma."""
    converged_final_s: float
    """Time after which the estimate stays within 5 % of its final value [s] (NaN: never)."""
    converged_truth_s: float | None
    """Time after which it stays within 5 % of truth [s] (NaN: never; None: no truth)."""


@dataclass(frozen=True)
class FilterSummary:
    kind: FilterKind
    coefficients: tuple[CoefficientSummary, ...]
    mean_nis: float
    """Mean NIS over the updates after the last restart (the filter as it runs on)."""
    mean_nis_all: float
    """Mean NIS over every update, the zero-start transient included."""
    mean_channels: float
    """Average number of observation channels per update (the NIS degrees of freedom)."""
    nees: float | None
    """Final (x - truth)^T P^-1 (x - truth) over the coefficients; None without truth."""
    steps: int
    gust_sigma: float = 0.0
    """Turbulence level (vertical gust sigma) the filter ended with [m/s]."""


def percent_error(estimate: float, reference: float) -> float | None:
    """100 * (estimate - reference) / |reference|; None for a zero reference."""
    if reference == 0.0:
        return None
    return 100.0 * (estimate - reference) / abs(reference)


def stay_within_time(t: FloatArray, values: FloatArray, target: float, band: float) -> float:
    """First time after which values stay within band*|target| of target [s]; NaN if the
    last value is outside. A target of 0 has no relative band: NaN."""
    if len(values) == 0 or target == 0.0 or not math.isfinite(target):
        return math.nan
    outside = np.abs(values - target) > band * abs(target)
    if outside[-1]:
        return math.nan
    idx = np.flatnonzero(outside)
    return float(t[0]) if len(idx) == 0 else float(t[idx[-1] + 1])


def summarise(result: EstimatorResult, truth: FloatArray | None) -> dict[FilterKind, FilterSummary]:
    """Figures for each filter of a finished run (needs the estimator's history)."""
    out: dict[FilterKind, FilterSummary] = {}
    restarts = result.config.filter.restart_times_s
    for kind, fr in result.filters.items():
        track = fr.track
        if track is None or len(track.t) == 0:
            continue
        x = fr.coefficients
        t0 = float(track.t[0])
        coeffs = []
        for i, name in enumerate(result.names):
            series = track.coefficients[:, i]
            tru = None if truth is None else float(truth[i])
            coeffs.append(
                CoefficientSummary(
                    name=name,
                    estimate=float(x[i]),
                    sigma=float(fr.sigma[i]),
                    truth=tru,
                    error_pct=None if tru is None else percent_error(float(x[i]), tru),
                    z=None if tru is None else float((x[i] - tru) / fr.sigma[i]),
                    converged_final_s=stay_within_time(
                        track.t, series, float(x[i]), CONVERGENCE_BAND
                    )
                    - t0,
                    converged_truth_s=None
                    if tru is None
                    else stay_within_time(track.t, series, tru, CONVERGENCE_BAND) - t0,
                )
            )
        used = track.n_used > 0
        settled = used & (track.t - t0 > (restarts[-1] if restarts else -1.0))
        nees = None
        if truth is not None:
            d = x - truth
            nees = float(d @ np.linalg.solve(fr.covariance, d))
        out[kind] = FilterSummary(
            kind=kind,
            coefficients=tuple(coeffs),
            mean_nis=float(track.nis[settled].mean()) if settled.any() else math.nan,
            mean_nis_all=float(track.nis[used].mean()) if used.any() else math.nan,
            mean_channels=float(track.n_used[settled].mean()) if settled.any() else math.nan,
            nees=nees,
            steps=len(track.t),
            gust_sigma=fr.gust_sigma,
        )
    return out
