"""Summaries of a finished run: accuracy, consistency and convergence per filter."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from gcs_estimator.arrays import FloatArray
from gcs_estimator.estimation.estimator import EstimatorResult, FilterKind
from gcs_estimator.model.channels import N_OBS

CONVERGENCE_BAND = 0.05
"""Convergence: the estimate stays within 5 % (docs/model.md)."""

IDENTIFIED, WEAK, NOT_IDENTIFIED = "identified", "weak", "not identified"
"""How well the data determine a coefficient (identifiability())."""
RELATIVE_SIGMA_IDENTIFIED = 0.10
"""sigma / |estimate| at or below which a coefficient counts as identified."""
RELATIVE_SIGMA_WEAK = 0.5
"""sigma / |estimate| above which it is not identified (the data barely fix its sign)."""
CORRELATION_LIMIT = 0.95
"""|correlation| with another coefficient above which the two are not told apart."""
PRIOR_SHRINK_LIMIT = 0.5
"""A filter's sigma still above this share of its prior sigma: the data added little."""
MOVEMENT_WINDOW_MIN_FRAMES = 50
"""Frames the movement check needs after the last restart (fewer: no correction)."""
MOVEMENT_BANDWIDTH = 0.25
"""Longest lag of the movement check, as a share of its window (Bartlett weights)."""


def sigma_inflation(coefficients: FloatArray, sigma: FloatArray, start: int) -> FloatArray:
    """How much more a filter's coefficient estimates moved from frame `start` to the end
    than its own covariance said they would (variance ratio per coefficient; 1: as
    expected; NaN where the window says nothing).

    Under the filter's model the estimate of a constant is a martingale: its increments
    are uncorrelated, and the variance of their sum over the window is the variance
    the covariance lost there, sigma(start-1)^2 - sigma(end)^2. Model-structure error
    and coloured noise break both (the estimate drifts as the manoeuvre changes which
    error it absorbs, and increments correlate over seconds). The ratio of the
    increments' long-run variance (Bartlett-weighted autocovariance up to a quarter of
    the window) to that loss is the factor by which the filter overcounted its
    information; sigma * sqrt(max(1, ratio)) is the corrected sigma. It is the filter's
    analogue of the Morelli-Klein correction of an output-error fit's Cramer-Rao bound
    (docs/decisions/0008).

    The weighted sum is taken in O(N) as the sum of squared moving sums: with the
    increments d zero-padded, sum_t (d_t + ... + d_t+L)^2 = sum_k (L + 1 - |k|) acov(k),
    and a moving sum of increments is a difference of two estimates."""
    p = coefficients.shape[1]
    w = coefficients.shape[0] - start
    if start < 1 or w < MOVEMENT_WINDOW_MIN_FRAMES:
        return np.full(p, np.nan)
    s2 = np.asarray(sigma[[start - 1, -1]], float) ** 2
    lag = max(1, int(MOVEMENT_BANDWIDTH * w))
    # Moving sums of lag + 1 increments d_t .. d_t+lag for t = -lag .. w - 1 (the
    # increments outside 0 .. w - 1 are zero): x[hi] - x[lo] with x the estimates.
    t = np.arange(-lag, w)
    hi = np.minimum(t + lag, w - 1) + 1
    lo = np.maximum(t, 0)
    moved = np.empty(p)
    for j in range(p):  # one column at a time: an hour's history stays a few MB
        x = np.asarray(coefficients[start - 1 :, j], float)
        sums = x[hi] - x[lo]
        moved[j] = (sums @ sums) / (lag + 1)
    expected = s2[0] - s2[1]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(expected > 1e-6 * s2[0], moved / expected, np.nan)
    return np.asarray(ratio)


