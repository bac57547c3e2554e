"""Shared fixtures: the project's configs and the bundled HFB-320 record."""

from __future__ import annotations

from pathlib import Path

import pytest

from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.ingest.flightdata import bundled

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = ROOT / "configs"
HFB320_DATA = bundled("hfb320") / "hfb320_1_10.asc"


@pytest.fixture(scope="session")
def noc_config() -> AircraftConfig:
    return load_config(CONFIGS / "noc_uav.toml")


@pytest.fixture(scope="session")
def hfb_config() -> AircraftConfig:
    return load_config(CONFIGS / "hfb320.toml")


@pytest.fixture(scope="session")
def hfb_data_path() -> Path:
    return HFB320_DATA


@pytest.fixture(autouse=True)
def no_viewer_windows(monkeypatch: pytest.MonkeyPatch) -> None:
    """The view's "auto" never opens a viewer window from a test run, display or not
    (it saves an .rrd into the test's output directory instead)."""
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
