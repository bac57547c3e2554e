"""The manoeuvre's elevator at many times at once (what the simulator flies) is the one at
each time alone, multisteps and pulses overlapping or not, samples on switching times."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from gcs_estimator.config import load_config
from sim.scenario import scenario_of
from sim.truth import elevator_offset_rad, elevator_offsets_rad


def test_all_times_at_once_equal_each_time_alone() -> None:
    base = scenario_of(load_config("noc_uav")).manoeuvre
    rng = np.random.default_rng(7)
    for _ in range(100):
        n_pulses = int(rng.integers(0, 5))
        m = replace(
            base,
            multistep_starts_s=tuple(sorted(rng.uniform(0, 50, int(rng.integers(0, 6))))),
            multistep_unit_s=float(rng.uniform(0.2, 1.5)),
            pulse_starts_s=tuple(rng.uniform(0, 50, n_pulses)),
            pulse_durations_s=tuple(rng.uniform(0.1, 5, n_pulses)),
            pulse_amplitudes_deg=tuple(rng.uniform(-5, 5, n_pulses)),
        )
        on_switches = [s + k * m.multistep_unit_s for s in m.multistep_starts_s for k in range(8)]
        t = np.sort(np.concatenate([np.arange(0, 60, 0.02), on_switches, m.pulse_starts_s]))
        alone = np.array([elevator_offset_rad(m, float(v)) for v in t])
        np.testing.assert_array_equal(elevator_offsets_rad(m, t), alone)
    unsorted = np.array([30.0, 1.0, 5.0])
    expect = [elevator_offset_rad(base, float(v)) for v in unsorted]
    np.testing.assert_array_equal(elevator_offsets_rad(base, unsorted), expect)
