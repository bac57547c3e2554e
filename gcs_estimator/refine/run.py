"""A finished run refined: `refine_run` fits the frames the filters saw, from filter
`kind`'s estimate, by the method "auto" chooses from what the filters found
(choose_method; decision 0025), and compares the fit with that filter (sigma)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from gcs_estimator.arrays import FloatArray, IntArray
from gcs_estimator.config import REFINE_METHODS, AircraftConfig
from gcs_estimator.estimation.filters.core import MAX_GAP_S, MAX_STEP_S, FilterKind
from gcs_estimator.estimation.history import Track
from gcs_estimator.estimation.results import EstimatorResult, FilterResult
from gcs_estimator.model import equations as eq
from gcs_estimator.model.aircraft import Model, build_model
from gcs_estimator.model.channels import N_FLIGHT
from gcs_estimator.refine.fit import refine
from gcs_estimator.refine.result import Refined, RefineError, RefineProgress
from gcs_estimator.uncertainty.sigma import FilterEstimate, trusted_sigma
from gcs_estimator.uncertainty.weighting import THRUST_PARTS

if TYPE_CHECKING:
    from gcs_estimator.uncertainty.result import VehicleResult
    from gcs_estimator.uncertainty.weighting import StructureCheck

TURBULENT_SHARE = 0.5
"""method "auto", where the filters measured no level over the pass (a fixed level:
[filter.turbulence] adaptive = false): filter error when the level was applied in at
least this share of the final pass."""


THROTTLE_EXCITED = 0.1
"""The throttle's (or thrust's) delay is fitted where the input moves over more than this
share of its largest magnitude in the record (decision 0044): a throttle held still has
no timing the data can show."""


def delayed_inputs(u: FloatArray) -> tuple[int, ...]:
    """The model inputs (u [N x m], model order) whose delay a fit estimates: the elevator
    always (a record that never moves it has no delay seen, and the fit leaves it at 0
    without a sigma), the throttle where it moves (THROTTLE_EXCITED)."""
    throttle = u[:, 1][np.isfinite(u[:, 1])]
    top = float(np.max(np.abs(throttle))) if throttle.size else 0.0
    moves = top > 0.0 and float(np.ptp(throttle)) > THROTTLE_EXCITED * top
    return (0, 1) if moves else (0,)


def _filter(result: EstimatorResult, kind: FilterKind) -> tuple[FilterResult, Track]:
    """Filter `kind`'s result and its history, which the fit needs."""
    fr = result.filters.get(kind)
    if fr is None or fr.track is None or len(fr.track.t) == 0:
        raise RefineError("no frames to refine (the run kept no history or saw no data)")
    return fr, fr.track


def choose_method(result: EstimatorResult, kind: FilterKind = "IEKF") -> tuple[str, str]:
    """The whole-record fit for this run ("auto"; decision 0025): filter error where
    filter `kind`'s turbulence level averaged over its final pass stands at least
    [filter.turbulence] detection_sigma standard errors above zero (the filters found
    turbulence in the record as a whole), output error otherwise; and why, in words. With
    no level measured (a fixed one), filter error where it was applied in at least
    TURBULENT_SHARE of the pass."""
    fr, track = _filter(result, kind)
    threshold = result.config.filter.turbulence.detection_sigma
    if math.isfinite(fr.gust_pass_z):
        turbulent = fr.gust_pass_z >= threshold
        seen = (
            f"the {kind}'s turbulence level over its final pass, σ_w {fr.gust_pass_sigma:.2f} "
            f"m/s, is {fr.gust_pass_z:+.1f} standard errors from zero (turbulent from "
            f"{threshold:g})"
        )
    else:
        level = track.gust_sigma[result.final_pass_from :]
        share = float(np.mean(level > 0.0)) if level.size else 0.0
        seen = f"the {kind} applied a turbulence level in {100.0 * share:.0f} % of its final pass"
        turbulent = share >= TURBULENT_SHARE
    if turbulent:
        return "filter-error", f"{seen}: turbulent air, so filter error"
    return "output-error", f"{seen}: calm air, so output error"


