"""The paper's Table I: the full table of results.md (each filter's estimate, sigma,
error and convergence, the marks, the whole-record fit), the terminal's within
TERMINAL_WIDTH columns (estimates, sigmas, reference and marks), and the live table of
a run under way."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Protocol

import numpy as np

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import AircraftConfig
from gcs_estimator.estimation import segments
from gcs_estimator.estimation.filters.core import FILTER_KINDS, FilterKind
from gcs_estimator.estimation.noise import MIN_DIFFERENCES, NoiseReading
from gcs_estimator.estimation.results import EstimatorResult, Snapshot
from gcs_estimator.model.channels import OBS_NAMES
from gcs_estimator.outputs.diagnosis import trust_warnings
from gcs_estimator.outputs.text import (
    TERMINAL_WIDTH,
    bullets,
    channel_text,
    fmt,
    fmt_sigma,
    fmt_time,
    wrap,
)
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
from gcs_estimator.uncertainty.result import VehicleResult
from gcs_estimator.uncertainty.weighting import StructureCheck

if TYPE_CHECKING:
    from gcs_estimator.refine import Refined

TERMINAL_KINDS: tuple[FilterKind, ...] = ("IEKF", "EKF")
"""The filters' order in the terminal's table (the paper's: the iterated filter first)."""

WARNINGS_HEAD = "**Before trusting these numbers:**"

SIGMA_LEGEND = (
    "σ: one standard deviation to trust: the filter covariance's, widened by the factor "
    "by which the estimate moved over the second half of the run more than the "
    "covariance said it would, and, where the structure check ran, with how far the "
    "estimate moves beyond its covariance when one channel at a time is trusted half as "
    "much added in quadrature (the JSON keeps these parts in sigma_parts); error/σ: the "
    "error in that σ"
)


def _render(head: list[str], rows: list[list[str]], numeric: set[int], pad: bool) -> list[str]:
    """A Markdown table's lines; with pad, each column as wide as its widest cell, the
    numeric ones right-aligned (still Markdown, and aligned on a terminal)."""
    if not pad:
        lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        return lines + ["| " + " | ".join(row) + " |" for row in rows]
    widths = [max(len(r[j]) for r in [head, *rows]) for j in range(len(head))]

    def line(cells: list[str]) -> str:
        return (
            "| "
            + " | ".join(
                c.rjust(w) if j in numeric else c.ljust(w)
                for j, (c, w) in enumerate(zip(cells, widths, strict=True))
            )
            + " |"
        )

    rule = (
        "|"
        + "|".join(
            "-" * (w + 1) + ":" if j in numeric else "-" * (w + 2) for j, w in enumerate(widths)
        )
        + "|"
    )
    return [line(head), rule] + [line(r) for r in rows]


def markdown_table(
    summaries: Mapping[FilterKind, FilterSummary],
    truth_label: str = "truth",
    refined: Refined | None = None,
) -> str:
    """Table I as results.md holds it: one row per coefficient, estimate and sigma per
    filter, plus the true (or reference) value, error in percent and in sigmas when it is
    known, convergence times, how well the data identify each coefficient, and the
    whole-record refinement when there is one; the legend and the filters' notes."""
    kinds: list[FilterKind] = [k for k in FILTER_KINDS if k in summaries]
    if not kinds:
        return "(no estimates yet)\n"
    first = summaries[kinds[0]]
    has_truth = any(c.truth is not None for c in first.coefficients)
    head = ["coefficient"] + ([truth_label] if has_truth else [])
    settle = f"within 5 % of {truth_label} from s" if has_truth else "steady from s"
    for k in kinds:
        head += [f"{k} estimate", f"{k} σ"]
        if has_truth:
            head += [f"{k} error %", f"{k} error/σ"]
        head += [f"{k} {settle}"]
    marks_from = summaries.get("IEKF", first)
    head += [f"identified? ({marks_from.kind if refined is None else refined.label})"]
    if refined is not None:
        fit = refined.label
        head += [f"{fit} estimate", f"{fit} σ"]
        if has_truth:
            head += [f"{fit} error %", f"{fit} error/σ"]
    rows = []
    for i, c0 in enumerate(first.coefficients):
        row = [c0.name] + ([fmt(c0.truth)] if has_truth else [])
        for k in kinds:
            row += _filter_cells(summaries[k].coefficients[i], has_truth)
        row += [_identified_cell(marks_from.coefficients[i], refined, i)]
        if refined is not None:
            row += _refined_cells(refined, i, c0.truth, has_truth)
        rows.append(row)
    lines = _render(head, rows, set(), pad=False)
    lines += ["", _legend(truth_label, has_truth, refined)]
    lines += [f"- {n}" for n in _filter_notes(summaries, kinds, refined)]
    return "\n".join(lines) + "\n"


def terminal_table(
    summaries: Mapping[FilterKind, FilterSummary],
    truth_label: str = "truth",
    refined: Refined | None = None,
) -> str:
    """Table I as the terminal shows it, aligned within TERMINAL_WIDTH columns: per
    coefficient the IEKF's and the EKF's estimate and sigma, the reference value where
    there is one, and the IEKF's mark of how well the data identify it; where a whole-record
    fit was made, the fit's estimate, sigma and mark beside the IEKF's it started from
    (the EKF's are in results.md). The correlations that made a mark weak follow the
    table. Errors, convergence times and notes are in results.md (markdown_table)."""
    kinds = [k for k in TERMINAL_KINDS if k in summaries]
    if not kinds:
        return "(no estimates yet)\n"
    first = summaries[kinds[0]]
    has_truth = any(c.truth is not None for c in first.coefficients)
    columns: list[tuple[str, list[float], list[float]]] = []
    for k in kinds:
        cs = summaries[k].coefficients
        columns.append((k, [c.estimate for c in cs], [c.sigma for c in cs]))
    if refined is not None:
        fit = (refined.label, refined.coefficients.tolist(), refined.sigma.tolist())
        columns = [fit, columns[0]]
    head = ["coefficient"]
    for label, _, _ in columns:
        head += [f"{label} estimate", f"{label} σ"]
    head += [truth_label] if has_truth else []
    head += ["identified?" if refined is None else f"identified? ({refined.label})"]
    rows, pairs = [], []
    for i, c0 in enumerate(first.coefficients):
        row = [c0.name]
        for _, estimates, sigmas in columns:
            row += [fmt(estimates[i]), fmt_sigma(sigmas[i])]
        row += [fmt(c0.truth)] if has_truth else []
        ident, partner, rho = _mark(c0, refined, i)
        rows.append([*row, ident])
        pair = f"{min(c0.name, partner)} and {max(c0.name, partner)} {rho:+.2f}"
        if ident == WEAK and abs(rho) > CORRELATION_LIMIT and pair not in pairs:
            pairs.append(pair)
    numeric = set(range(1, len(head) - 1))
    text = "\n".join(_render(head, rows, numeric, pad=True)) + "\n"
    if pairs:
        text += (
            "\n"
            + wrap(f"weak for a correlation above {CORRELATION_LIMIT:g}: " + ", ".join(pairs))
            + "\n"
        )
    return text


def _mark(mark: CoefficientSummary, refined: Refined | None, i: int) -> tuple[str, str, float]:
    """Coefficient i's mark, the coefficient it correlates with most and that
    correlation: the IEKF's (mark), or the whole-record fit's where there is one."""
    if refined is None:
        return mark.identifiability, mark.correlated_with, mark.correlation
    partner, rho = most_correlated(refined.correlation, refined.names, i)
    return refined.identifiability[i], partner, rho


def _filter_cells(c: CoefficientSummary, has_truth: bool) -> list[str]:
    row = [fmt(c.estimate), fmt_sigma(c.sigma)]
    if has_truth:
        row += [
            "-" if c.error_pct is None else f"{c.error_pct:+.2f}",
            "-" if c.z is None else f"{c.z:+.1f}",
            fmt_time(c.converged_truth_s),
        ]
    else:
        steady = c.identifiability != NOT_IDENTIFIED
        row += [fmt_time(c.converged_final_s) if steady else "-"]
    return row


def _identified_cell(mark: CoefficientSummary, refined: Refined | None, i: int) -> str:
    """The IEKF's mark, or the whole-record fit's where there is one (the column's head
    says which), with the correlation that made it weak from the same source."""
    ident, partner, rho = _mark(mark, refined, i)
    if ident == WEAK and abs(rho) > CORRELATION_LIMIT:
        ident += f" (ρ {rho:+.2f} with {partner})"
    return ident


def _refined_cells(refined: Refined, i: int, truth: float | None, has_truth: bool) -> list[str]:
    est = float(refined.coefficients[i])
    row = [fmt(est), fmt_sigma(float(refined.sigma[i]))]
    if has_truth and truth is not None:
        err = percent_error(est, truth)
        row += ["-" if err is None else f"{err:+.2f}", f"{(est - truth) / refined.sigma[i]:+.1f}"]
    elif has_truth:
        row += ["-", "-"]
    return row


def _legend(truth_label: str, has_truth: bool, refined: Refined | None) -> str:
    text = SIGMA_LEGEND
    if refined is not None:
        text += (
            f"; {refined.label} σ: the {refined.method.split(',')[0]} fit's Cramer-Rao bound "
            "corrected for the colour of its residuals (Morelli-Klein), with how far the fit "
            "moves when one channel at a time is trusted half as much (at least as far as "
            "the filter's own check found), and how far it lands "
            "from the filter it started from beyond what both covariances allow, added in "
            "quadrature: the one to trust on real data (the JSON keeps the parts)"
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


def _filter_notes(
    summaries: Mapping[FilterKind, FilterSummary],
    kinds: list[FilterKind],
    refined: Refined | None,
) -> list[str]:
    """Each filter's consistency (NIS, per channel, NEES) and turbulence, and the fit's
    method and noise."""
    notes = [_filter_note(summaries[k]) for k in kinds]
    if refined is not None:
        notes.append(_refined_note(refined))
    return notes


def _filter_note(s: FilterSummary) -> str:
    note = (
        f"{s.kind}: {s.steps} updates, mean NIS {s.mean_nis:.2f} over "
        f"{s.mean_channels:.1f} channels"
    )
    per_channel = [
        f"{n} {v:.2f}" for n, v in zip(OBS_NAMES, s.channel_nis, strict=True) if math.isfinite(v)
    ]
    if per_channel:
        note += " (per channel " + ", ".join(per_channel) + ")"
    if s.nees is not None:
        note += f", coefficient NEES {s.nees:.1f} (dof {len(s.coefficients)})"
    note += f", turbulence σ_w {s.gust_sigma:.2f} m/s"
    if math.isfinite(s.gust_pass_z):
        note += (
            f" (over the pass {s.gust_pass_sigma:.2f} m/s, {s.gust_pass_z:+.1f} standard "
            "errors from zero)"
        )
    return note


def _refined_note(refined: Refined) -> str:
    chosen = f"; chosen: {refined.choice}" if refined.choice else ""
    return (
        f"{refined.label} ({refined.method}{chosen}, {refined.frames} frames, "
        f"{refined.message}): noise σ "
        + channel_text(refined.noise_sigma)
        + "; residual colour (1 = white) "
        + channel_text(refined.residual_colour)
        + (f"; input delay {refined.delay_text()}" if refined.delay_names else "")
        + (f"; propeller {refined.factor_text()}" if refined.factor_names else "")
    )


def _bias_notes(result: EstimatorResult) -> list[str]:
    """The sensor biases each filter estimated beside the coefficients."""
    notes = []
    for kind, f in result.filters.items():
        if result.bias_names:
            biases = ", ".join(
                f"{n.removesuffix('_bias')} {b:+.3g} ± {s:.2g}"
                for n, b, s in zip(result.bias_names, f.biases, f.bias_sigma, strict=True)
            )
            notes.append(f"{kind} sensor biases [SI]: {biases}")
    return notes


def _run_notes(vehicle: VehicleResult) -> list[str]:
    """What the run estimated beside the coefficients or fitted to start them, the noise
    it used, and its structure check."""
    result = vehicle.result
    notes = _bias_notes(result) + _segment_notes(result)
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
            "estimates is in σ (the JSON's sigma_parts.structure)" + _undecided_text(check)
        )
    return notes


def _segment_notes(result: EstimatorResult) -> list[str]:
    """The segments used and the frames left out, and each flight's part (segments.py)."""
    line = segments.describe(result.segments)
    return ([line] if line else []) + segments.describe_flights(result.flights)


def _undecided_text(check: StructureCheck) -> str:
    """What the structure check took as undecided by the data (weighting.py), and where
    the first filter's likelihood put it."""
    if not check.tolerances:
        return ""
    floor = " and at the configured noise" if "noise_floor" in check.parts else ""
    propeller = "".join(
        f", the propeller's {name} ±{1e2 * check.tolerances[key]:.0f} %"
        for key, name in (("thrust", "thrust"), ("zero_thrust_speed", "zero-thrust airspeed"))
        if key in check.tolerances
    )
    text = (
        f", as is how far they moved with the inputs ±{1e3 * check.tolerances['timing']:.0f}"
        f" ms in time, each sensor position ±{1e2 * check.tolerances['placement']:.0f} cm"
        f"{propeller}{floor}, times how far the likelihood leaves each from the configured "
        "(structure_check.sigma_parts)"
    )
    delay = check.found.get("input_delay_s")
    if delay is not None and math.isfinite(delay[1]):
        text += (
            f"; the inputs' timing the likelihood prefers: {1e3 * delay[0]:+.1f} ± "
            f"{1e3 * delay[1]:.1f} ms from [data] input_delay_s"
        )
    return text + _hold_text(check)


def _hold_text(check: StructureCheck) -> str:
    """The inputs held the other way between samples, and what the likelihood said of the
    two holds (decision 0071)."""
    if not math.isfinite(check.hold_change):
        return ""
    ran = check.input_hold
    preferred = check.hold_preferred
    if preferred and preferred != ran:
        verdict = f"the likelihood prefers {preferred}: the whole move counts"
    elif preferred == "previous":
        verdict = "the likelihood prefers the run's: the move does not count"
    else:
        said = "prefers the run's" if preferred else "does not tell the two apart"
        verdict = f"the likelihood {said}: the move counts as lying anywhere between"
    return (
        f"; with the inputs held the other way between samples ([data] input_hold "
        f'"{ran}"; -2 log likelihood {check.hold_change:+.0f}), {verdict} (sigma_parts.hold)'
    )


def final_table(vehicle: VehicleResult, refined: Refined | None = None) -> str:
    """The finished run's Table I (with convergence times) as results.md and the view
    hold it, what the run estimated beside the coefficients or fitted to start them,
    and the warnings."""
    table = markdown_table(vehicle.summaries, vehicle.result.config.truth_label, refined)
    text = table + bullets(_run_notes(vehicle))
    checks = check_lines(vehicle)
    if checks:
        text += "\n```\n" + "\n".join(checks) + "\n```\n"
    warnings = trust_warnings(vehicle, refined)
    if warnings:
        text += f"\n{WARNINGS_HEAD}\n\n" + bullets(warnings)
    return text


def check_lines(vehicle: VehicleResult) -> list[str]:
    """The held-out check (each channel's Theil U and RMS error, and the marks it
    dropped) and what to fly next, as lines (none where neither was made)."""
    out: list[str] = []
    if vehicle.holdout is not None:
        out += vehicle.holdout.lines()
        for name, why in (vehicle.holdout_drops or {}).items():
            out.append(f"  {name}: weak at best, {why}")
    if vehicle.advice is not None:
        out += vehicle.advice.lines()
    return out


def terminal_legend(refined: Refined | None) -> str:
    """The terminal's legend of its table: which σ, whose marks, where the rest is."""
    marks = "the IEKF's mark" if refined is None else f"the {refined.label} fit's mark"
    return (
        "σ: one standard deviation to trust (the filter covariance's, widened where the "
        "run showed it too small"
        + ("" if refined is None else f"; {refined.label}: the whole-record fit's")
        + "; its parts are in the JSON's sigma_parts); identified?: "
        + marks
        + ", from that σ and the correlations. The full table, with errors and convergence "
        "times, and the run's notes are in the results' .md file."
    )


def terminal_text(vehicle: VehicleResult, refined: Refined | None = None) -> str:
    """The finished run as the terminal shows it, within TERMINAL_WIDTH columns: Table I
    (terminal_table), a short legend, the sensor biases and the whole-record fit's note
    where there are some, and the warnings; the rest is in results.md (final_table)."""
    table = terminal_table(vehicle.summaries, vehicle.result.config.truth_label, refined)
    notes = _bias_notes(vehicle.result) + _segment_notes(vehicle.result)
    notes += [] if refined is None else [_refined_note(refined)]
    text = table + "\n" + bullets([terminal_legend(refined), *notes], TERMINAL_WIDTH)
    checks = check_lines(vehicle)
    if checks:
        text += "\n" + "\n".join(wrap(line) for line in checks) + "\n"
    warnings = trust_warnings(vehicle, refined)
    if warnings:
        text += f"\n{WARNINGS_HEAD}\n\n" + bullets(warnings, TERMINAL_WIDTH)
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
        elif math.isclose(used, read, rel_tol=1e-12):
            cells.append(f"{n} {used:.3g} (read)")
        else:
            cells.append(f"{n} {used:.3g} (configured; read {read:.3g})")
    return f"measurement noise (σ, SI; measurement_noise = {policy!r}): " + ", ".join(cells)


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
        row = [name] + ([fmt(truth[i])] if truth is not None else [])
        for k in kinds:
            snap = current[k]
            x = float(snap.coefficients[i])
            row += [fmt(x), f"{2 * snap.sigma[i]:.2g}"]
            if truth is not None:
                err = percent_error(x, truth[i])
                row.append("-" if err is None else f"{err:+.2f}")
        lines.append("| " + " | ".join([*row, marks[i]]) + " |")
    gusts = ", ".join(f"{k} {current[k].gust_sigma:.2f}" for k in kinds)
    return f"{estimator.frames} frames; turbulence σ_w [m/s]: {gusts}\n\n" + "\n".join(lines) + "\n"
