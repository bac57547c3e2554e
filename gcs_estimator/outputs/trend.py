"""Each vehicle's coefficients across its flights: a weighted control chart (decision 0042).

    gcs-estimator trend OUT/coefficients.parquet     (and at the end of `batch`)

The rows of a batch's coefficient table (outputs/tables.py) are grouped by vehicle
identity and ordered by flight time. For each vehicle, filter and coefficient with at
least MIN_FLIGHTS flights:

- centre line: the weighted mean (weights 1/sigma^2) of the baseline, the first
  BASELINE_SHARE of the flights (at least MIN_BASELINE);
- scale: each flight's sigma times the baseline's Birge ratio sqrt(chi^2 / dof) where it
  is above 1 (flights that scatter more than their sigmas say widen every limit, so a
  vehicle without a change is not flagged for sigmas that are too small);
- limits: centre +- Z_LIMIT x scaled sigma (with the centre's own uncertainty); a flight
  after the baseline outside them is flagged "shift";
- drift: the weighted least-squares slope over the flights' order (the sigmas as
  relative weights), its standard error from the residuals' own scatter (a weighted
  regression with unknown scale: the sigma to trust holds a part for the model's
  structure, the same on every flight of an airframe, which does not scatter from flight
  to flight); flagged when the slope's t statistic is beyond the two-sided
  DRIFT_FALSE_FLAG level of Student's t with flights - 2 degrees of freedom.

The levels keep the chance of a false flag on a vehicle with ten coefficients and no
change to about one in fifty. Written: trend.md (a table per vehicle, a figure
per coefficient), trend_<vehicle>_<coefficient>.svg (hand-written SVG), and trend.rrd
(a Rerun timeline of flights).
"""

from __future__ import annotations

import html
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from statistics import NormalDist
from typing import Any, TextIO

import numpy as np

MIN_FLIGHTS = 6
MIN_BASELINE = 5
BASELINE_SHARE = 1 / 3
DRIFT_FALSE_FLAG = 0.001
"""The drift test's level (two-sided): the chance of a drift flag on a coefficient that
did not change."""
FALSE_FLAG_SHARE = 0.001
"""The chance per coefficient that one of its flights falls outside the limits when
nothing changed (Z_LIMIT is the Bonferroni bound over the flights)."""


def z_limit(flights: int) -> float:
    """The limits' width in scaled sigmas for this many flights checked: at least 3."""
    return max(3.0, NormalDist().inv_cdf(1 - FALSE_FLAG_SHARE / (2 * max(flights, 1))))


def drift_limit(flights: int) -> float:
    """The slope's t statistic a drift needs over this many flights."""
    from scipy.stats import t as student

    return float(student.ppf(1 - DRIFT_FALSE_FLAG / 2, max(flights - 2, 1)))


@dataclass
class Chart:
    """One vehicle's coefficient across its flights, and what the chart flags."""

    vehicle: str
    filter: str
    coefficient: str
    times: list[datetime | None]
    logs: list[str]
    estimate: np.ndarray
    sigma: np.ndarray
    baseline: int = 0
    centre: float = math.nan
    centre_sigma: float = math.nan
    birge: float = 1.0
    limit_z: float = 3.0
    slope: float = math.nan
    """Change per flight."""
    slope_sigma: float = math.nan
    drift_z: float = math.nan
    """The slope's t statistic."""
    drift_limit: float = math.inf
    """The t statistic beyond which the slope is flagged (DRIFT_FALSE_FLAG)."""
    shifts: list[int] = field(default_factory=list)
    """Flights (indices) outside the limits."""
    note: str = ""

    @property
    def drift(self) -> bool:
        return math.isfinite(self.drift_z) and abs(self.drift_z) >= self.drift_limit

    @property
    def flagged(self) -> bool:
        return self.drift or bool(self.shifts)

    def limits(self) -> tuple[np.ndarray, np.ndarray]:
        half = self.limit_z * np.hypot(self.sigma * self.birge, self.centre_sigma)
        return self.centre - half, self.centre + half


