"""A recording opened as a person would in a browser: `rerun --serve-web` and Rerun's web
viewer under headless Chromium, which loads it to the last frame; the screenshot shows
every coefficient panel with the filters' lines and the truth."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gcs_estimator.outputs.view import layout as lay
from tests.view.browser import CHROMIUM, decode_png, drawn, load_until_steady, served

ROOT = Path(__file__).resolve().parents[2]


def _near(img: np.ndarray, rgb: tuple[int, int, int], tol: int = 40) -> np.ndarray:
    return np.asarray(np.all(np.abs(img.astype(int) - np.array(rgb)) <= tol, axis=2))


@pytest.mark.skipif(CHROMIUM is None, reason="no chromium here (Debian: apt-get install chromium)")
def test_the_web_viewer_shows_the_whole_flight(tmp_path: Path) -> None:
    subprocess.run(
        [sys.executable, "-m", "gcs_estimator", "simulate", "--view", "save",
         "--set", "simulation.manoeuvre.duration_s=20", "--out", str(tmp_path / "run")],
        cwd=ROOT, check=True, capture_output=True, timeout=300,
    )  # fmt: skip
    with served(tmp_path / "run" / "view.rrd") as url:
        png, _seconds = load_until_steady(url, timeout_s=120.0)
    (tmp_path / "view.png").write_bytes(png)
    img = decode_png(png)
    height = img.shape[0]
    top = img[: int(0.45 * height)]  # the coefficient grid
    assert drawn(png)  # not a blank page
    # Every column of the grid (drag, lift, moment) holds the IEKF line and the truth.
    for third in np.array_split(np.arange(top.shape[1]), 3):
        panel = top[:, third]
        assert _near(panel, lay.IEKF_COLOR).sum() > 500, "IEKF lines missing"
        assert _near(panel, lay.TRUTH_COLOR, tol=30).sum() > 500, "truth lines missing"