def _frames(t: FloatArray, window_s: tuple[float | None, float | None]) -> IntArray:
    """The frames within window_s (seconds after the first frame), each at a later time
    than the one before: frames repeated at one time (a clock that stalled) carry no new
    interval to fly."""
    rel = t - t[0]
    lo = -math.inf if window_s[0] is None else window_s[0]
    hi = math.inf if window_s[1] is None else window_s[1]
    idx = np.flatnonzero((rel >= lo) & (rel <= hi))
    if idx.size:
        idx = idx[np.concatenate([[True], np.diff(t[idx]) > 0.0])]
    if idx.size < 10:
        raise RefineError(f"only {idx.size} frames in the window {window_s}; 10 needed")
    return idx


def _start(model: Model, fr: FilterResult, track: Track, first: int) -> FloatArray:
    """The fit's starting augmented state: the filter's final coefficients and biases, and
    the flight states measured at frame `first` (the filter's where not measured)."""
    start = np.zeros(model.n)
    start[model.coefficients] = fr.coefficients
    start[model.biases] = fr.biases
    measured = track.y[first, :N_FLIGHT] - _bias_on_flight(model, fr.biases)
    start[:N_FLIGHT] = np.where(np.isfinite(measured), measured, track.x[first, :N_FLIGHT])
    return start


def _pieces(
    result: EstimatorResult, model: Model, fr: FilterResult, track: Track, idx: IntArray
) -> list[tuple[int, FloatArray]]:
    """Where the frames idx are several pieces (a segment or a flight began afresh, or a
    gap longer than MAX_GAP_S: decision 0050), each further piece's first frame (in idx)
    and its start (_start)."""
    firsts = {int(j) for j in np.searchsorted(idx, np.asarray(result.fresh_frames, int))}
    gaps = np.flatnonzero(np.diff(track.t[idx]) > MAX_GAP_S) + 1
    firsts |= {int(j) for j in gaps}
    return [(j, _start(model, fr, track, int(idx[j]))) for j in sorted(firsts) if 0 < j < len(idx)]


def refine_run(
    run: EstimatorResult | VehicleResult,
    method: str = "auto",
    kind: FilterKind = "IEKF",
    window_s: tuple[float | None, float | None] = (None, None),
    progress: Callable[[RefineProgress], None] | None = None,
    hold_noise: bool = False,
    threads: int | None = None,
    estimate_delays: bool | None = None,
) -> Refined:
    """Refine a finished run (an estimator's result, or a session's vehicle): fit the
    frames the estimator saw (optionally only those within window_s, seconds after the
    first frame), starting from filter `kind`'s final coefficients and biases and the
    first frame's measured flight states. method "auto": the one choose_method picks,
    with its reason in the fit's `choice`. hold_noise: the noise levels stay instead of
    being estimated: the measurement noise where the filters' final pass had it (the
    config's [filter] measurement_sigma, or the data's where measurement_noise = "auto"
    took it), the process noise at the config's. threads: as refine's. The fit's sigma
    takes in how far it lands from filter `kind` (decision 0030), and a vehicle whose
    session made the structure check brings that filter's structure sigma, which the
    fit's own does not fall below (decision 0031). estimate_delays (default: [data]
    estimate_input_delay): the inputs' delays (delayed_inputs) are fitted with the
    coefficients (decision 0044), and the floor
    then leaves out the filter's timing part (the fit decides the timing itself)."""
    result = run if isinstance(run, EstimatorResult) else run.result
    if estimate_delays is None:
        estimate_delays = result.config.data.estimate_input_delay
    factors = thrust_factors(result.config)
    filter_structure = None
    propeller = None
    left_out = False
    check = None if isinstance(run, EstimatorResult) else run.structure
    if check is not None and not check.skipped:
        left = _left_parts(estimate_delays, bool(factors))
        left_out = bool(left & set(check.parts))
        filter_structure = _filter_structure(check, kind, left)
        propeller = _propeller_part(check, kind) if factors else None
    if method not in REFINE_METHODS:
        raise ValueError(f"refine method {method!r}: allowed {list(REFINE_METHODS)}")
    choice = ""
    if method == "auto":
        method, choice = choose_method(result, kind)
    fr, track = _filter(result, kind)
    idx = _frames(track.t, window_s)
    config = result.config
    model = build_model(config, gust_states=False)
    tuning = config.filter
    fit = refine(
        model,
        track.t[idx],
        track.u[idx],
        track.y[idx],
        _start(model, fr, track, idx[0]),
        np.asarray(result.measurement_sigma or tuning.measurement_sigma, float),
        np.asarray(tuning.process_noise.states, float),
        MAX_STEP_S,
        linear_inputs=config.data.input_hold == "linear",
        estimate_process_noise=method == "filter-error",
        progress=progress,
        hold_noise=hold_noise,
        threads=threads,
        compared=FilterEstimate(
            fr.coefficients,
            fr.sigma if propeller is None else np.hypot(fr.sigma, propeller),
            filter_structure,
            _filter_trusted(run, kind, window_s, filter_structure if left_out else None),
        ),
        delayed=delayed_inputs(track.u[idx]) if estimate_delays else (),
        factors=factors,
        pieces=_pieces(result, model, fr, track, idx),
    )
    configured = config.data.input_delay_s
    return replace(
        fit, choice=choice, delays_s=fit.delays_s + configured, configured_delay_s=configured
    )


