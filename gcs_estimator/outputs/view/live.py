"""The live view: buffers what each filter step produced and sends it to Rerun in blocks.

Per frame the estimator loop only appends references to lists (about a microsecond).
Every FLUSH_INTERVAL_S of wall-clock time (and at the end) the rows are stacked into
columns and sent with `send_columns`, one call per entity, so logging costs little next
to estimation however fast a replay runs. Coefficient estimates are decimated to
ESTIMATE_RATE_HZ (and the newest of each batch is always sent); their bands and the
display-only series to DISPLAY_RATE_HZ.
"""

from __future__ import annotations

import math
import sys
import time
import uuid
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import AircraftConfig
from gcs_estimator.estimation.estimator import FILTER_KINDS, FilterKind, StepOutput
from gcs_estimator.frames import Frame
from gcs_estimator.model.aircraft import build_model
from gcs_estimator.model.channels import FLIGHT_STATES, N_OBS, OBS_NAMES
from gcs_estimator.outputs.view import layout as lay
from gcs_estimator.outputs.view.outlets import (
    Columns,
    Layout,
    LocalOutlet,
    Op,
    Outlet,
    ProcessOutlet,
    RemoteSink,
    Style,
    Text,
)
from gcs_estimator.stop import PROCESS_STOP

if TYPE_CHECKING:
    from gcs_estimator.uncertainty.result import VehicleResult

KINDS = FILTER_KINDS

_DISPLAY_SCALE = np.array([1.0, 180.0 / math.pi, 180.0 / math.pi, 180.0 / math.pi])
"""SI states to display units: V m/s, alpha and theta deg, q deg/s."""


def _chi2_bounds() -> FloatArray:
    """95 % two-sided bounds of one NIS value with m = 0..7 degrees of freedom."""
    from scipy.stats import chi2

    out = np.full((N_OBS + 1, 2), np.nan)
    for m in range(1, N_OBS + 1):
        out[m] = chi2.ppf([0.025, 0.975], m)
    return out


LinkSource = Callable[[], tuple[float, Mapping[str, int]]]
"""Returns (session time [s], link counters) for the link entities."""

TableSource = Callable[[int], str]
"""Returns the current results table (Markdown) of a vehicle."""

LAYOUT_INTERVAL_S = 5.0
"""Wall clock between layouts sent because the coefficients' ranges moved."""
SETTLE_AFTER_RESTART_S = 1.0
"""Vehicle time after the last restart from which the estimates set the ranges for good
(before it, the zero start's wild seconds: only the newest batch does)."""
DISPLAY_RATE_HZ = 10.0
"""Rate of the display-only series and the ±2σ bands [Hz]."""
ESTIMATE_RATE_HZ = 25.0
"""Rate of the coefficient estimates in the view [Hz], the newest of each batch always
sent (the history file has every frame)."""
FLUSH_INTERVAL_S = 1.0
"""Wall clock between batches to the view [s]."""
RESULTS_INTERVAL_S = 5.0
ADVICE_INTERVAL_S = 30.0
"""What to fly next is worked out again this often [s], for one vehicle at a time in
turn: about a second of flying candidate manoeuvres through the model each time."""
"""Wall clock between refreshes of the live results table [s]."""
SHUTDOWN_TIMEOUT_S = 3.0
"""A viewer connection's time to drain at exit [s]."""
SERVER_MEMORY_LIMIT = "1GiB"
"""History a served view keeps for viewers that join late."""


@dataclass
class _Rows:
    """Frames of one vehicle not yet sent."""

    t: list[float] = field(default_factory=list)
    tv: list[float] = field(default_factory=list)
    u: list[FloatArray] = field(default_factory=list)
    y: list[FloatArray] = field(default_factory=list)
    outs: dict[FilterKind, list[StepOutput]] = field(default_factory=lambda: {k: [] for k in KINDS})
    last_bucket: float = math.nan
    """Display decimation: the last display interval a row was kept for."""
    last_estimate_bucket: float = math.nan
    """The same for the estimates (ESTIMATE_RATE_HZ)."""
    last_times: dict[str, float] = field(default_factory=dict)
    """Both timelines' values at the newest frame sent."""
    t_first: float = math.nan
    """Vehicle time of the first frame."""
    settled: FloatArray | None = None
    """[p x 2] lowest and highest estimate (band included) since the settle time."""
    recent: FloatArray | None = None
    """[p x 2] the same over the newest batch only."""

    def clear(self) -> None:
        self.t, self.tv, self.u, self.y = [], [], [], []
        self.outs = {k: [] for k in KINDS}