def movement_start(frames: int, final_pass_from: int) -> int:
    """First frame of the movement check: the second half of the run, and never before
    the final pass's second frame (a pass converging from its prior moves by design)."""
    return max(frames // 2, final_pass_from + 1, 1)


def correlation_of(cov: FloatArray) -> FloatArray:
    """Correlation matrix of a covariance."""
    s = np.sqrt(np.maximum(np.diag(cov), 1e-300))
    return np.asarray(cov / np.outer(s, s))


def identifiability(
    estimate: FloatArray,
    sigma: FloatArray,
    correlation: FloatArray,
    prior_sigma: FloatArray | None = None,
) -> tuple[str, ...]:
    """IDENTIFIED / WEAK / NOT_IDENTIFIED per coefficient. Not identified: the sigma is
    above half the estimate's magnitude (the data barely fix its sign), or, for a
    filter, still above half the prior's (the manoeuvre added little information). Weak:
    the sigma is above a tenth of the magnitude, or the coefficient correlates above
    0.95 with another (the data do not tell the two apart). Else identified."""
    out = []
    p = len(estimate)
    for i in range(p):
        rel = sigma[i] / max(abs(float(estimate[i])), 1e-300)
        corr = max((abs(float(correlation[i, j])) for j in range(p) if j != i), default=0.0)
        shrink = 0.0 if prior_sigma is None else sigma[i] / prior_sigma[i]
        if rel > RELATIVE_SIGMA_WEAK or shrink > PRIOR_SHRINK_LIMIT:
            out.append(NOT_IDENTIFIED)
        elif rel > RELATIVE_SIGMA_IDENTIFIED or corr > CORRELATION_LIMIT:
            out.append(WEAK)
        else:
            out.append(IDENTIFIED)
    return tuple(out)


def most_correlated(correlation: FloatArray, names: tuple[str, ...], i: int) -> tuple[str, float]:
    """The coefficient most correlated with coefficient i, and that correlation."""
    best, value = "", 0.0
    for j, n in enumerate(names):
        if j != i and abs(float(correlation[i, j])) > abs(value):
            best, value = n, float(correlation[i, j])
    return best, value


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
    identifiability: str = IDENTIFIED
    """IDENTIFIED, WEAK or NOT_IDENTIFIED (identifiability())."""
    correlated_with: str = ""
    """The coefficient it correlates with most."""
    correlation: float = 0.0
    """That correlation."""
    corrected_sigma: float = math.nan
    """sigma corrected for how far the estimate moved against its covariance
    (sigma_inflation()) and, where the structure check was made, with its structure sigma
    added in quadrature (weighting.py); NaN: the run was too short to tell."""
    sigma_inflation: float = math.nan
    """corrected_sigma / sigma (at least 1; NaN: the run was too short to tell)."""
    structure_sigma: float = math.nan
    """How far the estimate depends on how much each channel is trusted, beyond what its
    covariance allows (weighting.structure_check; NaN: not checked)."""

    @property
    def trusted_sigma(self) -> float:
        """The corrected sigma where there is one, else the covariance's."""
        return self.corrected_sigma if math.isfinite(self.corrected_sigma) else self.sigma


@dataclass(frozen=True)
class FilterSummary:
    kind: FilterKind
    coefficients: tuple[CoefficientSummary, ...]
    mean_nis: float
    """Mean NIS over the updates of the pass that runs on (from the last restart's swap)."""
    mean_nis_all: float
    """Mean NIS over every update, the zero-start transient included."""
    mean_channels: float
    """Average number of observation channels per update (the NIS degrees of freedom)."""
    nees: float | None
    """Final (x - truth)^T P^-1 (x - truth) over the coefficients; None without truth."""
    steps: int
    gust_sigma: float = 0.0
    """Turbulence level (vertical gust sigma) the filter ended with [m/s]."""
    gust_on_share: float = 0.0
    """Share of the frames since the last restart's swap (the pass that ran on to the end)
    in which the turbulence level was applied."""
    gust_pass_sigma: float = 0.0
    """Turbulence level averaged over that pass [m/s] (FilterResult.gust_pass_sigma)."""
    gust_pass_z: float = math.nan
    """That average in its standard errors (NaN: not measured)."""
    channel_nis: tuple[float, ...] = (math.nan,) * N_OBS
    """Per observation channel (OBS_NAMES order), the mean of (innovation / its predicted
    sigma)^2 over the same updates as mean_nis: 1 where the filter's noise model and
    dynamics account for what the channel shows (NaN: no update used the channel)."""


def _share_on(gust_sigma: FloatArray) -> float:
    """Share of the frames with a turbulence level applied (0 for none)."""
    return float(np.mean(gust_sigma > 0.0)) if len(gust_sigma) else 0.0


ZERO_REFERENCE = 1e-9
"""A reference value this small is zero up to rounding (a least-squares reference of a
term the aerodynamics lack comes out near 1e-14): no error in percent of it."""


def percent_error(estimate: float, reference: float) -> float | None:
    """100 * (estimate - reference) / |reference|; None for a zero reference (one within
    ZERO_REFERENCE of zero)."""
    if abs(reference) < ZERO_REFERENCE:
        return None
    return 100.0 * (estimate - reference) / abs(reference)


def stay_within_time(t: FloatArray, values: FloatArray, target: float, band: float) -> float:
    """First time after which values stay within band*|target| of target [s]; NaN if the
    last value is outside. A target of 0 has no relative band: NaN."""
    if len(values) == 0 or abs(target) < ZERO_REFERENCE or not math.isfinite(target):
        return math.nan
    outside = np.abs(values - target) > band * abs(target)
    if outside[-1]:
        return math.nan
    idx = np.flatnonzero(outside)
    return float(t[0]) if len(idx) == 0 else float(t[idx[-1] + 1])


def summarise(
    result: EstimatorResult,
    truth: FloatArray | None,
    structure: Mapping[FilterKind, FloatArray] | None = None,
) -> dict[FilterKind, FilterSummary]:
    """Figures for each filter of a finished run (needs the estimator's history);
    structure: each filter's structure sigma per coefficient (weighting.py), where the
    check was made."""
    out: dict[FilterKind, FilterSummary] = {}
    for kind, fr in result.filters.items():
        track = fr.track
        if track is None or len(track.t) == 0:
            continue
        x = fr.coefficients
        t0 = float(track.t[0])
        corr = correlation_of(fr.covariance)
        start = movement_start(len(track.t), result.final_pass_from)
        ratio = sigma_inflation(track.coefficients, track.coefficient_sigma, start)
        corrected = fr.sigma * np.sqrt(np.maximum(ratio, 1.0))
        struct = None if structure is None else structure.get(kind)
        if struct is not None:
            corrected = np.hypot(np.where(np.isfinite(corrected), corrected, fr.sigma), struct)
        with np.errstate(divide="ignore", invalid="ignore"):
            factor = corrected / fr.sigma
        trusted = np.where(np.isfinite(corrected), corrected, fr.sigma)
        marks = identifiability(
            x, trusted, corr, np.asarray(result.config.filter.initial_sigma.coefficients)
        )
        coeffs = []
        for i, name in enumerate(result.names):
            series = track.coefficients[:, i]
            tru = None if truth is None else float(truth[i])
            partner, rho = most_correlated(corr, result.names, i)
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
                    identifiability=marks[i],
                    correlated_with=partner,
                    correlation=rho,
                    corrected_sigma=float(corrected[i]),
                    sigma_inflation=float(factor[i]),
                    structure_sigma=math.nan if struct is None else float(struct[i]),
                )
            )
        used = track.n_used > 0
        settled = used.copy()  # the pass that runs on: from the last restart's swap
        settled[: result.final_pass_from] = False
        channel_nis = channel_mean_squares(
            track.innovation[settled], track.innovation_sigma[settled]
        )
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
            gust_on_share=_share_on(track.gust_sigma[result.final_pass_from :]),
            gust_pass_sigma=fr.gust_pass_sigma,
            gust_pass_z=fr.gust_pass_z,
            channel_nis=channel_nis,
        )
    return out


def channel_mean_squares(innovation: FloatArray, sigma: FloatArray) -> tuple[float, ...]:
    """Per channel (column), the mean of (innovation / sigma)^2 over the rows where the
    channel was used (finite and sigma > 0); NaN for a channel never used."""
    used = np.isfinite(innovation) & np.isfinite(sigma) & (sigma > 0.0)
    ratio = np.where(used, innovation / np.where(used, sigma, 1.0), 0.0)
    count = used.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count > 0, (ratio * ratio).sum(axis=0) / count, math.nan)
    return tuple(float(v) for v in mean)