def thrust_factors(config: AircraftConfig) -> tuple[tuple[int, float], ...]:
    """The propeller model's guesses a fit estimates with the coefficients (decision
    0054): the thrust (a factor on 0.5 rho S C) and the airspeed where it vanishes (a
    factor on k), each where the airframe file gives it a tolerance (its prior sigma)."""
    p = config.propulsion
    if p.model != "propeller":
        return ()
    c = p.constants(config.airframe.air_density_kgpm3)
    pairs = ((eq.PROP_COEF, c.scale_sigma), (eq.MOTOR_K, c.speed_sigma))
    return tuple((i, sd) for i, sd in pairs if sd > 0.0)


def _filter_trusted(
    run: EstimatorResult | VehicleResult,
    kind: FilterKind,
    window_s: tuple[float | None, float | None],
    structure: FloatArray | None = None,
) -> FloatArray | None:
    """Filter `kind`'s sigma to trust, the floor of the fit's sigma (decision 0057), where
    the fit reads the frames the filter was judged over (no window) and the run was
    summarised (a vehicle's). `structure`: the filter's structure sigma without the parts
    the fit decides itself (_filter_structure), which then takes the place of the whole
    in the sigma to trust (decision 0072); None: the sigma to trust as the table shows
    it."""
    if isinstance(run, EstimatorResult) or window_s != (None, None):
        return None
    summary = run.summaries.get(kind)
    if summary is None:
        return None
    if structure is None:
        return np.array([c.sigma for c in summary.coefficients])
    covariance = np.array([c.sigma_parts.covariance for c in summary.coefficients])
    factor = np.array([c.sigma_parts.movement_factor for c in summary.coefficients])
    return trusted_sigma(covariance, factor * factor, structure).sigma


def _left_parts(estimate_delays: bool, factors: bool) -> set[str]:
    """The structure check's parts a fit decides itself: the timing where it estimates
    the inputs' delay (decision 0044), the propeller's where it fits its factors (0054)."""
    return ({"timing"} if estimate_delays else set()) | (set(THRUST_PARTS) if factors else set())


def _filter_structure(check: StructureCheck, kind: FilterKind, left: set[str]) -> FloatArray | None:
    """Filter `kind`'s structure sigma, the floor of the fit's (decision 0031): without the
    parts `left` the fit decides itself (_left_parts)."""
    if not left & set(check.parts):
        return check.sigma.get(kind)
    kept = [part[kind] for name, part in check.parts.items() if name not in left]
    out: FloatArray = np.sqrt(sum(v * v for v in kept))
    return out


def _propeller_part(check: StructureCheck, kind: FilterKind) -> FloatArray | None:
    """Filter `kind`'s propeller parts of its structure sigma (decision 0054), None where
    the check has none: the filter flew the airframe file's thrust, so its estimates may
    lie that far from a fit that fits the thrust without either being wrong (the
    difference sigma, decision 0030, allows it)."""
    parts = [check.parts[p][kind] for p in THRUST_PARTS if p in check.parts]
    if not parts:
        return None
    out: FloatArray = np.sqrt(sum(v * v for v in parts))
    return out


def _bias_on_flight(model: Model, biases: FloatArray) -> FloatArray:
    """The estimated biases on the directly observed flight-state channels [4]."""
    out = np.zeros(N_FLIGHT)
    for ch, b in zip(model.arrays.bias_channel, biases, strict=True):
        if ch < N_FLIGHT:
            out[ch] += b
    return out
