"""Summaries of a finished run: accuracy, consistency and convergence per filter."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import AircraftConfig
from gcs_estimator.estimation.filters.core import FilterKind
from gcs_estimator.estimation.history import Track
from gcs_estimator.estimation.results import EstimatorResult, FilterResult
from gcs_estimator.model.channels import N_OBS, OBS_NAMES
from gcs_estimator.uncertainty.sigma import SigmaParts, TrustedSigma, filter_sigma

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


ALPHA = OBS_NAMES.index("alpha")


def needs_alpha_level(name: str) -> bool:
    """A coefficient only an informed angle of attack fixes (a vane, or a climb rate where
    the vertical wind is told apart: _alpha_absent): an intercept (CD0, CL0, Cm0) or an
    alpha derivative (CDa, CLa, Cma). Without either the filters reconstruct alpha from
    the dynamics alone, and an offset in it moves these and nothing the data can see."""
    return name.endswith("0") or name[2:].startswith("a")


def without_alpha(names: tuple[str, ...], marks: tuple[str, ...]) -> tuple[str, ...]:
    """The marks where the record holds no alpha at all: the intercepts and alpha
    derivatives not identified, every other coefficient weak at best (alpha's unmeasured
    motion enters each force and moment with it). On a simulated flight written as a PX4
    log the sigmas alone left CL0 "identified" 24 sigma from truth (decision 0045)."""
    out = []
    for name, mark in zip(names, marks, strict=True):
        if needs_alpha_level(name):
            out.append(NOT_IDENTIFIED)
        else:
            out.append(WEAK if mark == IDENTIFIED else mark)
    return tuple(out)


HDOT = OBS_NAMES.index("h_dot")
CALM_FOR_CLIMB_MPS = 0.1
"""Vertical gust level [m/s] (the pass's average) up to which a climb rate informs alpha:
above it the vertical wind moves the air's alpha against the path's, which the climb
rate sees, and the two are not told apart (decision 0049: with gust states too, on the
NOC mission in light turbulence the estimates missed by up to 26 sigma)."""


def told_alpha_level(config: AircraftConfig) -> float:
    """The vertical gust level [m/s] that the configured process noise on alpha
    ([filter.process_noise] alpha) is worth, at the turbulence model's density per unit
    sigma_w^2 at trim: alpha moving in ways the model does not explain, which the filters
    cannot tell from a vertical wind's (decision 0085). The shipped density is worth
    about a thousandth of CALM_FOR_CLIMB_MPS."""
    unit = config.filter.turbulence.unit(config.airframe.trim_airspeed_mps)[1]
    told = config.filter.process_noise.states[1]
    return math.sqrt(told / unit) if unit > 0.0 and told > 0.0 else 0.0


def _alpha_absent(track: Track, told_level: float = 0.0) -> bool:
    """Whether nothing informs alpha's level: no vane, and no climb rate or a climb rate
    in air that moved: the pass's gust level, with told_level (told_alpha_level) beside
    it, above CALM_FOR_CLIMB_MPS. A process noise on alpha set from a filter-error fit
    takes up the innovations the gust level would have read, so the gust level alone
    would call such air calm."""
    y = np.asarray(track.y)
    if not (y.ndim == 2 and y.shape[0] > 0) or np.isfinite(y[:, ALPHA]).any():
        return False
    if y.shape[1] <= HDOT or not np.isfinite(y[:, HDOT]).any():
        return True
    gust = np.asarray(track.gust_pass_sigma, float)
    level = float(gust[-1]) if gust.size and np.isfinite(gust[-1]) else 0.0
    return math.hypot(level, told_level) > CALM_FOR_CLIMB_MPS


def moves_with_alpha(name: str) -> bool:
    """A coefficient an uninformed alpha drags (with_alpha_confound): those only alpha's
    level fixes (needs_alpha_level), and the pitch-rate derivatives (CLq, Cmq), which in
    the short period take what alpha's excursions leave (q and alpha-dot move together):
    on the NOC mission in light turbulence without a vane they missed by 2 to 7 sigmas
    where the elevator derivatives stayed within 2."""
    return needs_alpha_level(name) or name[2:].startswith("q")


def with_alpha_confound(
    names: tuple[str, ...], prior: FloatArray, structure: FloatArray | None
) -> FloatArray:
    """The structure sigma with what an uninformed alpha leaves undecided (decision 0060):
    each coefficient alpha's level and excursions drag (moves_with_alpha) known no better
    than before the flight, its prior sigma added in quadrature; the others as they
    were. Without a vane, in air that moves, the filters' alpha takes the vertical wind
    with the manoeuvre, and their covariance does not hold it: on the NOC mission in
    light turbulence CLa and Cma came out at half their truth, 25 to 70 covariance
    sigmas off, with the gust level right and with gust states alike."""
    base = np.zeros(len(names)) if structure is None else np.nan_to_num(structure, nan=0.0)
    confound = np.array(
        [float(prior[i]) if moves_with_alpha(n) else 0.0 for i, n in enumerate(names)]
    )
    return np.asarray(np.hypot(base, confound))


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
    """The sigma to trust (sigma.trusted_sigma): the covariance's, widened by how far the
    estimate moved against it and by the structure check."""
    sigma_parts: SigmaParts
    """What sigma is made of (covariance sigma, movement factor, structure sigma)."""
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
    """IDENTIFIED, WEAK or NOT_IDENTIFIED (identifiability(), from sigma)."""
    correlated_with: str = ""
    """The coefficient it correlates with most."""
    correlation: float = 0.0
    """That correlation."""


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
    tracks = [fr.track for fr in result.filters.values() if fr.track is not None]
    told = told_alpha_level(result.config)
    # One air for both filters: where either reads it moving, neither's alpha is told
    # apart from the vertical wind. A filter whose alpha took the wind in reads calmer
    # air (a JSBSim mission flight in steady wind and light turbulence: the EKF 0.115
    # m/s, the IEKF 0.065 with CLa near zero, marked weak instead of not identified).
    absent = any(_alpha_absent(t, told) for t in tracks if len(t.t) > 0)
    for kind, fr in result.filters.items():
        track = fr.track
        if track is None or len(track.t) == 0:
            continue
        struct = None if structure is None else structure.get(kind)
        prior = np.asarray(result.config.filter.initial_sigma.coefficients)
        if absent:
            struct = with_alpha_confound(result.names, prior, struct)
        trusted = filter_sigma(
            track.coefficients, track.coefficient_sigma, fr.sigma, result.final_pass_from, struct
        )
        corr = correlation_of(fr.covariance)
        marks = identifiability(fr.coefficients, trusted.sigma, corr, prior)
        if absent:
            marks = without_alpha(result.names, marks)
        coeffs = tuple(
            _coefficient(result.names, i, fr.coefficients, trusted, track, truth, corr, marks[i])
            for i in range(len(result.names))
        )
        out[kind] = _filter_summary(result, fr, track, coeffs, truth)
    return out


def _coefficient(
    names: tuple[str, ...],
    i: int,
    x: FloatArray,
    trusted: TrustedSigma,
    track: Track,
    truth: FloatArray | None,
    corr: FloatArray,
    mark: str,
) -> CoefficientSummary:
    """Coefficient i's figures: x the final estimates, trusted their sigma."""
    t0 = float(track.t[0])
    series = track.coefficients[:, i]
    tru = None if truth is None else float(truth[i])
    partner, rho = most_correlated(corr, names, i)
    return CoefficientSummary(
        name=names[i],
        estimate=float(x[i]),
        sigma=float(trusted.sigma[i]),
        sigma_parts=trusted.parts(i),
        truth=tru,
        error_pct=None if tru is None else percent_error(float(x[i]), tru),
        z=None if tru is None else float((x[i] - tru) / trusted.sigma[i]),
        converged_final_s=stay_within_time(track.t, series, float(x[i]), CONVERGENCE_BAND) - t0,
        converged_truth_s=None
        if tru is None
        else stay_within_time(track.t, series, tru, CONVERGENCE_BAND) - t0,
        identifiability=mark,
        correlated_with=partner,
        correlation=rho,
    )


def _filter_summary(
    result: EstimatorResult,
    fr: FilterResult,
    track: Track,
    coeffs: tuple[CoefficientSummary, ...],
    truth: FloatArray | None,
) -> FilterSummary:
    """A filter's figures around its coefficients': NIS over the pass that runs on (from
    the last restart's swap) and over the whole run, NEES against truth, turbulence."""
    used = track.n_used > 0
    settled = used.copy()  # the pass that runs on: from the last restart's swap
    settled[: result.final_pass_from] = False
    channel_nis = channel_mean_squares(track.innovation[settled], track.innovation_sigma[settled])
    nees = None
    if truth is not None:
        d = fr.coefficients - truth
        nees = float(d @ np.linalg.solve(fr.covariance, d))
    return FilterSummary(
        kind=fr.kind,
        coefficients=coeffs,
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


def channel_mean_squares(innovation: FloatArray, sigma: FloatArray) -> tuple[float, ...]:
    """Per channel (column), the mean of (innovation / sigma)^2 over the rows where the
    channel was used (finite and sigma > 0); NaN for a channel never used."""
    used = np.isfinite(innovation) & np.isfinite(sigma) & (sigma > 0.0)
    ratio = np.where(used, innovation / np.where(used, sigma, 1.0), 0.0)
    count = used.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count > 0, (ratio * ratio).sum(axis=0) / count, math.nan)
    return tuple(float(v) for v in mean)
