"""Segments: the parts of a record the model covers (estimation/segments.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gcs_estimator.config import ConfigError
from gcs_estimator.estimation import segments
from gcs_estimator.estimation.segments import Gate, Limits, find, parse_windows

DT = 0.02
BLOCKS = (
    # (frames, airborne, hover, airspeed m/s, bank rad): what a VTOL's flight log holds
    (500, 0, 0, 3.0, 0.0),  # on the ground
    (150, 1, 1, 2.0, 0.0),  # hovering after take-off
    (100, 1, 0, 10.0, 0.0),  # transition: slower than half the trim
    (1000, 1, 0, 24.0, 0.1),  # wings level (bank within the limit): segment 1
    (250, 1, 0, 25.0, 1.0),  # a turn at 57 degrees of bank
    (50, 1, 0, 24.0, 0.0),  # one second level: too short
    (100, 1, 0, 24.0, -1.0),  # another steep turn
    (1500, 1, 0, 23.0, 0.2),  # segment 2
    (200, 1, 0, 10.0, 0.0),  # landing approach, slow
    (300, 0, 0, 0.0, 0.0),  # on the ground
)


def _record() -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    n = sum(b[0] for b in BLOCKS)
    t = 100.0 + DT * np.arange(n)
    cols = [np.concatenate([np.full(b[0], b[k]) for b in BLOCKS]) for k in (1, 2, 3, 4)]
    airborne, hover, v, phi = (np.asarray(c, float) for c in cols)
    sampled = np.full(n, np.nan)  # the airspeed sampled in every fifth frame only
    sampled[::5] = v[::5]
    return t, sampled, {"airborne": airborne, "hover": hover, "phi": phi}


def test_segments_of_a_flight_with_ground_take_off_turns_and_landing() -> None:
    t, v, aux = _record()
    plan = find(t, v, aux, Limits(trim_airspeed_mps=24.0))
    assert [(s.first, s.stop) for s in plan.segments] == [(750, 1750), (2150, 3650)]
    assert plan.segments[0].t0 == pytest.approx(t[750])
    assert plan.segments[1].duration_s == pytest.approx(1499 * DT)
    assert dict(plan.left_out) == {
        "window": 0,
        "ground": 800,
        "hover": 150,
        "airspeed": 300,
        "bank": 350,
        "short": 50,
    }
    assert plan.used + sum(plan.left_out.values()) == plan.frames == len(t)
    assert plan.left_out_s["ground"] == pytest.approx(800 * DT)
    mask, starts = plan.mask(), plan.starts()
    assert mask.sum() == 2500 and np.flatnonzero(starts).tolist() == [750, 2150]
    line = plan.summary()
    assert "2 used, 2500 of 4150 frames" in line and "bank 350 (7.0 s)" in line
    assert plan.as_json()["left_out_frames"]["hover"] == 150


def test_without_airborne_flags_or_bank_the_airspeed_alone_decides() -> None:
    t, v, _ = _record()
    plan = find(t, v, {}, Limits(trim_airspeed_mps=24.0))
    # the ground and hover frames are too slow; the turns count as flight now
    assert [(s.first, s.stop) for s in plan.segments] == [(750, 3650)]
    assert plan.left_out["airspeed"] == 500 + 150 + 100 + 200 + 300


def test_windows_cut_segments_and_a_steeper_limit_lets_the_turns_in() -> None:
    t, v, aux = _record()
    windows = parse_windows(["16:30", "50:"])
    limits = Limits(trim_airspeed_mps=24.0, max_bank_rad=math.radians(60.0), windows=windows)
    plan = find(t, v, aux, limits)
    # 16-30 s after the first frame: frames 800..1500; from 50 s: 2500 to the landing
    assert [(s.first, s.stop) for s in plan.segments] == [(800, 1501), (2500, 3650)]
    assert plan.left_out["bank"] == 0
    assert plan.left_out["window"] == 800 + 999  # before 16 s, and from 30 s to 50 s
    assert plan.used + sum(plan.left_out.values()) == len(t)


def test_a_gap_in_time_splits_a_segment() -> None:
    t = np.concatenate([np.arange(0.0, 10.0, 0.1), np.arange(15.0, 20.0, 0.1)])
    plan = find(t, np.full(len(t), 24.0), {}, Limits(trim_airspeed_mps=24.0))
    assert [(s.first, s.stop) for s in plan.segments] == [(0, 100), (100, 150)]


def test_merged_plans_keep_their_flights() -> None:
    t, v, aux = _record()
    a = find(t, v, aux, Limits(24.0))
    b = find(t, v, aux, Limits(24.0), flight=1)
    both = segments.merged([a, b], [0, len(t)])
    assert [(s.first, s.flight) for s in both.segments] == [
        (750, 0),
        (2150, 0),
        (750 + len(t), 1),
        (2150 + len(t), 1),
    ]
    assert both.left_out["bank"] == 700 and both.frames == 2 * len(t)


@pytest.mark.parametrize("text", ["5", "a:b", "9:3", "4:4"])
def test_bad_windows_are_refused_naming_the_option(text: str) -> None:
    with pytest.raises(ConfigError, match="--window"):
        parse_windows([text])


def test_the_live_gate_leaves_out_and_counts_and_starts_afresh() -> None:
    gate = Gate(Limits(trim_airspeed_mps=24.0, windows=parse_windows([":10"])))
    speeds = (24.0, math.nan, 5.0, math.nan, 24.0, 25.0)
    seen = [gate.admit(float(i), v) for i, v in enumerate(speeds)]
    assert seen == [
        (True, False),
        (True, False),
        (False, False),
        (False, False),
        (True, True),
        (True, False),
    ]
    assert gate.left_out["airspeed"] == 2 and gate.segments == 2
    assert gate.admit(6.0, 24.0, phi=1.2) == (False, False) and gate.left_out["bank"] == 1
    assert gate.admit(7.0, 24.0) == (True, True)
    assert gate.admit(10.5, 24.0) == (False, False) and gate.left_out["window"] == 1


def test_a_held_out_window_is_taken_out_of_the_windows_fitted() -> None:
    # No --window: the whole flight less the held-out stretch, on both sides of it.
    assert segments.excluding((), (60.0, 90.0)) == ((None, 60.0), (90.0, None))
    # A window that ends inside the held-out stretch is cut at its start; one beyond it
    # stays whole; one that covers it is split in two.
    fitted = segments.excluding(((0.0, 70.0), (100.0, 150.0), (None, None)), (60.0, 90.0))
    assert fitted == ((0.0, 60.0), (100.0, 150.0), (None, 60.0), (90.0, None))
    # Held out from the start: nothing of the flight before it is left.
    assert segments.excluding((), (None, 30.0)) == ((30.0, None),)
    t = np.arange(0.0, 120.0, 1.0)
    used = segments.in_windows(t, segments.excluding((), (60.0, 90.0)))
    assert not used[(t > 60.0) & (t < 90.0)].any()
    assert used[t < 60.0].all() and used[t > 90.0].all()


def test_the_segments_bank_limit_is_the_filters_and_live_frames_carry_the_bank() -> None:
    from gcs_estimator.config import load_config
    from gcs_estimator.model.channels import bank_of
    from gcs_estimator.runtime.flights import limits_of

    config = load_config("noc_uav")
    limits = limits_of(config)
    assert limits.max_bank_rad == pytest.approx(math.radians(config.filter.bank_limit_deg))
    steep = math.radians(config.filter.bank_limit_deg + 5.0)
    inputs = np.array([0.0, 0.3, np.nan, steep, 0.0, 0.2])
    assert bank_of(inputs) == steep and math.isnan(bank_of(inputs[:3]))
    gate = Gate(limits)
    assert gate.admit(0.0, 24.0, bank_of(inputs[:3])) == (True, False)  # no bank: used
    assert gate.admit(0.1, 24.0, bank_of(inputs)) == (False, False)
    assert gate.left_out["bank"] == 1
    assert gate.admit(0.2, 24.0, 0.1) == (True, True)  # back within: afresh
