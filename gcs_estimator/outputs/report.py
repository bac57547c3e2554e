"""Results people can use: the paper's Table I as Markdown, JSON, and CSV time histories."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO, Protocol

import numpy as np

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import POWER_COLUMNS, AircraftConfig
from gcs_estimator.estimation.estimator import (
    FILTER_KINDS,
    EstimatorResult,
    FilterKind,
    NoiseReading,
    Snapshot,
    Track,
)
from gcs_estimator.estimation.noise import CLEARLY, MIN_DIFFERENCES, reading_z
from gcs_estimator.model.channels import FLIGHT_STATES, OBS_NAMES
from gcs_estimator.runtime.session import VehicleResult
from gcs_estimator.uncertainty.metrics import (
    CORRELATION_LIMIT,
    NOT_IDENTIFIED,
    WEAK,
    CoefficientSummary,
    FilterSummary,
    identifiability,
    most_correlated,
    percent_error,
)
from gcs_estimator.uncertainty.weighting import VARIANCE_FACTOR

if TYPE_CHECKING:
    from gcs_estimator.refine.fit import Refined


def _fmt(v: float | None, digits: int = 4) -> str:
    if v is None or not math.isfinite(v):
        return "-"
    return f"{v:.{digits}g}" if abs(v) < 1e-3 and v != 0 else f"{v:.{digits}f}"


def _time(v: float | None) -> str:
    return "never" if v is None or not math.isfinite(v) else f"{v:.1f}"


def markdown_table(
    summaries: Mapping[FilterKind, FilterSummary],
    truth_label: str = "truth",
    refined: Refined | None = None,
) -> str:
    """Table I layout: one row per coefficient, estimate and sigma per filter, plus the
    true (or reference) value, error in percent and in sigmas when it is known, how well
    the data identify each coefficient, and the whole-record refinement when there is one."""
    kinds: list[FilterKind] = [k for k in FILTER_KINDS if k in summaries]
    if not kinds:
        return "(no estimates yet)\n"
    first = summaries[kinds[0]]
    has_truth = any(c.truth is not None for c in first.coefficients)
    head = ["coefficient"] + ([truth_label] if has_truth else [])
    settle = f"within 5 % of {truth_label} from s" if has_truth else "steady from s"
    for k in kinds:
        head += [f"{k} estimate", f"{k} σ", f"{k} σ corrected"]
        if has_truth:
            head += [f"{k} error %", f"{k} error/σ"]
        head += [f"{k} {settle}"]
    marks_from = summaries.get("IEKF", first)
    head += [f"identified? ({marks_from.kind if refined is None else refined.label})"]
    if refined is not None:
        fit = refined.label
        head += [f"{fit} estimate", f"{fit} σ", f"{fit} Cramer-Rao σ"]
        if has_truth:
            head += [f"{fit} error %", f"{fit} error/σ"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for i, c0 in enumerate(first.coefficients):
        row = [c0.name] + ([_fmt(c0.truth)] if has_truth else [])
        for k in kinds:
            row += _filter_cells(summaries[k].coefficients[i], has_truth)
        row += [_identified_cell(marks_from.coefficients[i], refined, i)]
        if refined is not None:
            row += _refined_cells(refined, i, c0.truth, has_truth)
        lines.append("| " + " | ".join(row) + " |")
    lines.append("")
    lines.append(_legend(truth_label, has_truth, refined))
    lines += [f"- {n}" for n in _run_notes(summaries, kinds, refined)]
    return "\n".join(lines) + "\n"


def _filter_cells(c: CoefficientSummary, has_truth: bool) -> list[str]:
    row = [_fmt(c.estimate), f"{c.sigma:.2g}", _corrected_cell(c)]
    if has_truth:
        row += [
            "-" if c.error_pct is None else f"{c.error_pct:+.2f}",
            "-" if c.z is None else f"{c.z:+.1f}",
            _time(c.converged_truth_s),
        ]
    else:
        steady = c.identifiability != NOT_IDENTIFIED
        row += [_time(c.converged_final_s) if steady else "-"]
    return row


def _corrected_cell(c: CoefficientSummary) -> str:
    if not math.isfinite(c.corrected_sigma):
        return "-"
    return f"{c.corrected_sigma:.2g} (×{c.sigma_inflation:.1f})"


def _identified_cell(mark: CoefficientSummary, refined: Refined | None, i: int) -> str:
    """The IEKF's mark, or the whole-record fit's where there is one (the column's head
    says which), with the correlation that made it weak from the same source."""
    if refined is None:
        ident, rho, partner = mark.identifiability, mark.correlation, mark.correlated_with
    else:
        ident = refined.identifiability[i]
        partner, rho = most_correlated(refined.correlation, refined.names, i)
    if ident == WEAK and abs(rho) > CORRELATION_LIMIT:
        ident += f" (ρ {rho:+.2f} with {partner})"
    return ident


def _refined_cells(refined: Refined, i: int, truth: float | None, has_truth: bool) -> list[str]:
    est = float(refined.coefficients[i])
    row = [_fmt(est), f"{refined.sigma[i]:.2g}", f"{refined.crb_sigma[i]:.2g}"]
    if has_truth and truth is not None:
        err = percent_error(est, truth)
        row += ["-" if err is None else f"{err:+.2f}", f"{(est - truth) / refined.sigma[i]:+.1f}"]
    elif has_truth:
        row += ["-", "-"]
    return row


def _legend(truth_label: str, has_truth: bool, refined: Refined | None) -> str:
    text = (
        "σ: one standard deviation from the filter covariance; σ corrected: that σ times "
        "the factor by which the estimate moved over the second half of the run more "
        "than the covariance said it would, with, where the structure check ran, how far "
        "the estimate moves beyond its covariance when one channel at a time is trusted "
        "half as much added in quadrature (×1.0: as the covariance said; on real data, "
        "the one to trust)"
    )
    if refined is not None:
        text += (
            f"; {refined.label} σ: the {refined.method.split(',')[0]} fit's Cramer-Rao bound "
            "corrected for the colour of its residuals (Morelli-Klein), with how far the fit "
            "moves when one channel at a time is trusted half as much (at least as far as "
            "the filter's own check found), and how far it lands "
            "from the filter it started from beyond what both covariances allow, added in "
            "quadrature: the one to trust on real data"
        )
    if has_truth:
        text += (
            f". Within 5 % of {truth_label} from: the time after which the estimate stays "
            f"within 5 % of the {truth_label} value."
        )
    else:
        text += (
            ". Steady from: the time after which the estimate stays within 5 % of its own "
            "final value (not a measure of accuracy; '-' where the data do not identify it)."
        )
    return text + (
        " Identified?: σ/|estimate| at most 0.1 and no correlation above 0.95 with another "
        "coefficient; weak: σ/|estimate| up to 0.5 or such a correlation; not identified: "
        "beyond that, or the filter's σ still above half its prior."
    )


def _run_notes(
    summaries: Mapping[FilterKind, FilterSummary],
    kinds: list[FilterKind],
    refined: Refined | None,
) -> list[str]:
    notes = []
    for k in kinds:
        s = summaries[k]
        note = (
            f"{k}: {s.steps} updates, mean NIS {s.mean_nis:.2f} over {s.mean_channels:.1f} channels"
        )
        if any(math.isfinite(v) for v in s.channel_nis):
            note += (
                " (per channel "
                + ", ".join(
                    f"{n} {v:.2f}"
                    for n, v in zip(OBS_NAMES, s.channel_nis, strict=True)
                    if math.isfinite(v)
                )
                + ")"
            )
        if s.nees is not None:
            note += f", coefficient NEES {s.nees:.1f} (dof {len(s.coefficients)})"
        note += f", turbulence σ_w {s.gust_sigma:.2f} m/s"
        if math.isfinite(s.gust_pass_z):
            note += (
                f" (over the pass {s.gust_pass_sigma:.2f} m/s, {s.gust_pass_z:+.1f} standard "
                "errors from zero)"
            )
        notes.append(note)
    if refined is not None:
        chosen = f"; chosen: {refined.choice}" if refined.choice else ""
        notes.append(
            f"{refined.label} ({refined.method}{chosen}, {refined.frames} frames, "
            f"{refined.message}): noise σ "
            + channel_text(refined.noise_sigma)
            + "; residual colour (1 = white) "
            + channel_text(refined.residual_colour)
        )
    return notes


def channel_text(values: FloatArray) -> str:
    """'V 0.13, alpha 0.001, ...' for the channels with a value."""
    return ", ".join(
        f"{n} {v:.3g}" for n, v in zip(OBS_NAMES, values, strict=True) if math.isfinite(v)
    )


class LiveEstimate(Protocol):
    """What the live table and the status line read of a vehicle's estimator (an
    Estimator, or the station's view of one a filter worker runs)."""

    @property
    def config(self) -> AircraftConfig: ...
    @property
    def names(self) -> tuple[str, ...]: ...
    @property
    def frames(self) -> int: ...
    def snapshot(self) -> dict[FilterKind, Snapshot]: ...


