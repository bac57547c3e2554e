"""Restarts off the receive path: a restart's re-run catches up a few frames per new
frame, and ends exactly where a re-run done at once would."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.estimator import Estimator
from sim.truth import simulate


def _run(config: AircraftConfig) -> tuple[Estimator, list[int]]:
    """Both filters over a 15 s simulated flight; kernel steps taken in each frame's call."""
    fl = simulate(config, seed=5)
    est = Estimator(config)
    inner = est._step
    calls = [0]

    def counted(*args, **kwargs):  # type: ignore[no-untyped-def]
        calls[0] += 1
        return inner(*args, **kwargs)

    est._step = counted
    per_frame = []
    for t, u, y in zip(fl.t_s, fl.inputs, fl.measurements, strict=True):
        calls[0] = 0
        est.step(float(t), u, y)
        per_frame.append(calls[0])
    est.finish_restarts()
    return est, per_frame


def test_an_incremental_re_run_ends_where_one_at_once_does() -> None:
    config = load_config("noc_uav", ["simulation.manoeuvre.duration_s=15"])
    at_once, heavy = _run(replace(config, filter=replace(config.filter, restart_frames_per_step=0)))
    spread, light = _run(config)
    assert at_once.restarts_done == spread.restarts_done == 2
    for kind, s in at_once.states.items():
        other = spread.states[kind]
        assert s is not None and other is not None
        np.testing.assert_array_equal(other.x, s.x)
        np.testing.assert_array_equal(other.P, s.P)
    # At once, a restart's frame steps every frame so far; spread, a bounded number.
    kinds = len(at_once.states)
    assert max(heavy) > 200 * kinds
    assert max(light) <= kinds * (1 + config.filter.restart_frames_per_step)