def first_in_interval(
    tv: FloatArray, rate_hz: float, last_bucket: float
) -> tuple[np.ndarray, float]:
    """Decimation to rate_hz: which of the times tv [s] (increasing) are the first in
    their 1/rate_hz interval, the interval of the last row kept before being
    last_bucket; and the newest interval. rate_hz 0: every row."""
    if rate_hz <= 0.0:
        return np.ones(len(tv), bool), last_bucket
    bucket = np.floor(tv * rate_hz)
    keep = np.empty(len(tv), bool)
    keep[0] = bucket[0] != last_bucket
    keep[1:] = bucket[1:] != bucket[:-1]
    return keep, float(bucket[-1])


class PanelRanges:
    """Each vehicle's coefficient panels' y ranges: the estimates with their ±2σ bands
    since the settle time (before it, over the newest batch) and the vehicle's truth,
    with a margin; and whether the ranges the viewer was sent are out of date."""

    def __init__(
        self,
        coefficients: slice,
        count: int,
        settle_s: float,
        truth_of: Callable[[int], FloatArray | None] | None,
    ) -> None:
        self.coefficients = coefficients
        """Where the coefficients are in the augmented state."""
        self.count = count
        """How many coefficients."""
        self.settle_s = settle_s
        """Vehicle time after the first frame from which the estimates set the ranges."""
        self.truth_of = truth_of
        """Each vehicle's truth (None: no truth lines are drawn)."""
        self.sent: dict[int, list[lay.Range | None]] = {}
        """The ranges of the last layout, per vehicle."""

    def track(
        self,
        rows: _Rows,
        tv: FloatArray,
        x: dict[FilterKind, FloatArray],
        sd: dict[FilterKind, FloatArray],
    ) -> None:
        """Lowest and highest estimate with its band (the band clipped to the estimate's
        own magnitude, so a coefficient the data barely constrain keeps its line in
        view) per coefficient: over this batch, and since the settle time."""
        if math.isnan(rows.t_first):
            rows.t_first = float(tv[0])
        coef = self.coefficients
        lows, highs = [], []
        for k in KINDS:
            est = x[k][:, coef]
            band = np.minimum(2.0 * sd[k][:, coef], np.abs(est))
            lows.append(est - band)
            highs.append(est + band)
        lo = np.fmin.reduce(lows)
        hi = np.fmax.reduce(highs)
        with np.errstate(all="ignore"):
            rows.recent = np.column_stack([np.nanmin(lo, axis=0), np.nanmax(hi, axis=0)])
            late = tv - rows.t_first >= self.settle_s
            if late.any():
                now = np.column_stack([np.nanmin(lo[late], axis=0), np.nanmax(hi[late], axis=0)])
                if rows.settled is None:
                    rows.settled = now
                else:
                    rows.settled = np.column_stack(
                        [
                            np.fmin(rows.settled[:, 0], now[:, 0]),
                            np.fmax(rows.settled[:, 1], now[:, 1]),
                        ]
                    )

    def of(self, sid: int, rows: _Rows, margin: float = 0.25) -> list[lay.Range | None]:
        """Each coefficient panel's range: the estimates and bands since the settle time
        (before it, of the newest batch) and the vehicle's truth, with a margin."""
        span = rows.settled if rows.settled is not None else rows.recent
        truth = None if self.truth_of is None else self.truth_of(sid)
        out: list[lay.Range | None] = []
        for i in range(self.count):
            t = None if truth is None else float(truth[i])
            if span is None:
                out.append(lay.coefficient_range(math.nan, math.nan, t, margin))
            else:
                lo, hi = float(span[i, 0]), float(span[i, 1])
                out.append(lay.coefficient_range(lo, hi, t, margin))
        return out

    def moved(self, vehicles: Mapping[int, _Rows]) -> bool:
        """Whether an estimate left its panel's range, or the range it would get now is
        less than half the one it has (the scale shrank as the estimates converged)."""
        for sid, rows in vehicles.items():
            sent = self.sent.get(sid)
            if sent is None:
                return True
            held = self.of(sid, rows, margin=0.0)
            wanted = self.of(sid, rows)
            for old, now, want in zip(sent, held, wanted, strict=True):
                if now is None or want is None:
                    continue
                if old is None or now[0] < old[0] or now[1] > old[1]:
                    return True
                if (want[1] - want[0]) < 0.5 * (old[1] - old[0]):
                    return True
        return False