def live_table(estimator: LiveEstimate, truth: Sequence[float] | FloatArray | None = ()) -> str:
    """The current estimates as a Markdown table (cheap: no history is read), against
    truth (None: none; by default the config's)."""
    current = estimator.snapshot()
    if not current:
        return "(waiting for data)\n"
    if truth is not None and len(truth) == 0:
        truth = estimator.config.truth
    kinds = [k for k in FILTER_KINDS if k in current]
    head = ["coefficient"] + ([estimator.config.truth_label] if truth is not None else [])
    for k in kinds:
        head += [f"{k} estimate", f"{k} ±2σ"] + ([f"{k} error %"] if truth is not None else [])
    head += ["identified?"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    last = current[kinds[-1]]
    prior = np.asarray(estimator.config.filter.initial_sigma.coefficients, float)
    marks = identifiability(last.coefficients, last.sigma, np.eye(len(prior)), prior)
    for i, name in enumerate(estimator.names):
        row = [name] + ([_fmt(truth[i])] if truth is not None else [])
        for k in kinds:
            snap = current[k]
            x = float(snap.coefficients[i])
            row += [_fmt(x), f"{2 * snap.sigma[i]:.2g}"]
            if truth is not None:
                err = percent_error(x, truth[i])
                row.append("-" if err is None else f"{err:+.2f}")
        lines.append("| " + " | ".join([*row, marks[i]]) + " |")
    gusts = ", ".join(f"{k} {current[k].gust_sigma:.2f}" for k in kinds)
    return f"{estimator.frames} frames; turbulence σ_w [m/s]: {gusts}\n\n" + "\n".join(lines) + "\n"


NIS_RATIO_LIMIT = 3.0
"""Mean NIS this many times the channel count (or a third of it): the noise model is off."""
CHANNEL_NIS_LIMIT = 2.0
"""A channel's mean squared innovation this many times what the filter predicts (or less
than its inverse): that channel says the filter's model or its noise settings are off
there, where the whole NIS, averaged over the channels, may not."""
INFLATION_LIMIT = 2.0
"""A corrected sigma above this multiple of the covariance's: worth a warning."""
GUST_BURSTS = (0.02, 0.9)
"""A turbulence level applied in more than the first and less than the second share of
the final pass: on and off. Calm simulated flights stay below 1 %, turbulent ones at 100 %;
model misfit during manoeuvres reads as bursts (docs/decisions/0004)."""
COLOUR_LIMIT = 5.0
"""Residual colour above this on a channel: the model misses something the data hold."""
DISAGREE_SIGMAS = 3.0
"""The EKF and the IEKF ending further apart on a coefficient than this many of the larger
of their trusted sigmas: the data do not settle it (both filters read the same frames, so
their estimates differ by far less than either sigma where the data fix a value)."""


def trust_warnings(vehicle: VehicleResult, refined: Refined | None = None) -> list[str]:
    """What a user should know before trusting the numbers: a noise model that does not
    fit (NIS far from the channel count), a warm start that fitted few frames, a
    turbulence level switched on and off or one the whole pass found and the running
    level missed, coefficients the data do not identify, a filter
    that diverged and started again, residuals far from white in the whole-record
    fit, and what points at the setup: a channel the data never hold, an elevator that
    never moves, a coefficient of the sign no conventional aircraft has."""
    out: list[str] = []
    result = vehicle.result
    for kind, s in vehicle.summaries.items():
        if s.mean_channels > 0 and math.isfinite(s.mean_nis):
            ratio = s.mean_nis / s.mean_channels
            if ratio > NIS_RATIO_LIMIT or ratio < 1.0 / NIS_RATIO_LIMIT:
                out.append(
                    f"{kind}: mean NIS {s.mean_nis:.1f} over {s.mean_channels:.1f} channels: "
                    "the noise model does not fit these data, so its sigmas do not either "
                    "(check [filter.measurement_sigma] against the sensors)"
                )
        out += _channel_warnings(kind, s)
        threshold = result.config.filter.turbulence.detection_sigma
        if s.gust_pass_z >= threshold and s.gust_on_share < GUST_BURSTS[1]:
            out.append(
                f"{kind}: turbulence over the whole pass (σ_w {s.gust_pass_sigma:.2f} m/s, "
                f"{s.gust_pass_z:.1f} standard errors above zero) while a turbulence level "
                f"was applied in only {100 * s.gust_on_share:.0f} % of it: gusts too weak or "
                "too slow (a long scale length) for a few seconds of data to tell from "
                "calm; where none was applied the covariance's σ assumes calm air, so trust "
                "the corrected σ; `refine` (auto) fits such a record by filter error"
            )
        elif GUST_BURSTS[0] < s.gust_on_share < GUST_BURSTS[1]:
            out.append(
                f"{kind}: the turbulence level was applied on and off, in "
                f"{100 * s.gust_on_share:.0f} % of the frames since the last restart: "
                "turbulence near the detection limit, or what the model misses during the "
                "manoeuvres read as turbulence (its process noise then discounts the most "
                "informative seconds); if the air was calm, compare a run with "
                "[filter.turbulence] adaptive = false"
            )
        moved = [
            f"{c.name} ×{c.sigma_inflation:.1f}"
            for c in s.coefficients
            if c.sigma_inflation > INFLATION_LIMIT and c.identifiability != NOT_IDENTIFIED
        ]
        if moved:
            out.append(
                f"{kind}: estimates moved more than the covariance allows, over the run or "
                "with the channels weighted otherwise ("
                + ", ".join(moved)
                + "): the model misses something in these data (unmodelled aerodynamics, "
                "turbulence, sensor errors); trust the corrected σ, not the covariance's"
            )
        weak = [c.name for c in s.coefficients if c.identifiability == NOT_IDENTIFIED]
        if weak:
            out.append(f"{kind}: not identified by these data: {', '.join(weak)}")
        out += _sign_warnings(kind, s)
    out += _disagreement_warning(vehicle)
    out += _noise_warning(vehicle)
    out += _run_warnings(result)
    if refined is not None:
        out += _refined_warnings(refined)
    return out


def _channel_warnings(kind: str, s: FilterSummary) -> list[str]:
    """The channels whose innovations over the final pass are far larger, or far smaller,
    than the filter predicts (FilterSummary.channel_nis)."""
    pairs = [(n, v) for n, v in zip(OBS_NAMES, s.channel_nis, strict=True) if math.isfinite(v)]
    high = [f"{n} {v:.1f}" for n, v in pairs if v > CHANNEL_NIS_LIMIT]
    low = [f"{n} {v:.2f}" for n, v in pairs if v < 1.0 / CHANNEL_NIS_LIMIT]
    out = []
    if high:
        out.append(
            f"{kind}: innovations larger than the filter predicts on "
            + ", ".join(high)
            + " (their mean square over the predicted σ², 1 expected): the model or the "
            "noise settings miss something these channels show (aerodynamics the "
            "structure lacks, turbulence, a sensor noisier or placed otherwise than the "
            "airframe file says), and the filter counts on them more than it should: "
            "trust the corrected σ"
        )
    if low:
        out.append(
            f"{kind}: innovations smaller than the filter predicts on "
            + ", ".join(low)
            + ": their [filter.measurement_sigma] is larger than these data show, so the "
            "filters use them less than they could"
        )
    return out


def _disagreement_warning(vehicle: VehicleResult) -> list[str]:
    """The coefficients on which the two filters end more than DISAGREE_SIGMAS apart.

    Both read the same frames, so where the data fix a coefficient they end close
    together. Where they leave a ridge (coefficients whose combination alone the flight
    fixes: CLq and CLadot, say), the IEKF's relinearisation can follow it far from where
    the EKF stays, while each filter's covariance, taken at its own point, still calls the
    coefficient identified. Not-identified coefficients are left out: the table says so
    already."""
    summaries = [vehicle.summaries[k] for k in FILTER_KINDS if k in vehicle.summaries]
    if len(summaries) < 2:
        return []
    a, b = summaries[0], summaries[1]
    apart = []
    for ca, cb in zip(a.coefficients, b.coefficients, strict=True):
        if NOT_IDENTIFIED in (ca.identifiability, cb.identifiability):
            continue
        sigma = max(ca.trusted_sigma, cb.trusted_sigma)
        if abs(ca.estimate - cb.estimate) > DISAGREE_SIGMAS * sigma:
            apart.append(f"{ca.name} {_fmt(ca.estimate)} against {_fmt(cb.estimate)}")
    if not apart:
        return []
    return [
        f"the {a.kind} and the {b.kind} end more than {DISAGREE_SIGMAS:g} σ apart on "
        + ", ".join(apart)
        + ": the data do not settle these coefficients (a ridge of the fit, or one filter "
        "led off by a bad stretch of data), whatever their σ say; compare `refine` and a "
        "run with fewer coefficients"
    ]


def _noise_warning(vehicle: VehicleResult) -> list[str]:
    """What the measurement noise read from the data says (docs/decisions/0011, 0014):
    with "data", that in turbulence the motion the gusts cause from sample to sample
    reads as sensor noise; with "auto", which channels read clearly noisier than
    configured (kept at the configured sigma)."""
    result = vehicle.result
    if result.noise_reading is None:
        return []
    configured = np.array(result.config.filter.measurement_sigma, float)
    reading = np.array(result.noise_reading.sigma)
    if result.config.filter.measurement_noise == "auto":
        z = reading_z(reading, np.array(result.noise_reading.differences), configured)
        above = [
            f"{n} {r / c:.1f}×"
            for n, r, c, zc in zip(OBS_NAMES, reading, configured, z, strict=True)
            if zc > CLEARLY
        ]
        if not above:
            return []
        return [
            "the data read noisier than the configured σ on "
            + ", ".join(above)
            + " (the configured σ was kept): noisier sensors than configured, or motion "
            "as rough as noise (gusts of a short scale length, which the filters' process "
            "noise carries); if the sensors are that noisy, set [filter.measurement_sigma] "
            'for them, or measurement_noise = "data"'
        ]
    gust = max((s.gust_sigma for s in vehicle.summaries.values()), default=0.0)
    if not gust > 0.0:
        return []
    ratio = np.array(result.measurement_sigma) / configured
    c = int(np.argmax(ratio))
    return [
        f"measurement noise read from the data while the filters saw turbulence (σ_w "
        f"{gust:.2f} m/s): what the gusts move from sample to sample reads as sensor noise "
        f"({OBS_NAMES[c]} read {ratio[c]:.1f} times the configured σ), which biases the "
        "estimates and shrinks the turbulence level; if the sensors' noise is known, "
        'compare a run with [filter] measurement_noise = "config"'
    ]


EXPECTED_SIGNS: dict[str, tuple[int, str]] = {
    "CLa": (1, "lift grows with alpha: is alpha read with its sign reversed?"),
    "Cmq": (-1, "pitch damping opposes the pitch rate: is q read with its sign reversed?"),
    "Cmde": (
        -1,
        "an elevator deflected trailing edge down (positive here) pitches the nose down: "
        "is the elevator read with its sign reversed ([link] elevator_us_per_rad, or the "
        "data's elevator column)?",
    ),
    "CLde": (
        1,
        "an elevator deflected trailing edge down (positive here) adds lift: is the "
        "elevator read with its sign reversed?",
    ),
}
"""Signs every conventional aircraft's coefficients have (docs/model.md's conventions),
and what an estimate of the other sign most likely means."""

SIGN_SIGMAS = 3.0
"""An estimate of the unexpected sign is named when it stands this many of its trusted
sigmas from zero."""

STILL_ELEVATOR_RAD = math.radians(0.1)
"""An elevator that moves less than this over a whole flight [rad] did not move: no
manoeuvre, or the elevator read from the wrong servo or column."""

OPTIONAL_CHANNELS = ("qdot",)
"""Observation channels a flight may lack with nothing to warn of (the warm start
differentiates q; the README's CSV layout lets qdot be empty)."""


def _sign_warnings(kind: str, s: FilterSummary) -> list[str]:
    """Estimates of the sign no conventional aircraft's coefficient has (EXPECTED_SIGNS),
    SIGN_SIGMAS of their trusted sigma from zero: a sensor or the elevator read with its
    sign reversed, most likely."""
    out = []
    for c in s.coefficients:
        sign, why = EXPECTED_SIGNS.get(c.name, (0, ""))
        if sign and sign * c.estimate < -SIGN_SIGMAS * c.trusted_sigma:
            out.append(
                f"{kind}: {c.name} came out {c.estimate:+.4g} "
                f"({abs(c.estimate) / c.trusted_sigma:.0f} σ from zero), of the sign no "
                f"conventional aircraft's has: {why}"
            )
    return out


def _run_warnings(result: EstimatorResult) -> list[str]:
    """A channel the data never held, an elevator that never moved, a filter that
    diverged, a warm start that fitted few frames."""
    out: list[str] = []
    track = next((f.track for f in result.filters.values() if f.track is not None), None)
    if track is not None and len(track.y):
        held = np.any(np.isfinite(track.y), axis=0)
        none = [
            name
            for c, name in enumerate(OBS_NAMES)
            if not held[c] and name not in OPTIONAL_CHANNELS
        ]
        elevator = track.u[:, 0]
        if np.isfinite(elevator).any() and np.nanmax(elevator) - np.nanmin(elevator) < (
            STILL_ELEVATOR_RAD
        ):
            out.append(
                "the elevator did not move in this flight (less than "
                f"{math.degrees(STILL_ELEVATOR_RAD):g} deg): the moment "
                "coefficients cannot be told apart; if the aircraft did manoeuvre, the "
                "elevator is read from the wrong place ([link] elevator_servo, or "
                "[data.columns] elevator)"
            )
        if none:
            out.append(
                f"no {', '.join(none)} in these data at all: the filters ran without "
                f"{'it' if len(none) == 1 else 'them'}, and what only "
                f"{'it tells' if len(none) == 1 else 'they tell'} is not identified (a column "
                "the file lacks, or a message the vehicle does not send)"
            )
    for kind, f in result.filters.items():
        if f.health.divergences:
            out.append(
                f"{kind}: the estimate diverged {f.health.divergences} time(s) and started "
                "again from the prior there (a long gap early in the flight, or bad data); "
                "the history shows absurd values before each"
            )
    if result.warm_start_samples is not None and result.warm_start_frames > 0:
        least = min(result.warm_start_samples)
        if least < 0.5 * result.warm_start_frames:
            cd, cl, cm = result.warm_start_samples
            out.append(
                f"the equation-error warm start fitted CD, CL, Cm on only {cd}, {cl}, {cm} of "
                f"{result.warm_start_frames} frames (gaps or missing channels)"
            )
    return out


def _refined_warnings(refined: Refined) -> list[str]:
    out = []
    coloured = [
        f"{n} {v:.0f}"
        for n, v in zip(OBS_NAMES, refined.residual_colour, strict=True)
        if math.isfinite(v) and v > COLOUR_LIMIT
    ]
    if coloured:
        hint = (
            "; in turbulence, `--method filter-error` lets a filter follow the gusts"
            if refined.method == "output error"
            else ""
        )
        fit = refined.label
        out.append(
            f"{fit} residuals far from white (" + ", ".join(coloured) + "): the model misses "
            f"something (turbulence, unmodelled aerodynamics); trust {fit} σ, not "
            "Cramer-Rao's" + hint
        )
    if refined.difference_sigma is not None:
        apart = [
            f"{n} ×{s / a:.1f}"
            for n, s, a, mark in zip(
                refined.names,
                refined.sigma,
                refined.sigma_within_fit,
                refined.identifiability,
                strict=True,
            )
            if a > 0.0 and s > INFLATION_LIMIT * a and mark != NOT_IDENTIFIED
        ]
        if apart:
            fit = refined.label
            out.append(
                f"{fit} lands further from the filter it started from than both covariances "
                "allow (" + ", ".join(apart) + " on its σ): the two weigh the record "
                "differently, and where the model misses part of the aircraft (unmodelled "
                "aerodynamics, turbulence it models otherwise) each settles on its own "
                f"compromise; {fit} σ includes the difference (docs/decisions/0030)"
            )
    if not refined.converged:
        out.append(f"{refined.label}: {refined.message}")
    return out


def final_table(vehicle: VehicleResult, refined: Refined | None = None) -> str:
    """The finished run's Table I (with convergence times), as in results.md, and what
    the run estimated beside the coefficients or fitted to start them."""
    result = vehicle.result
    notes = []
    for kind, f in result.filters.items():
        if result.bias_names:
            biases = ", ".join(
                f"{n.removesuffix('_bias')} {b:+.3g} ± {s:.2g}"
                for n, b, s in zip(result.bias_names, f.biases, f.bias_sigma, strict=True)
            )
            notes.append(f"{kind} sensor biases [SI]: {biases}")
    if result.warm_start_samples is not None:
        cd, cl, cm = result.warm_start_samples
        notes.append(
            f"equation-error warm start: fitted CD, CL, Cm on {cd}, {cl}, {cm} of "
            f"{result.warm_start_frames} frames"
        )
    if result.noise_reading is not None:
        notes.append(_noise_note(result, result.noise_reading))
    check = vehicle.structure
    if check is not None:
        notes.append(
            f"structure check: not made: {check.skipped}"
            if check.skipped
            else f"structure check: the final pass replayed with each of "
            f"{', '.join(check.channels)} trusted half as much; how far that moved the "
            "estimates is in σ corrected"
        )
    table = markdown_table(vehicle.summaries, result.config.truth_label, refined)
    text = table + "".join(f"- {n}\n" for n in notes)
    warnings = trust_warnings(vehicle, refined)
    if warnings:
        text += "\n**Before trusting these numbers:**\n\n" + "".join(f"- {w}\n" for w in warnings)
    return text


def _noise_note(result: EstimatorResult, reading: NoiseReading) -> str:
    """The measurement noise the final pass used, per channel, and where it came from."""
    policy = result.config.filter.measurement_noise
    cells = []
    for n, used, read, m in zip(
        OBS_NAMES, result.measurement_sigma, reading.sigma, reading.differences, strict=True
    ):
        if m == 0:
            cells.append(f"{n} {used:.3g} (configured; no samples)")
        elif m < MIN_DIFFERENCES:
            cells.append(f"{n} {used:.3g} (configured: too few samples to read)")
        elif policy == "data" or math.isclose(used, read, rel_tol=1e-12):
            cells.append(f"{n} {used:.3g} (read)")
        else:
            cells.append(f"{n} {used:.3g} (configured; read {read:.3g})")
    return f"measurement noise (σ, SI; measurement_noise = {policy!r}): " + ", ".join(cells)


def results_dict(
    vehicle: VehicleResult,
    extra: Mapping[str, Any] | None = None,
    refined: Refined | None = None,
) -> dict[str, Any]:
    """Everything a script needs: estimates, sigmas, convergence, NIS, config used."""
    result = vehicle.result
    config = result.config
    out: dict[str, Any] = {
        "aircraft": config.airframe.name,
        "config_source": config.source,
        "truth_label": config.truth_label if vehicle.truth is not None else None,
        "coefficients": list(result.names),
        "filters": {},
        "diagnostics": {
            "frames": result.frames,
            "restarts_done": result.restarts_done,
            "gaps": result.gaps,
            "frames_out_of_order": result.frames_out_of_order,
            "warm_start": None if result.warm_start is None else result.warm_start.tolist(),
            "warm_start_samples": result.warm_start_samples,
            "warm_start_frames": result.warm_start_frames,
            "measurement_noise": config.filter.measurement_noise,
            "measurement_sigma": dict(zip(OBS_NAMES, result.measurement_sigma, strict=True)),
            "noise_differences": None
            if result.noise_reading is None
            else dict(zip(OBS_NAMES, result.noise_reading.differences, strict=True)),
            "noise_reading": None
            if result.noise_reading is None
            else dict(zip(OBS_NAMES, result.noise_reading.sigma, strict=True)),
            "structure_check": _structure_dict(vehicle),
            "failed_updates": {k: f.health.failed_updates for k, f in result.filters.items()},
            "divergences": {k: f.health.divergences for k, f in result.filters.items()},
            "covariance_repairs": {
                k: f.health.covariance_repairs for k, f in result.filters.items()
            },
        },
        "warnings": trust_warnings(vehicle, refined),
        "refined": None if refined is None else refined_dict(refined, vehicle.truth),
        "config": _jsonable(config.raw),
    }
    for kind, s in vehicle.summaries.items():
        out["filters"][kind] = {
            "mean_nis": _num(s.mean_nis),
            "mean_nis_whole_flight": _num(s.mean_nis_all),
            "mean_channels": _num(s.mean_channels),
            "turbulence_sigma_w_mps": s.gust_sigma,
            "turbulence_pass_sigma_w_mps": s.gust_pass_sigma,
            "turbulence_pass_z": _num(s.gust_pass_z),
            "nees": _num(s.nees),
            "innovation_mean_square": {
                n: _num(v) for n, v in zip(OBS_NAMES, s.channel_nis, strict=True)
            },
            "updates": s.steps,
            "estimates": {
                c.name: {
                    "estimate": c.estimate,
                    "sigma": c.sigma,
                    "corrected_sigma": _num(c.corrected_sigma),
                    "sigma_inflation": _num(c.sigma_inflation),
                    "structure_sigma": _num(c.structure_sigma),
                    "truth": c.truth,
                    "error_pct": _num(c.error_pct),
                    "error_sigmas": _num(c.z),
                    "settled_s": _num(c.converged_final_s),
                    "within_5pct_of_truth_s": _num(c.converged_truth_s),
                    "identifiability": c.identifiability,
                    "relative_sigma": _num(
                        c.trusted_sigma / abs(c.estimate) if c.estimate else None
                    ),
                    "most_correlated_with": c.correlated_with or None,
                    "correlation": c.correlation,
                }
                for c in s.coefficients
            },
            "sensor_biases": {
                name: {"estimate": float(b), "sigma": float(sd)}
                for name, b, sd in zip(
                    result.bias_names,
                    result.filters[kind].biases,
                    result.filters[kind].bias_sigma,
                    strict=True,
                )
            },
        }
    if extra:
        out.update(extra)
    return out


def _structure_dict(vehicle: VehicleResult) -> dict[str, Any] | None:
    """The structure check (weighting.py): the channels re-weighted and how far each
    moved each estimate, or why it was not made."""
    check = vehicle.structure
    if check is None:
        return None
    if check.skipped:
        return {"skipped": check.skipped}
    names = vehicle.result.names
    return {
        "skipped": None,
        "variance_factor": VARIANCE_FACTOR,
        "channels": list(check.channels),
        "moves": {
            kind: {
                ch: dict(zip(names, (float(v) for v in row), strict=True))
                for ch, row in zip(check.channels, moves, strict=True)
            }
            for kind, moves in check.moves.items()
        },
    }


def refined_dict(refined: Refined, truth: FloatArray | None) -> dict[str, Any]:
    """The whole-record fit as JSON."""
    return {
        "method": refined.method,
        "method_choice": refined.choice or None,
        "frames": refined.frames,
        "converged": refined.converged,
        "message": refined.message,
        "noise_sigma": {
            n: _num(float(v)) for n, v in zip(OBS_NAMES, refined.noise_sigma, strict=True)
        },
        "process_noise_density": {
            n: float(v) for n, v in zip(FLIGHT_STATES, refined.process_noise, strict=True)
        },
        "residual_colour": {
            n: _num(float(v)) for n, v in zip(OBS_NAMES, refined.residual_colour, strict=True)
        },
        "initial_state": dict(zip(FLIGHT_STATES, map(float, refined.state0), strict=True)),
        "estimates": {
            n: {
                "estimate": float(refined.coefficients[i]),
                "sigma": _num(float(refined.sigma[i])),
                "cramer_rao_sigma": _num(float(refined.crb_sigma[i])),
                "structure_sigma": _num(float(refined.structure_sigma[i])),
                "difference_sigma": None
                if refined.difference_sigma is None
                else _num(float(refined.difference_sigma[i])),
                "filter_structure_sigma": None
                if refined.filter_structure_sigma is None
                else _num(float(refined.filter_structure_sigma[i])),
                "identifiability": refined.identifiability[i],
                "truth": None if truth is None else float(truth[i]),
                "error_pct": None
                if truth is None
                else _num(percent_error(float(refined.coefficients[i]), float(truth[i]))),
            }
            for i, n in enumerate(refined.names)
        },
        "correlation": refined.correlation.tolist(),
        "sensor_biases": {
            n: {"estimate": float(b), "sigma": _num(float(s))}
            for n, b, s in zip(refined.bias_names, refined.biases, refined.bias_sigma, strict=True)
        },
    }


def _num(v: float | None) -> float | None:
    return None if v is None or not math.isfinite(v) else float(v)


def _jsonable(data: Any) -> Any:
    if isinstance(data, Mapping):
        return {str(k): _jsonable(v) for k, v in data.items()}
    if isinstance(data, list | tuple):
        return [_jsonable(v) for v in data]
    if hasattr(data, "isoformat"):
        return data.isoformat()
    return data


class HistoryCsv:
    """The history CSV, written as the run goes: one row per filter and frame with the
    estimates and sigmas of every state and coefficient, NIS, channels used, and the
    frame's inputs and measurements.

    Rows come in blocks of frames (append), each block the EKF's rows then the IEKF's,
    so within a filter the rows are in frame order; a stop then writes only the last
    block, whatever the flight's length, and the file holds what was processed even if
    the process is killed.

    Each value is written as the shortest text that reads back as the number kept: the
    estimates and sigmas to the history's float32 (estimator.HISTORY_DTYPE, 7 significant
    digits), times, inputs and measurements to float64; an empty cell where a value is
    missing. Arrow's CSV writer formats whole columns (an hour's history in seconds)."""

    def __init__(self, path: Path, state_names: Sequence[str], power_input: str) -> None:
        names = list(state_names)
        power = POWER_COLUMNS[power_input]
        self.header = (
            ["filter", "t_s"]
            + names
            + [f"sigma_{n}" for n in names]
            + ["nis", "channels", "in_elevator_rad", f"in_{power}", "in_air_density_kgpm3"]
            + [f"meas_{n}" for n in OBS_NAMES]
        )
        self.rows = 0
        """Frames written so far (per filter)."""
        path.parent.mkdir(parents=True, exist_ok=True)
        self._fh: BinaryIO | None = open(path, "wb")  # noqa: SIM115 (closed by close())
        self._fh.write((",".join(self.header) + "\n").encode())
        self._fh.flush()

    def append(self, tracks: Mapping[FilterKind, Track], stop: int) -> None:
        """Frames rows..stop of each filter's track (a track may be longer)."""
        import pyarrow as pa
        import pyarrow.csv as pacsv

        if self._fh is None or stop <= self.rows:
            return
        options = pacsv.WriteOptions(include_header=False, quoting_style="none")
        a = self.rows
        for kind, tr in tracks.items():
            n = min(stop, len(tr.t))
            if n <= a:
                continue
            columns = [
                pa.array([kind] * (n - a)),
                pa.array(np.asarray(tr.t[a:n], float)),
                *_arrow_columns(tr.x[a:n]),
                *_arrow_columns(tr.sigma[a:n]),
                *_arrow_columns(tr.nis[a:n, None], blank_nan=True),
                pa.array(np.asarray(tr.n_used[a:n]).astype(np.int64)),
                *_arrow_columns(tr.u[a:n], blank_nan=True),
                *_arrow_columns(tr.y[a:n], blank_nan=True),
            ]
            pacsv.write_csv(pa.table(columns, names=self.header), self._fh, options)
        self._fh.flush()
        self.rows = stop

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None


def write_history_csv(path: Path, result: EstimatorResult, csv: HistoryCsv | None = None) -> None:
    """The whole history CSV of a run (HistoryCsv); given the one written as the run
    went, only the frames it does not hold yet, then it is closed."""
    if csv is None:
        csv = HistoryCsv(path, result.state_names, result.config.propulsion.input_name)
    tracks = {k: f.track for k, f in result.filters.items() if f.track is not None}
    csv.append(tracks, max((len(t.t) for t in tracks.values()), default=0))
    csv.close()


def _arrow_columns(values: np.ndarray, blank_nan: bool = False) -> list[Any]:
    """Each column of a [N x k] array as an Arrow array (NaN as a missing value: an empty
    cell, where blank_nan)."""
    import pyarrow as pa

    return [pa.array(np.asarray(c), from_pandas=blank_nan) for c in np.asarray(values).T]


def write_results(
    out_dir: Path,
    vehicle: VehicleResult,
    extra: Mapping[str, Any] | None = None,
    stem: str = "results",
    refined: Refined | None = None,
    history: HistoryCsv | None = None,
) -> dict[str, Path]:
    """Write <stem>.json, <stem>.md and <stem>_history.csv into out_dir (the history: the
    rest of the one written as the run went, where given); return their paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    data = results_dict(vehicle, extra, refined)
    paths = {
        "json": out_dir / f"{stem}.json",
        "markdown": out_dir / f"{stem}.md",
        "csv": out_dir / f"{stem}_history.csv",
    }
    paths["json"].write_text(json.dumps(data, indent=2, allow_nan=False) + "\n", encoding="utf-8")
    title = f"# {vehicle.result.config.airframe.name}: estimated aerodynamic coefficients\n\n"
    paths["markdown"].write_text(title + final_table(vehicle, refined), encoding="utf-8")
    write_history_csv(paths["csv"], vehicle.result, history)
    return paths
