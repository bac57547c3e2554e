"""The view's layout follows the estimates: every final estimate (and the truth) inside
its panel's range, a range not set by the zero start's wild first seconds, the
identifiability in the panel titles and the run's warnings in the legend at the end."""

from __future__ import annotations

import math

import numpy as np

from gcs_estimator.config import load_config
from gcs_estimator.outputs.view import layout as lay
from gcs_estimator.outputs.view.live import RerunView, ViewSink, first_in_interval
from gcs_estimator.outputs.view.outlets import Layout, Text
from gcs_estimator.runtime.session import RecordingSource, Session
from sim.truth import simulate
from tests.view.test_layout_burst import Collect


def test_ranges_follow_the_estimates_and_the_end_says_what_is_identified() -> None:
    config = load_config("noc_uav", ["simulation.manoeuvre.duration_s=30"])
    flight = simulate(config, seed=3)
    out = Collect()
    clock = iter(np.arange(0.0, 1e6, 0.04))  # about real time: a call or two per frame
    view = RerunView([out], config, clock=lambda: float(next(clock)))
    session = Session(config)
    session.add_sink(ViewSink(view))
    results = session.run(RecordingSource(flight.t_s, flight.inputs, flight.measurements))
    res = results[1]

    layouts = [op for op in out.ops if isinstance(op, Layout)]
    assert 2 < len(layouts) < 20  # moved with the estimates, not once per batch
    final = layouts[-1]
    ranges = final.ranges[1]
    for i, name in enumerate(res.result.names):
        rng = ranges[i]
        assert rng is not None, name
        for f in res.result.filters.values():
            assert rng[0] < f.coefficients[i] < rng[1], (name, rng, f.coefficients[i])
        assert rng[0] < flight.truth[i] < rng[1], (name, rng, flight.truth[i])
        # The zero start's excursions do not set the scale: the range is far tighter
        # than what the estimates swept in the first seconds.
        track = res.result.filters["IEKF"].track
        assert track is not None
        early = track.coefficients[track.t - track.t[0] < 3.0, i]
        swept = float(np.nanmax(early) - np.nanmin(early))
        if swept > 10 * abs(flight.truth[i]):
            assert rng[1] - rng[0] < 0.5 * swept, (name, rng, swept)

    marks = final.marks[1]
    iekf = res.summaries["IEKF"].coefficients
    assert list(marks) == [c.identifiability for c in iekf]
    assert "not identified" in marks  # CDa on this manoeuvre
    legends = [op.text for op in out.ops if isinstance(op, Text) and op.entity == lay.LEGEND]
    assert len(legends) == 2 and "Before trusting" in legends[-1] and "CDa" in legends[-1]
    assert all(not op.times for op in out.ops if isinstance(op, Text) and op.entity == lay.LEGEND)


def test_decimation_keeps_the_first_row_of_each_interval() -> None:
    tv = np.arange(50) / 50.0  # 50 Hz
    keep, last = first_in_interval(tv, 25.0, math.nan)
    np.testing.assert_array_equal(np.flatnonzero(keep), np.arange(0, 50, 2))
    assert last == 24.0
    # The next batch goes on from the last interval kept: its first row, in the same
    # interval as the batch's last, is not kept again.
    keep, _ = first_in_interval(np.array([0.99, 1.0, 1.02]), 25.0, last)
    np.testing.assert_array_equal(keep, [False, True, False])
    keep, same = first_in_interval(tv, 0.0, 7.0)  # 0: every row
    assert keep.all() and same == 7.0