def style_ops(
    sid: int, names: Sequence[str], axes: Sequence[str], truth_label: str | None
) -> list[Op]:
    """A new vehicle's series styles (sent once; truth_label None: no truth lines)."""
    ops: list[Op] = []
    for n, a in zip(names, axes, strict=True):
        ops.append(Style(lay.coefficient_path(sid, n, a), lay.COEFFICIENT_STYLE))
        ops.append(Style(lay.band_path(sid, n, a), lay.BAND_STYLE))
        if truth_label is not None:
            ops.append(Style(lay.truth_path(sid, n, a), lay.truth_style(truth_label)))
    ops += [
        Style(lay.state_path(sid, s), lay.state_style(s, unit))
        for s, unit in zip(FLIGHT_STATES, lay.STATE_UNITS, strict=True)
    ]
    ops.append(Style(lay.nis_path(sid), lay.NIS_STYLE))
    ops.append(Style(lay.turbulence_path(sid), lay.TURBULENCE_STYLE))
    ops += [Style(lay.innovation_path(sid, k), lay.innovation_style()) for k in KINDS]
    return ops


def band_columns(
    sid: int,
    names: Sequence[str],
    axes: Sequence[str],
    c0: int,
    times: dict[str, FloatArray],
    x: dict[FilterKind, FloatArray],
    sd: dict[FilterKind, FloatArray],
) -> list[Op]:
    """The ±2σ bands at the display rate (the estimates at ESTIMATE_RATE_HZ): the
    filters' covariance sigma as the run goes; c0: the first coefficient's column."""
    ops: list[Op] = []
    for i, name in enumerate(names):
        cols = []
        for k in KINDS:
            est, s2 = x[k][:, c0 + i], 2.0 * sd[k][:, c0 + i]
            cols += [est - s2, est + s2]
        ops.append(Columns(lay.band_path(sid, name, axes[i]), times, np.column_stack(cols)))
    return ops


def display_columns(
    sid: int,
    rows: _Rows,
    idx: np.ndarray,
    times: dict[str, FloatArray],
    x: dict[FilterKind, FloatArray],
    flight_start: int,
    power_input: str,
    chi2: FloatArray,
) -> list[Op]:
    """The display-only series of the rows idx: states measured and estimated, inputs,
    NIS with its 95 % bounds (chi2: _chi2_bounds), turbulence levels, innovations in
    their sigmas."""
    y = np.array(rows.y)[idx]
    u = np.array(rows.u)[idx]
    ops: list[Op] = []
    for j, s in enumerate(FLIGHT_STATES):
        col = flight_start + j
        vals = np.column_stack([y[:, j], x["EKF"][idx, col], x["IEKF"][idx, col]])
        ops.append(Columns(lay.state_path(sid, s), times, vals * _DISPLAY_SCALE[j]))
    ops.append(Columns(lay.input_path(sid, "elevator"), times, np.degrees(u[:, :1])))
    ops.append(Columns(lay.input_path(sid, power_input), times, u[:, 1:2]))
    outs = {k: [rows.outs[k][i] for i in idx] for k in KINDS}
    m = np.array([o.info.n_used for o in outs["IEKF"]], int)
    nis = np.column_stack([np.array([o.info.nis for o in outs[k]]) for k in KINDS] + [chi2[m]])
    ops.append(Columns(lay.nis_path(sid), times, nis))
    gust = np.column_stack(
        [np.array([o.info.gust_sigma for o in outs[k]]) for k in KINDS]
        + [np.array([o.info.gust_pass_sigma for o in outs[k]]) for k in KINDS]
    )
    ops.append(Columns(lay.turbulence_path(sid), times, gust))
    for k in KINDS:
        e = np.array([o.info.innovation for o in outs[k]])
        sig = np.array([o.info.innovation_sigma for o in outs[k]])
        with np.errstate(invalid="ignore", divide="ignore"):
            z = e / sig
        guides = np.tile([-2.0, 2.0], (len(idx), 1))
        ops.append(Columns(lay.innovation_path(sid, k), times, np.hstack([z, guides])))
    return ops


