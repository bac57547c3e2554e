"""Shared fixtures: the project's configs and the bundled HFB-320 record."""

from __future__ import annotations

import os
import resource
import time
from collections.abc import Iterator
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


CPU_TSV = "GCS_TEST_CPU_TSV"
"""Where to append each test's CPU time (decision 0066): `GCS_TEST_CPU_TSV=cpu.tsv pytest
tests/test_x.py` adds a line per test, its id, CPU seconds (this process and the child
processes it waited for) and wall seconds. CPU, not wall: on a shared machine the wall
time says more about the other processes than about the tests."""


def _cpu_s() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item) -> Iterator[None]:
    path = os.environ.get(CPU_TSV)
    if not path:
        yield
        return
    cpu, wall = _cpu_s(), time.perf_counter()
    yield
    with open(path, "a", encoding="utf-8") as out:
        out.write(f"{item.nodeid}\t{_cpu_s() - cpu:.2f}\t{time.perf_counter() - wall:.2f}\n")
