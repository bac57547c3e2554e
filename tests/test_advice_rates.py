"""What to fly next at the rates a record has (uncertainty/advice.py): a channel sampled
slowly carries less information, is named as the first thing to fix, and no multistep is
shorter than a pilot can fly or than the fastest short-period channel can see."""

from __future__ import annotations

from functools import cache

import numpy as np

from gcs_estimator.config import load_config
from gcs_estimator.model.channels import N_OBS, OBS_NAMES
from gcs_estimator.uncertainty.advice import (
    MIN_SAMPLES_PER_STEP,
    PILOT_MIN_UNIT_S,
    Advice,
    advise,
)
from gcs_estimator.uncertainty.metrics import NOT_IDENTIFIED

RATE_HZ = 10.0


@cache
def _advice(rates: tuple[float, ...] | None) -> Advice:
    """The NOC UAV at its true coefficients with a wide covariance (nothing known),
    every channel observed at the configured noise, frames at RATE_HZ."""
    config = load_config("noc_uav")
    assert config.truth is not None
    beta = np.asarray(config.truth, float)
    p = len(beta)
    return advise(
        config,
        beta,
        np.diag((0.5 * np.abs(beta) + 0.05) ** 2),
        [NOT_IDENTIFIED] * p,
        config.filter.measurement_sigma,
        [True] * N_OBS,
        None,
        RATE_HZ,
        None,
        rates,
    )


def test_a_slow_channel_is_named_and_carries_less() -> None:
    """theta at a quarter of the frame rate: named first (below the 10 Hz the short
    period needs), every coefficient's predicted sigma no smaller than with theta at
    the full rate, and the ones theta informs larger."""
    full = _advice(None)
    rates = [RATE_HZ] * N_OBS
    rates[OBS_NAMES.index("theta")] = RATE_HZ / 4
    slow = _advice(tuple(rates))
    assert full.slow == ()
    assert [n for n, _ in slow.slow] == ["theta"]
    assert slow.lines()[1].lstrip().startswith("first, faster data: theta 2.5 Hz")
    assert slow.as_dict()["slow_channels_hz"] == {"theta": RATE_HZ / 4}
    for label, sd in slow.predicted.items():
        assert np.all(sd >= full.predicted[label] * (1 - 1e-9)), label
    assert any(np.any(sd > 1.01 * full.predicted[k]) for k, sd in slow.predicted.items())


def test_no_multistep_shorter_than_a_pilot_or_the_data_allow() -> None:
    """Every multistep candidate's unit step is at least PILOT_MIN_UNIT_S and spans
    MIN_SAMPLES_PER_STEP samples of the fastest short-period channel (q at 5 Hz: 0.6 s)."""
    full = _advice(None)
    rates = [RATE_HZ / 2] * N_OBS
    coarse = _advice(tuple(rates))
    for advice, floor in ((full, PILOT_MIN_UNIT_S), (coarse, MIN_SAMPLES_PER_STEP / 5.0)):
        multisteps = [a.candidate for a in advice.advised if a.candidate.kind != "throttle step"]
        units = [c.unit_s for c in multisteps if c.kind in ("doublet", "3-2-1-1")]
        assert units, "no multistep advised"
        assert min(units) >= floor - 1e-9
        labelled = [k for k in advice.predicted if "unit" in k]
        assert all(float(k.split("unit ")[1].split(" s")[0]) >= floor - 0.005 for k in labelled)
