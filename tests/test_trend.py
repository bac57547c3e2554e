"""The trend across flights (outputs/trend.py): a drift beyond the sigmas is flagged, a
vehicle without one is not, and `gcs-estimator trend TABLE` writes the report, a figure
per coefficient and the Rerun recording."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from gcs_estimator.cli import main
from gcs_estimator.outputs.tables import COEFFICIENT_COLUMNS, write_table
from gcs_estimator.outputs.trend import charts

START = datetime(2026, 3, 1, tzinfo=UTC)


def _rows(
    vehicle: str, values: np.ndarray, sigma: float, name: str = "CD0"
) -> list[dict[str, Any]]:
    """A vehicle's flights of one coefficient, a day apart, given out of order."""
    rows = [
        {
            "log": f"{vehicle}/{k:03d}.tlog",
            "vehicle": vehicle,
            "status": "ok",
            "filter": "IEKF",
            "coefficient": name,
            "estimate": float(v),
            "sigma": sigma,
            "flight_time_utc": START + timedelta(days=k),
        }
        for k, v in enumerate(values)
    ]
    return rows[::-1]


def test_a_drift_of_five_percent_over_fifty_flights_is_flagged_and_no_drift_is_not() -> None:
    rng = np.random.default_rng(7)
    cd0, sigma = 0.0377, 0.0377 * 0.01  # each flight's estimate good to 1 %
    drift = cd0 * (1 + 0.05 * np.arange(50) / 49) + rng.normal(0, sigma, 50)
    steady = cd0 + rng.normal(0, sigma, 50)
    found = {c.vehicle: c for c in charts(_rows("a", drift, sigma) + _rows("b", steady, sigma))}
    assert found["a"].drift and found["a"].drift_z >= found["a"].drift_limit > 3
    assert found["a"].slope * 49 == pytest.approx(0.05 * cd0, rel=0.2)
    assert not found["b"].flagged
    assert list(found["b"].estimate) == list(steady)  # in flight-time order


def test_a_drift_the_flights_show_is_found_under_sigmas_that_are_too_large() -> None:
    """The sigmas four times the flights' scatter (the sigma to trust holds the model's
    structure, the same on every flight): the drift test reads the scale from the
    scatter, the limits do not narrow."""
    rng = np.random.default_rng(9)
    cd0 = 0.0377
    values = cd0 * (1 + 0.05 * np.arange(50) / 49) + rng.normal(0, 0.01 * cd0, 50)
    (chart,) = charts(_rows("a", values, 0.04 * cd0))
    assert chart.drift and not chart.shifts and chart.birge == 1.0


def test_a_step_after_a_repair_is_a_shift_at_its_flight() -> None:
    rng = np.random.default_rng(3)
    sigma = 0.001
    values = 0.04 + rng.normal(0, sigma, 30)
    values[20:] += 0.01  # ten sigmas
    (chart,) = charts(_rows("a", values, sigma))
    assert chart.shifts == list(range(20, 30))


def test_flights_scattering_more_than_their_sigmas_widen_the_limits() -> None:
    """Sigmas five times too small: the baseline's scatter widens every limit, so a
    vehicle without a change is not flagged."""
    rng = np.random.default_rng(11)
    values = 0.04 + rng.normal(0, 0.002, 40)
    (chart,) = charts(_rows("a", values, 0.0004))
    assert chart.birge > 2
    assert not chart.flagged


def test_trend_command_writes_the_report_figures_and_recording(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    sigma = 0.0004
    rows = _rows("plane", 0.04 * (1 + 0.05 * np.arange(50) / 49) + rng.normal(0, sigma, 50), sigma)
    rows += _rows("plane", 5.0 + rng.normal(0, 0.05, 50), 0.05, name="CLa")
    rows.append({"log": "bad.tlog", "status": "failed", "error": "no usable frame"})
    table = write_table(rows, COEFFICIENT_COLUMNS, tmp_path / "coefficients.parquet")
    assert main(["trend", str(table), "--out", str(tmp_path / "t")]) == 0
    report = (tmp_path / "t" / "trend.md").read_text()
    assert "Flagged: 1 of 2 charts: plane CD0" in report
    assert "![plane CD0](trend_plane_CD0.svg)" in report
    for name in ("CD0", "CLa"):
        svg = ET.parse(tmp_path / "t" / f"trend_plane_{name}.svg").getroot()
        circles = svg.findall("{http://www.w3.org/2000/svg}circle")
        assert len(circles) == 50  # a point per flight
    assert (tmp_path / "t" / "trend.rrd").stat().st_size > 0
