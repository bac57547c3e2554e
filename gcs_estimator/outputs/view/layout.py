"""What the Rerun view shows, where (entity paths), and how the viewer lays it out.

Entity paths (documented in the README; tests read them back):

    /vehicle/{id}/coefficients/{drag|lift|moment}/{name}
        Scalars [EKF, IEKF] at live.ESTIMATE_RATE_HZ, and the newest of each batch
    /vehicle/{id}/coefficients/{drag|lift|moment}/{name}/band
        Scalars [EKF - 2σ, EKF + 2σ, IEKF - 2σ, IEKF + 2σ] at the display rate
    /vehicle/{id}/coefficients/{drag|lift|moment}/{name}/truth
        Scalars [truth] at the first and last frame of each batch (a constant: a line)
    /vehicle/{id}/states/{V|alpha|theta|q}
        Scalars [measured, EKF, IEKF]; V in m/s, angles in deg, q in deg/s
    /vehicle/{id}/inputs/elevator          Scalars [elevator deg]
    /vehicle/{id}/inputs/{throttle|thrust} Scalars [throttle 0..1 or thrust N]
    /vehicle/{id}/diagnostics/nis          Scalars [EKF, IEKF, 95 % low, 95 % high]
    /vehicle/{id}/diagnostics/turbulence   Scalars [EKF, IEKF, EKF over the pass,
        IEKF over the pass]: the gust intensity sigma_w [m/s] each filter's process
        noise assumes (0: calm air), and its average over the pass so far (what the
        whole pass says of the air where the running level does not pass detection)
    /vehicle/{id}/diagnostics/innovations/{EKF|IEKF}
        Scalars, one per observation channel: innovation / its predicted sigma
        (NaN where the channel was missing), with ±2 guide lines
    /vehicle/{id}/results                  TextDocument (Markdown): the current table
    /vehicle/{id}/advice                   TextDocument (Markdown): what to fly next,
        refreshed every live.ADVICE_INTERVAL_S while flying, the run's at the end
    /vehicle/{id}/validation/{channel}     Scalars [measured, predicted]: the held-out
        check's overlay (--validate), at the end; channels of OBS_NAMES, SI units
    /legend                                TextDocument (Markdown, static): how to read the
        plots; at the end, the run's warnings too
    /link/rate                             Scalars [packets/s]
    /link/counts                           Scalars [lost, duplicates, out of order, corrupt]

Timelines (durations, seconds): "flight_time", the vehicle's own clock (the data's time
offline), and "receive_time", seconds since the session's first packet (the data's first
sample offline). The link entities take the flight time of the newest frame. Display-only
series are decimated to live.DISPLAY_RATE_HZ.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from gcs_estimator.config import AXES
from gcs_estimator.model.channels import FLIGHT_STATES, OBS_NAMES

GROUPS: dict[str, str] = {"CD": "drag", "CL": "lift", "Cm": "moment"}
"""Coefficient group of each axis, as it appears in entity paths and the layout."""

TIMELINE = "flight_time"
RECEIVE_TIMELINE = "receive_time"

STATE_UNITS: tuple[str, ...] = ("m/s", "deg", "deg", "deg/s")

EKF_COLOR = (31, 119, 180)
IEKF_COLOR = (255, 127, 14)
TRUTH_COLOR = (44, 160, 44)
"""Green, drawn wider than the estimates: it stands out on the dark and the light theme."""
GUIDE_COLOR = (150, 150, 150)
"""Reference lines (chi-square bounds, +-2): grey."""
MEASURED_COLOR = (120, 120, 120)
LEGEND = "/legend"

Range = tuple[float, float]


def _lighter(rgb: tuple[int, int, int]) -> tuple[int, int, int, int]:
    return (rgb[0], rgb[1], rgb[2], 150)


def vehicle_root(system_id: int) -> str:
    return f"/vehicle/{system_id}"


def coefficient_path(system_id: int, name: str, axis: str) -> str:
    """Entity of coefficient `name` of `axis` ("CD", "CL" or "Cm"; the config's structure)."""
    return f"{vehicle_root(system_id)}/coefficients/{GROUPS[axis]}/{name}"


def band_path(system_id: int, name: str, axis: str) -> str:
    return coefficient_path(system_id, name, axis) + "/band"


def truth_path(system_id: int, name: str, axis: str) -> str:
    return coefficient_path(system_id, name, axis) + "/truth"


def state_path(system_id: int, state: str) -> str:
    return f"{vehicle_root(system_id)}/states/{state}"


def input_path(system_id: int, which: str) -> str:
    return f"{vehicle_root(system_id)}/inputs/{which}"


def nis_path(system_id: int) -> str:
    return f"{vehicle_root(system_id)}/diagnostics/nis"


def turbulence_path(system_id: int) -> str:
    return f"{vehicle_root(system_id)}/diagnostics/turbulence"


def innovation_path(system_id: int, kind: str) -> str:
    return f"{vehicle_root(system_id)}/diagnostics/innovations/{kind}"


def results_path(system_id: int) -> str:
    return f"{vehicle_root(system_id)}/results"


def advice_path(system_id: int) -> str:
    return f"{vehicle_root(system_id)}/advice"


def validation_path(system_id: int, channel: str | None = None) -> str:
    root = f"{vehicle_root(system_id)}/validation"
    return root if channel is None else f"{root}/{channel}"


LINK_RATE = "/link/rate"
LINK_COUNTS = "/link/counts"


@dataclass(frozen=True)
class SeriesStyle:
    """Static styling of one multi-series entity: names, colours (RGBA) and widths."""

    names: tuple[str, ...]
    colors: tuple[tuple[int, int, int, int], ...]
    widths: tuple[float, ...]


def _style(*series: tuple[str, tuple[int, ...], float]) -> SeriesStyle:
    return SeriesStyle(
        names=tuple(s[0] for s in series),
        colors=tuple(
            (c[0], c[1], c[2], c[3] if len(c) > 3 else 255) for c in (s[1] for s in series)
        ),
        widths=tuple(s[2] for s in series),
    )


COEFFICIENT_STYLE = _style(("EKF", EKF_COLOR, 2.0), ("IEKF", IEKF_COLOR, 2.0))
BAND_STYLE = _style(
    ("EKF -2σ", _lighter(EKF_COLOR), 1.5),
    ("EKF +2σ", _lighter(EKF_COLOR), 1.5),
    ("IEKF -2σ", _lighter(IEKF_COLOR), 1.5),
    ("IEKF +2σ", _lighter(IEKF_COLOR), 1.5),
)


def truth_style(truth_label: str) -> SeriesStyle:
    return _style((truth_label, TRUTH_COLOR, 3.0))


def state_style(state: str, unit: str) -> SeriesStyle:
    return _style(
        (f"measured {state} [{unit}]", MEASURED_COLOR, 1.0),
        ("EKF", EKF_COLOR, 1.5),
        ("IEKF", IEKF_COLOR, 1.5),
    )


NIS_STYLE = _style(
    ("EKF", EKF_COLOR, 1.0),
    ("IEKF", IEKF_COLOR, 1.0),
    ("95 % low", GUIDE_COLOR, 1.0),
    ("95 % high", GUIDE_COLOR, 1.0),
)

VALIDATION_STYLE = _style(
    ("measured", MEASURED_COLOR, 1.0),
    ("predicted", IEKF_COLOR, 2.0),
)

TURBULENCE_STYLE = _style(
    ("EKF", EKF_COLOR, 1.0),
    ("IEKF", IEKF_COLOR, 1.0),
    ("EKF over the pass", _lighter(EKF_COLOR), 2.0),
    ("IEKF over the pass", _lighter(IEKF_COLOR), 2.0),
)


def innovation_style() -> SeriesStyle:
    palette = (
        (31, 119, 180),
        (255, 127, 14),
        (44, 160, 44),
        (214, 39, 40),
        (148, 103, 189),
        (140, 86, 75),
        (227, 119, 194),
    )
    series = [(n, palette[i % len(palette)], 1.0) for i, n in enumerate(OBS_NAMES)]
    series += [("-2", GUIDE_COLOR, 1.0), ("+2", GUIDE_COLOR, 1.0)]
    return _style(*series)


def legend_text(truth_label: str | None, warnings: Sequence[str] = ()) -> str:
    """How to read the coefficient plots (one legend for the whole grid); at the end, what
    to check before trusting them, first (the panel is small)."""
    text = (
        "**Coefficients:** blue **EKF**, orange **IEKF**; lighter lines of each colour: ±2σ "
        "of the filter's covariance as the run goes (the final table's σ, the one to trust, "
        "widens it where the run shows it too small)"
    )
    if truth_label:
        text += f"; wide green: **{truth_label}**"
    text += (
        ". Ranges follow the estimates once the zero start settles (double-click a plot "
        "for the whole run); at the end the titles mark what the flight did not identify."
    )
    if warnings:
        text = "**Before trusting these numbers:** " + "; ".join(warnings) + ".\n\n" + text
    return text


def coefficient_range(
    lo: float, hi: float, truth: float | None = None, margin: float = 0.25
) -> Range | None:
    """A panel's y range holding [lo, hi] (the estimates and their bands) and the truth,
    widened by `margin` of their span on each side; None when nothing is finite."""
    values = [v for v in (lo, hi, truth) if v is not None and math.isfinite(v)]
    if not values:
        return None
    low, high = min(values), max(values)
    span = max(high - low, 0.05 * max(abs(low), abs(high)), 1e-9)
    return (low - margin * span, high + margin * span)


def build_blueprint(
    system_ids: Sequence[int],
    names: Sequence[str],
    axes: Sequence[str],
    power_input: str,
    ranges: Mapping[int, Sequence[Range | None]] | None = None,
    marks: Mapping[int, Sequence[str]] | None = None,
) -> object:
    """The viewer's layout: per vehicle, the drag, lift and moment coefficients side by
    side on top, one legend for all of them below, and states, inputs, diagnostics and
    the results table in tabs under that. Several vehicles get one tab each."""
    import rerun.blueprint as rrb

    def coefficient_view(sid: int, i: int) -> rrb.TimeSeriesView:
        name = names[i]
        own = (ranges or {}).get(sid)
        rng = None if own is None else own[i]
        mark = (marks or {}).get(sid)
        title = name if not mark or mark[i] == "identified" else f"{name} ({mark[i]})"
        return rrb.TimeSeriesView(
            origin=coefficient_path(sid, name, axes[i]),
            name=title,
            axis_y=rrb.ScalarAxis(range=rng) if rng is not None else None,
            plot_legend=rrb.PlotLegend(visible=False),
        )

    per_vehicle = []
    for sid in system_ids:
        columns = []
        for axis in AXES:
            group = [i for i, a in enumerate(axes) if a == axis]
            if not group:
                continue
            columns.append(
                rrb.Vertical(
                    *[coefficient_view(sid, i) for i in group],
                    name=f"{GROUPS[axis]} ({axis})",
                )
            )
        states = rrb.Grid(
            *[
                rrb.TimeSeriesView(origin=state_path(sid, s), name=f"{s} [{u}]")
                for s, u in zip(FLIGHT_STATES, STATE_UNITS, strict=True)
            ],
            name="states",
        )
        inputs = rrb.Vertical(
            rrb.TimeSeriesView(origin=input_path(sid, "elevator"), name="elevator [deg]"),
            rrb.TimeSeriesView(origin=input_path(sid, power_input), name=power_input),
            name="inputs",
        )
        diagnostics = rrb.Grid(
            rrb.TimeSeriesView(origin=nis_path(sid), name="NIS"),
            rrb.TimeSeriesView(origin=turbulence_path(sid), name="turbulence σ_w [m/s]"),
            rrb.TimeSeriesView(origin=innovation_path(sid, "EKF"), name="EKF innovations / σ"),
            rrb.TimeSeriesView(origin=innovation_path(sid, "IEKF"), name="IEKF innovations / σ"),
            rrb.TimeSeriesView(origin="/link", name="link"),
            name="diagnostics",
        )
        results = rrb.TextDocumentView(origin=results_path(sid), name="results")
        advice = rrb.TextDocumentView(origin=advice_path(sid), name="what to fly next")
        held_out = rrb.Grid(
            *[
                rrb.TimeSeriesView(origin=validation_path(sid, c), name=f"held out: {c}")
                for c in OBS_NAMES
            ],
            name="held-out check",
        )
        per_vehicle.append(
            rrb.Vertical(
                rrb.Horizontal(*columns, name="coefficients"),
                rrb.TextDocumentView(origin=LEGEND, name="how to read"),
                rrb.Tabs(states, inputs, diagnostics, results, advice, held_out, name="flight"),
                row_shares=[3.0, 0.6, 2.0],
                name=f"vehicle {sid}",
            )
        )
    root_container = per_vehicle[0] if len(per_vehicle) == 1 else rrb.Tabs(*per_vehicle)
    return rrb.Blueprint(
        root_container,
        rrb.TimePanel(timeline=TIMELINE, play_state="following", state="collapsed"),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
    )