def _weighted_mean(x: np.ndarray, s: np.ndarray) -> tuple[float, float, float]:
    """(mean, its sigma, Birge ratio >= 1) of values with sigmas."""
    w = 1.0 / s**2
    mean = float(np.sum(w * x) / np.sum(w))
    sigma = float(1.0 / math.sqrt(np.sum(w)))
    dof = len(x) - 1
    chi2 = float(np.sum(w * (x - mean) ** 2))
    birge = math.sqrt(chi2 / dof) if dof > 0 else 1.0
    return mean, sigma * max(birge, 1.0), max(birge, 1.0)


def _slope(x: np.ndarray, s: np.ndarray) -> tuple[float, float]:
    """Weighted least-squares slope of x over its index (weights 1/s^2), and its sigma
    from the residuals' scatter (the weights' scale unknown)."""
    i = np.arange(len(x), dtype=float)
    w = 1.0 / s**2
    a = np.array([[np.sum(w), np.sum(w * i)], [np.sum(w * i), np.sum(w * i * i)]])
    b = np.array([np.sum(w * x), np.sum(w * i * x)])
    cov = np.linalg.inv(a)
    coef = cov @ b
    resid = x - coef[0] - coef[1] * i
    dof = len(x) - 2
    scale = math.sqrt(float(np.sum(w * resid**2)) / dof) if dof > 0 else math.inf
    return float(coef[1]), math.sqrt(float(cov[1, 1])) * scale


def analyse(chart: Chart) -> Chart:
    """The chart's centre, limits, shifts and drift (the rule in the module's doc)."""
    x, s = chart.estimate, chart.sigma
    n = len(x)
    if n < MIN_FLIGHTS:
        chart.note = f"{n} flights: a chart needs {MIN_FLIGHTS}"
        return chart
    chart.baseline = max(MIN_BASELINE, math.ceil(n * BASELINE_SHARE))
    chart.centre, chart.centre_sigma, chart.birge = _weighted_mean(
        x[: chart.baseline], s[: chart.baseline]
    )
    after = n - chart.baseline
    chart.limit_z = z_limit(after)
    lo, hi = chart.limits()
    chart.shifts = [i for i in range(chart.baseline, n) if not lo[i] <= x[i] <= hi[i]]
    chart.slope, chart.slope_sigma = _slope(x, s)
    chart.drift_z = chart.slope / chart.slope_sigma if chart.slope_sigma > 0 else math.nan
    chart.drift_limit = drift_limit(n)
    return chart


def charts(rows: Sequence[Mapping[str, Any]], filter_kind: str = "IEKF") -> list[Chart]:
    """A chart per vehicle and coefficient of the table's rows (filter_kind's estimates;
    failed logs and estimates without a finite sigma left out), flights in time order."""
    groups: dict[tuple[str, str], list[Mapping[str, Any]]] = {}
    for r in rows:
        if r.get("status") != "ok" or r.get("filter") != filter_kind:
            continue
        est, sig = r.get("estimate"), r.get("sigma")
        if est is None or sig is None or not math.isfinite(est) or not sig > 0:
            continue
        groups.setdefault((str(r["vehicle"]), str(r["coefficient"])), []).append(r)
    out = []
    for (vehicle, name), group in sorted(groups.items()):
        group.sort(key=lambda r: (_sortable(r.get("flight_time_utc")), str(r.get("log"))))
        chart = Chart(
            vehicle,
            filter_kind,
            name,
            [r.get("flight_time_utc") for r in group],
            [str(r.get("log")) for r in group],
            np.array([float(r["estimate"]) for r in group]),
            np.array([float(r["sigma"]) for r in group]),
        )
        out.append(analyse(chart))
    return out


def _sortable(t: Any) -> float:
    return t.timestamp() if isinstance(t, datetime) else math.inf


def _file_name(chart: Chart) -> str:
    safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", f"{chart.vehicle}_{chart.coefficient}")
    return f"trend_{safe}.svg"