def link_columns(t: float, counts: Mapping[str, int], last: tuple[float, int]) -> list[Op]:
    """The link entities at session time t [s]: the packet rate since `last` (session
    time, packets received then) and the counts of what went wrong."""
    ops: list[Op] = []
    received = int(counts.get("received", 0))
    if t > last[0]:
        rate = (received - last[1]) / (t - last[0])
        ops.append(Columns(lay.LINK_RATE, {lay.TIMELINE: np.array([t])}, np.array([[rate]])))
    vals = [counts.get(k, 0) for k in ("lost", "duplicates", "out_of_order", "corrupt")]
    ops.append(Columns(lay.LINK_COUNTS, {lay.TIMELINE: np.array([t])}, np.array([vals], float)))
    return ops


class LiveAdvice:
    """What to fly next while flying: every ADVICE_INTERVAL_S, the next vehicle's in
    turn, at its latest measured airspeed."""

    def __init__(self, source: Callable[[int, float], str], now: float) -> None:
        self.source = source
        """A vehicle's advice (Markdown) at an airspeed [m/s] (NaN: not measured)."""
        self.last = now
        self.turn = 0
        self.airspeed: dict[int, float] = {}

    def saw(self, sid: int, airspeed: float) -> None:
        if math.isfinite(airspeed):
            self.airspeed[sid] = airspeed

    def due(self, now: float, rows: Mapping[int, _Rows]) -> list[Op]:
        """The next vehicle's advice where the interval has passed."""
        if not rows or now - self.last < ADVICE_INTERVAL_S:
            return []
        self.last = now
        ids = sorted(rows)
        sid = ids[self.turn % len(ids)]
        self.turn += 1
        at = rows[sid].last_times
        if not at:
            return []
        text = self.source(sid, self.airspeed.get(sid, math.nan))
        return [Text(lay.advice_path(sid), at, text)]


def final_check_ops(checked: Mapping[int, VehicleResult], rows: Mapping[int, _Rows]) -> list[Op]:
    """Each checked vehicle's advice and held-out overlay (check_ops), at its last times."""
    ops: list[Op] = []
    for sid, vehicle in checked.items():
        own = rows.get(sid)
        if own is not None and own.last_times:
            ops += check_ops(sid, vehicle, own.last_times)
    return ops


