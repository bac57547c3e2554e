"""Input timing estimated, not assumed (decision 0044): the inputs' delay line for the
filters, the shifted inputs of the whole-record fit, and the fit finding a delay the
record was made with."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np

from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.estimation.delay import MAX_DELAY_S, InputDelay, delayed_inputs
from gcs_estimator.outputs.diagnosis import trust_warnings
from gcs_estimator.outputs.results_json import results_dict
from gcs_estimator.refine import refine_run
from gcs_estimator.refine.run import delayed_inputs as inputs_to_delay
from gcs_estimator.runtime.session import run_recording
from gcs_estimator.uncertainty.metrics import IDENTIFIED
from sim.truth import simulate


def test_delay_line_gives_the_inputs_of_the_earlier_time() -> None:
    """Frames of a signal linear in time: after the delay has passed, each frame's input
    is the signal's value delay earlier; before, the first frame's; zero: as given."""
    line = InputDelay(0.05)
    t = np.arange(0.0, 1.0, 0.02)
    signal = np.column_stack([3.0 * t + 1.0, -t, np.full_like(t, 1.2)])
    out = np.array([line.at(ti, row) for ti, row in zip(t, signal, strict=True)])
    late = t >= 0.05
    np.testing.assert_allclose(out[late, 0], 3.0 * (t[late] - 0.05) + 1.0)
    np.testing.assert_allclose(out[late, 1], -(t[late] - 0.05))
    np.testing.assert_array_equal(out[~late], np.repeat(signal[:1], (~late).sum(), axis=0))
    row = signal[5]
    assert InputDelay(0.0).at(0.1, row) is row
    line.restart()
    np.testing.assert_array_equal(line.at(2.0, signal[7]), signal[7])  # nothing before


def test_shifted_inputs_follow_the_record_later() -> None:
    """A delayed column is the record's, interpolated delay earlier (held at the first
    sample before the record); the delay is clipped to MAX_DELAY_S; other columns stay."""
    t = np.linspace(0.0, 2.0, 101)
    u = np.column_stack([np.sin(3.0 * t), t, np.ones_like(t)])
    out = delayed_inputs(t, u, np.array([0]), np.array([0.013]))
    np.testing.assert_allclose(out[:, 0], np.interp(t - 0.013, t, u[:, 0]))
    np.testing.assert_array_equal(out[:, 1:], u[:, 1:])
    early = delayed_inputs(t, u, np.array([1]), np.array([-0.03]))
    np.testing.assert_allclose(early[:-2, 1], t[:-2] + 0.03)
    far = delayed_inputs(t, u, np.array([1]), np.array([5.0]))
    np.testing.assert_allclose(far[:, 1], np.maximum(t - MAX_DELAY_S, 0.0))


def test_throttle_delay_only_where_it_moves() -> None:
    u = np.column_stack([np.zeros(50), np.full(50, 0.6), np.ones(50)])
    assert inputs_to_delay(u) == (0,)
    u[25:, 1] = 0.8
    assert inputs_to_delay(u) == (0, 1)


def _late_flight(config: AircraftConfig, samples: int) -> tuple[np.ndarray, ...]:
    """The simulator's calm flight with its log's inputs `samples` samples early (the
    aircraft responds to each logged input that much later)."""
    flight = simulate(config, seed=3)
    logged = np.concatenate([flight.inputs[samples:], np.repeat(flight.inputs[-1:], samples, 0)])
    return flight.t_s, logged, flight.measurements


def test_refine_finds_the_delay_and_the_filters_fly_at_it(noc_config: AircraftConfig) -> None:
    """The NOC simulator's flight, its elevator and throttle logged 2 samples (40 ms)
    ahead of the servos: the fit finds the delay within 3 of its sigmas and the
    coefficients within 3 of theirs, and warns that the filters took none (whose marks
    stay honest: their structure check weighs the timing); the filters
    run with [data] input_delay_s at it land within 3 sigma of the truth, and the fit
    then finds nothing left to point out. Half the manoeuvre (30 s, its multisteps and
    pulses) shows it at half the cost (decision 0062)."""
    noc_config = load_config(noc_config.source, ["simulation.manoeuvre.duration_s=30"])
    t, u, y = _late_flight(noc_config, 2)
    late = 2.0 * float(np.median(np.diff(t)))
    truth = np.array(noc_config.truth)
    run = run_recording(noc_config, t, u, y)
    fit = refine_run(run.result, "output-error")
    assert fit.delay_names[0] == "elevator"
    assert abs(fit.delays_s[0] - late) < 3.0 * fit.delay_sigma_s[0]
    assert fit.delay_sigma_s[0] < 0.25 * late
    assert np.all(np.abs(fit.coefficients - truth) < 3.0 * fit.sigma)
    assert any("later or earlier than the filters" in w for w in trust_warnings(run, fit))
    # The filters flew the inputs 40 ms early: their structure check's timing part
    # covers it, so no coefficient is marked identified beyond 3 sigma (decision 0047).
    for summary in run.summaries.values():
        for c in summary.coefficients:
            assert c.identifiability != IDENTIFIED or abs(c.z or 0.0) < 3.0, c
    blob = json.loads(json.dumps(results_dict(run, refined=fit)))
    assert blob["refined"]["input_delays_s"]["elevator"]["estimate"] == fit.delays_s[0]

    config = replace(noc_config, data=replace(noc_config.data, input_delay_s=late))
    again = run_recording(config, t, u, y)
    iekf = again.result.filters["IEKF"]
    assert np.all(np.abs(iekf.coefficients - truth) < 3.0 * iekf.sigma)
    refit = refine_run(again.result, "output-error")
    assert abs(refit.delays_s[0] - late) < 3.0 * refit.delay_sigma_s[0]
    assert not any("later or earlier than the filters" in w for w in trust_warnings(again, refit))