def markdown(all_charts: Sequence[Chart]) -> str:
    """The report: per vehicle, a row per coefficient and its figure."""
    lines = ["# Coefficient trends across flights", ""]
    lines += [
        "Each vehicle's flights in time order; centre: the baseline's weighted mean (its "
        "first third); limits: +- z x sigma (sigmas widened by the baseline's scatter where "
        "larger); drift: the weighted slope's t statistic beyond the two-sided "
        f"{100 * DRIFT_FALSE_FLAG:g} % level (decision 0042).",
        "",
    ]
    flagged = [c for c in all_charts if c.flagged]
    lines.append(
        f"Flagged: {len(flagged)} of {len(all_charts)} charts"
        + (": " + ", ".join(f"{c.vehicle} {c.coefficient}" for c in flagged) if flagged else "")
    )
    for vehicle in dict.fromkeys(c.vehicle for c in all_charts):
        mine = [c for c in all_charts if c.vehicle == vehicle]
        lines += ["", f"## {vehicle}", ""]
        lines.append(
            "| coefficient | flights | centre ± sigma | widened x | limit z | slope per 10 "
            "flights | drift t (limit) | flag |"
        )
        lines.append("|---|---|---|---|---|---|---|---|")
        for c in mine:
            lines.append(_row(c))
        lines.append("")
        for c in mine:
            if c.note:
                continue
            lines.append(f"![{c.vehicle} {c.coefficient}]({_file_name(c)})")
    return "\n".join(lines) + "\n"


def _row(c: Chart) -> str:
    n = len(c.estimate)
    if c.note:
        return f"| {c.coefficient} | {n} | {c.note} | | | | | |"
    flags = []
    if c.drift:
        flags.append("drift")
    if c.shifts:
        flags.append(f"shift at flight {', '.join(str(i + 1) for i in c.shifts[:5])}")
    rel = 100 * 10 * c.slope / abs(c.centre) if c.centre else math.nan
    return (
        f"| {c.coefficient} | {n} | {c.centre:.4g} ± {c.centre_sigma:.2g} | {c.birge:.2f} | "
        f"{c.limit_z:.2f} | {10 * c.slope:+.3g} ({rel:+.1f} %) | {c.drift_z:+.2f} "
        f"({c.drift_limit:.2f}) | "
        f"{'; '.join(flags) or '-'} |"
    )


SVG_W, SVG_H, PAD = 640, 300, 50


def svg(c: Chart) -> str:
    """The chart as SVG: each flight's estimate +- sigma, the centre line, the limits,
    the fitted slope, flagged flights in red."""
    n = len(c.estimate)
    lo, hi = c.limits()
    ys = np.concatenate([c.estimate - c.sigma, c.estimate + c.sigma, lo, hi])
    ymin, ymax = float(np.min(ys)), float(np.max(ys))
    if ymax <= ymin:
        ymax = ymin + 1.0

    def px(i: float) -> float:
        return PAD + (SVG_W - 2 * PAD) * (i / max(n - 1, 1))

    def py(v: float) -> float:
        return SVG_H - PAD - (SVG_H - 2 * PAD) * (v - ymin) / (ymax - ymin)

    title = html.escape(f"{c.vehicle} {c.coefficient} ({c.filter})")
    parts = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{SVG_W}" height="{SVG_H}" '
        f'viewBox="0 0 {SVG_W} {SVG_H}" font-family="sans-serif" font-size="11">',
        '<rect width="100%" height="100%" fill="white"/>',
        f'<text x="{PAD}" y="20" font-size="13">{title}</text>',
        f'<line x1="{PAD}" y1="{SVG_H - PAD}" x2="{SVG_W - PAD}" y2="{SVG_H - PAD}" '
        'stroke="black"/>',
        f'<line x1="{PAD}" y1="{PAD}" x2="{PAD}" y2="{SVG_H - PAD}" stroke="black"/>',
        f'<text x="{SVG_W / 2}" y="{SVG_H - 12}" text-anchor="middle">flight (time order)</text>',
        f'<text x="5" y="{py(ymax) + 4:.1f}">{ymax:.4g}</text>',
        f'<text x="5" y="{py(ymin) + 4:.1f}">{ymin:.4g}</text>',
    ]
    if math.isfinite(c.centre):
        parts.append(_polyline([(px(i), py(float(lo[i]))) for i in range(n)], "#999", dash=True))
        parts.append(_polyline([(px(i), py(float(hi[i]))) for i in range(n)], "#999", dash=True))
        parts.append(_polyline([(px(0), py(c.centre)), (px(n - 1), py(c.centre))], "#2a7"))
        parts.append(
            f'<line x1="{px(c.baseline - 0.5):.1f}" y1="{PAD}" x2="{px(c.baseline - 0.5):.1f}" '
            f'y2="{SVG_H - PAD}" stroke="#ccc"/>'
        )
    if math.isfinite(c.slope):
        a = _intercept(c)
        colour = "#d22" if c.drift else "#57c"
        parts.append(_polyline([(px(0), py(a)), (px(n - 1), py(a + c.slope * (n - 1)))], colour))
    for i in range(n):
        colour = "#d22" if i in c.shifts else "#124"
        x, e, s = px(i), float(c.estimate[i]), float(c.sigma[i])
        parts.append(
            f'<line x1="{x:.1f}" y1="{py(e - s):.1f}" x2="{x:.1f}" y2="{py(e + s):.1f}" '
            f'stroke="{colour}"/>'
        )
        parts.append(f'<circle cx="{x:.1f}" cy="{py(e):.1f}" r="2.5" fill="{colour}"/>')
    parts.append("</svg>")
    return "\n".join(parts) + "\n"