# Over 200 lines: the view's one sender; per-frame buffering, flushing, layout, the live
# advice's turn and the final panels share its rows and outlets.
class RerunView:
    """Sends estimates, states, inputs and diagnostics of every vehicle to the outlets."""

    def __init__(
        self,
        outlets: Sequence[Outlet],
        config: AircraftConfig,
        link_source: LinkSource | None = None,
        table_source: TableSource | None = None,
        clock: Callable[[], float] = time.monotonic,
        truth_of: Callable[[int], FloatArray | None] | None = None,
        advice_source: Callable[[int, float], str] | None = None,
    ) -> None:
        self.outlets = list(outlets)
        self.advice = None if advice_source is None else LiveAdvice(advice_source, clock())
        self.config = config
        self.names = config.coefficient_names
        self.axes = config.structure.axes
        model = build_model(config)
        self.flight = model.flight
        self.coefficients = model.coefficients
        self.truth = None if config.truth is None else np.array(config.truth, float)
        """The config's [truth]: the viewer's layout draws a truth line when it is set."""
        self.truth_of = truth_of if truth_of is not None else (lambda sid: self.truth)
        """Each vehicle's own truth (Session.truth_of); NaN where a vehicle has none."""
        self.truth_label = config.truth_label
        self.power_input = config.propulsion.input_name
        self.link_source = link_source
        self.table_source = table_source
        self.clock = clock
        self.rate = DISPLAY_RATE_HZ
        self.estimate_rate = ESTIMATE_RATE_HZ
        self.rows: dict[int, _Rows] = {}
        self._layout_due = False
        self._chi2 = _chi2_bounds()
        self._last_flush = clock()
        self._last_table = -math.inf
        restarts = config.filter.restart_times_s
        self.ranges = PanelRanges(
            self.coefficients,
            len(self.names),
            (restarts[-1] if restarts else 0.0) + SETTLE_AFTER_RESTART_S,
            self.truth_of if self.truth is not None else None,
        )
        self._last_layout = -math.inf
        self._newest: dict[str, float] = {}
        """Both timelines' values at the newest frame of any vehicle (for the link)."""
        self._link_last = (0.0, 0)
        """(session time, packets received) at the last link update; the session starts
        at 0 with nothing received."""
        self.frames_sent = 0

    # ------------------------------------------------------------ per frame
    def step(
        self,
        system_id: int,
        t_session: float,
        t_vehicle: float,
        u: FloatArray,
        y: FloatArray,
        outs: Mapping[FilterKind, StepOutput],
    ) -> None:
        rows = self.rows.get(system_id)
        if rows is None:
            rows = self.rows[system_id] = _Rows()
            self._announce(system_id)
        if self.advice is not None:
            self.advice.saw(system_id, float(y[0]))
        rows.t.append(t_session)
        rows.tv.append(t_vehicle)
        rows.u.append(u)
        rows.y.append(y)
        for k in KINDS:
            rows.outs[k].append(outs[k])
        self.tick()

    def tick(self) -> None:
        """Send what is buffered if the flush interval has passed (call it when idle too)."""
        if self.clock() - self._last_flush >= FLUSH_INTERVAL_S:
            self.flush()

    def _announce(self, system_id: int) -> None:
        """A new vehicle: style its series once, and lay the viewer out for all vehicles."""
        label = self.truth_label if self.truth is not None else None
        for op in style_ops(system_id, self.names, self.axes, label):
            self._send(op)
        if len(self.rows) == 1:
            self._send(Text(lay.LEGEND, {}, lay.legend_text(label)))
            self._send_layout()  # the first vehicle is laid out at once
        else:
            self._layout_due = True  # the others with the next batch: one layout per burst

    def _send_layout(self, marks: Mapping[int, Sequence[str]] | None = None) -> None:
        """The viewer's layout for every vehicle so far, with each coefficient panel's
        range. It is a whole blueprint each time, so it goes at most once per batch:
        vehicles that appear together (a fleet coming up) cost one layout, not one per
        vehicle with all the vehicles before."""
        ranges = {sid: self.ranges.of(sid, rows) for sid, rows in self.rows.items()}
        self.ranges.sent = ranges
        ids = tuple(sorted(self.rows))
        self._send(Layout(ids, self.names, self.axes, self.power_input, ranges, dict(marks or {})))
        self._layout_due = False
        self._last_layout = self.clock()

    # ------------------------------------------------------------ sending
    def _send(self, op: Op) -> None:
        for outlet in self.outlets:
            outlet.send(op)

    def flush(self) -> None:
        """Send every buffered row; update the link entities and, now and then, the
        results tables."""
        self._last_flush = self.clock()
        for sid, rows in self.rows.items():
            if rows.t:
                self._send_rows(sid, rows)
        if self._layout_due or (
            self._last_flush - self._last_layout >= LAYOUT_INTERVAL_S
            and self.ranges.moved(self.rows)
        ):
            self._send_layout()
        self._send_link()
        if self.table_source is not None and (
            self._last_flush - self._last_table >= RESULTS_INTERVAL_S
        ):
            self._last_table = self._last_flush
            for sid, rows in self.rows.items():
                self._send(Text(lay.results_path(sid), rows.last_times, self.table_source(sid)))
        if self.advice is not None:
            for op in self.advice.due(self._last_flush, self.rows):
                self._send(op)

    def _send_rows(self, sid: int, rows: _Rows) -> None:
        n = len(rows.t)
        t = np.array(rows.t)
        tv = np.array(rows.tv)
        times = {lay.TIMELINE: tv, lay.RECEIVE_TIMELINE: t}
        x = {k: np.array([o.x for o in rows.outs[k]]) for k in KINDS}
        sd = {k: np.array([o.info.sigma for o in rows.outs[k]]) for k in KINDS}
        c0 = self.coefficients.start
        self.ranges.track(rows, tv, x, sd)
        ends = [0, n - 1] if n > 1 else [0]
        own = self.truth_of(sid) if self.truth is not None else None
        keep, rows.last_estimate_bucket = first_in_interval(
            tv, self.estimate_rate, rows.last_estimate_bucket
        )
        keep[-1] = True  # the newest estimate is always shown
        e_idx = np.flatnonzero(keep)
        e_times = {name: v[e_idx] for name, v in times.items()}
        for i, name in enumerate(self.names):
            est = np.column_stack([x[k][e_idx, c0 + i] for k in KINDS])
            self._send(Columns(lay.coefficient_path(sid, name, self.axes[i]), e_times, est))
            if self.truth is not None:
                # A constant: the first and last frame of each batch draw its line.
                value = math.nan if own is None else float(own[i])
                at = {tl: v[ends] for tl, v in times.items()}
                truth = np.full((len(ends), 1), value)
                self._send(Columns(lay.truth_path(sid, name, self.axes[i]), at, truth))
        self.frames_sent += n

        # Display-only series: one row per display interval of vehicle time.
        keep, rows.last_bucket = first_in_interval(tv, self.rate, rows.last_bucket)
        rows.last_times = {lay.TIMELINE: float(tv[-1]), lay.RECEIVE_TIMELINE: float(t[-1])}
        self._newest = rows.last_times
        idx = np.flatnonzero(keep)
        if len(idx):
            shown = {name: v[idx] for name, v in times.items()}
            xs, sds = {k: x[k][idx] for k in KINDS}, {k: sd[k][idx] for k in KINDS}
            ops = band_columns(sid, self.names, self.axes, c0, shown, xs, sds)
            ops += display_columns(
                sid, rows, idx, shown, x, self.flight.start, self.power_input, self._chi2
            )
            for op in ops:
                self._send(op)
        rows.clear()

    def _send_link(self) -> None:
        if self.link_source is None:
            return
        t, counts = self.link_source()
        if math.isfinite(t):
            for op in link_columns(t, counts, self._link_last):
                self._send(op)
            self._link_last = (t, int(counts.get("received", 0)))

    def close(
        self,
        final_tables: Mapping[int, str] | None = None,
        marks: Mapping[int, Sequence[str]] | None = None,
        warnings: Sequence[str] = (),
        checked: Mapping[int, VehicleResult] | None = None,
    ) -> None:
        """Send what is left, the final layout (ranges of the whole run, identifiability
        in the panel titles), the legend with the run's warnings, the final results
        tables, and each checked vehicle's advice and held-out overlay; close every
        outlet."""
        self.flush()
        if self.rows:
            self._send_layout(marks)
            label = self.truth_label if self.truth is not None else None
            self._send(Text(lay.LEGEND, {}, lay.legend_text(label, warnings)))
        for sid, text in (final_tables or {}).items():
            rows = self.rows.get(sid)
            if rows is not None and rows.last_times:
                self._send(Text(lay.results_path(sid), rows.last_times, text))
        for op in final_check_ops(checked or {}, self.rows):
            self._send(op)
        for outlet in self.outlets:
            outlet.close()


def check_ops(sid: int, vehicle: VehicleResult, at: Mapping[str, float]) -> list[Op]:
    """A finished vehicle's advice (at the times `at`) and the held-out overlay
    (measured and predicted per channel, on the segment's own clock; the check's figures
    are in the final results table)."""
    ops: list[Op] = []
    if vehicle.advice is not None:
        ops.append(Text(lay.advice_path(sid), dict(at), advice_markdown(vehicle.advice.lines())))
    h = vehicle.holdout
    if h is not None:
        for c, name in enumerate(OBS_NAMES):
            if not np.isfinite(h.predicted[:, c]).any():
                continue
            path = lay.validation_path(sid, name)
            ops.append(Style(path, lay.VALIDATION_STYLE))
            values = np.column_stack([h.measured[:, c], h.predicted[:, c]])
            ops.append(Columns(path, {lay.TIMELINE: np.asarray(h.t, float)}, values))
    return ops


def advice_markdown(lines: Sequence[str]) -> str:
    """Lines as a Markdown code block (kept as they are laid out)."""
    return "```\n" + "\n".join(lines) + "\n```\n"


class ViewSink:
    """The view as a session sink: every frame's outputs, refreshed when idle, final
    tables at the end (with the checks outputs.checks made of each vehicle, where
    `checked` has them: that sink must finish before this one)."""

    def __init__(
        self,
        view: RerunView,
        t_zero: Callable[[], float] | None = None,
        checked: Callable[[], Mapping[int, VehicleResult]] | None = None,
    ) -> None:
        self.checked = checked
        self.view = view
        self.t_zero = t_zero
        """Zero of the receive timeline (the session's first packet); default: the first
        frame's time."""
        self._t0 = math.nan

    def on_frame(self, frame: Frame, outs: Mapping[FilterKind, StepOutput]) -> None:
        if math.isnan(self._t0):
            self._t0 = self.t_zero() if self.t_zero is not None else frame.t_recv_s
        self.view.step(
            frame.system_id,
            frame.t_recv_s - self._t0,
            frame.t_vehicle_s,
            frame.inputs,
            frame.y,
            outs,
        )

    def tick(self) -> None:
        self.view.tick()

    def finish(self, results: Mapping[int, VehicleResult], link: Mapping[str, Any] | None) -> None:
        from gcs_estimator.outputs.diagnosis import trust_warnings
        from gcs_estimator.outputs.table import final_table

        marks = {}
        done = {} if self.checked is None else self.checked()
        for sid, v in results.items():
            v = done.get(sid, v)
            s = v.summaries.get("IEKF") or next(iter(v.summaries.values()), None)
            if s is not None:
                marks[sid] = [c.identifiability for c in s.coefficients]
        warnings = [
            (f"vehicle {sid}: " if len(results) > 1 else "") + w
            for sid, v in results.items()
            for w in trust_warnings(v)
        ]
        checked = {} if self.checked is None else dict(self.checked())
        self.view.close(
            {sid: final_table(checked.get(sid, v)) for sid, v in results.items()},
            marks,
            warnings,
            checked,
        )