def _intercept(c: Chart) -> float:
    i = np.arange(len(c.estimate), dtype=float)
    w = 1.0 / c.sigma**2
    return float(np.sum(w * (c.estimate - c.slope * i)) / np.sum(w))


def _polyline(points: Sequence[tuple[float, float]], colour: str, dash: bool = False) -> str:
    pts = " ".join(f"{x:.1f},{y:.1f}" for x, y in points)
    style = ' stroke-dasharray="4 3"' if dash else ""
    return f'<polyline points="{pts}" fill="none" stroke="{colour}"{style}/>'


def recording(all_charts: Sequence[Chart], path: Path) -> None:
    """The charts as a Rerun recording: a `flight` timeline (each vehicle's flights in
    order) with, per vehicle and coefficient, the estimate, estimate +- sigma, the
    centre and the limits as series, and the flags as text."""
    import rerun as rr

    rec = rr.RecordingStream("gcs_estimator_trend")
    rec.save(path)
    for c in all_charts:
        if c.note:
            continue
        entity = f"trend/{_entity(c.vehicle)}/{_entity(c.coefficient)}"
        names = ["estimate", "estimate - sigma", "estimate + sigma", "centre", "lower", "upper"]
        rec.log(entity, rr.SeriesLines(names=names), static=True)
        lo, hi = c.limits()
        for i in range(len(c.estimate)):
            rec.set_time("flight", sequence=i + 1)
            e, s = float(c.estimate[i]), float(c.sigma[i])
            values = [e, e - s, e + s, c.centre, float(lo[i]), float(hi[i])]
            rec.log(entity, rr.Scalars(values))
            if i in c.shifts:
                rec.log(f"{entity}/flags", rr.TextLog(f"shift: {c.logs[i]}", level="WARN"))
        if c.drift:
            rec.set_time("flight", sequence=len(c.estimate))
            rec.log(f"{entity}/flags", rr.TextLog(f"drift: t {c.drift_z:+.2f}", level="WARN"))
    rec.flush(timeout_sec=30)
    rec.disconnect()


def _entity(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_-]+", "_", text)


def write_trend(
    rows: Sequence[Mapping[str, Any]],
    out: Path,
    view: str = "save",
    log: TextIO | None = None,
    filter_kind: str = "IEKF",
) -> list[Chart]:
    """trend.md, a figure per chart and (view "save") trend.rrd in out; the charts."""
    found = charts(rows, filter_kind)
    out.mkdir(parents=True, exist_ok=True)
    for c in found:
        if not c.note:
            (out / _file_name(c)).write_text(svg(c), encoding="utf-8")
    (out / "trend.md").write_text(markdown(found), encoding="utf-8")
    written = [out / "trend.md"]
    if view == "save":
        recording(found, out / "trend.rrd")
        written.append(out / "trend.rrd")
    flagged = [c for c in found if c.flagged]
    summary = ", ".join(f"{c.vehicle} {c.coefficient}" for c in flagged) or "none"
    print(f"trend: {len(found)} charts, flagged: {summary}")
    print("trend: " + ", ".join(str(p) for p in written))
    return found