# ------------------------------------------------------------------ opening


def _viewer_command() -> str:
    """How to call the viewer from here: the environment's own binary when it is not on
    PATH (a project .venv that is not activated), else plain `rerun`."""
    import os
    import shutil

    from gcs_estimator.outputs.view.outlets import viewer_executable

    own = viewer_executable()
    if own is None or shutil.which("rerun") == own:
        return "rerun"
    rel = os.path.relpath(own)
    return rel if not rel.startswith("..") else own


def has_display() -> bool:
    import os

    return sys.platform in ("darwin", "win32") or bool(
        os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    )


@dataclass(frozen=True)
class ViewChoice:
    """Resolved outputs for one session."""

    save: Path | None
    serve: bool
    spawn: bool
    connect: str | None

    @property
    def any(self) -> bool:
        return self.save is not None or self.serve or self.spawn or self.connect is not None


def resolve_outputs(
    config: AircraftConfig, outputs: Sequence[str], default_rrd: Path
) -> ViewChoice:
    """Turn the outputs asked for ("auto" included) into concrete sinks."""
    wanted = set(outputs)
    if "off" in wanted:
        return ViewChoice(None, False, False, None)
    if "auto" in wanted:
        wanted.discard("auto")
        wanted.add("save")
        if has_display():
            wanted.add("spawn")
    rrd = Path(config.view.rrd_path) if config.view.rrd_path else default_rrd
    return ViewChoice(
        save=rrd if "save" in wanted else None,
        serve="serve" in wanted,
        spawn="spawn" in wanted,
        connect=config.view.connect_url if "connect" in wanted else None,
    )


def open_outlets(
    config: AircraftConfig, choice: ViewChoice, log: TextIO = sys.stderr
) -> list[Outlet]:
    """Open the outlets chosen and say where the view goes and how to look at it."""
    vc = config.view
    recording_id = str(uuid.uuid4())
    viewer = _viewer_command()
    outlets: list[Outlet] = []
    if choice.save is not None or choice.serve:
        local = LocalOutlet(
            recording_id,
            save=choice.save,
            serve=(vc.serve_bind, vc.serve_port, SERVER_MEMORY_LIMIT) if choice.serve else None,
            shutdown_timeout_s=SHUTDOWN_TIMEOUT_S,
            linger_s=vc.serve_linger_s,
            stop=PROCESS_STOP,
            log=log,
        )
        outlets.append(local)
        if choice.save is not None:
            print(f"view: saving to {choice.save}; open it with: {viewer} {choice.save}", file=log)
        if local.server_uri is not None:
            print(
                f"view: serving live at {local.server_uri}; join (any time) with: "
                f"{viewer} {local.server_uri}",
                file=log,
            )
    remote: list[RemoteSink] = []
    if choice.spawn:
        remote.append(("spawn", str(vc.viewer_port)))
    if choice.connect is not None:
        remote.append(("connect", choice.connect))
    if remote:
        outlet = ProcessOutlet(remote, recording_id, SHUTDOWN_TIMEOUT_S)
        outlets.append(outlet)
        print(f"view: {outlet.description}", file=log)
    return outlets
