"""Turns in the model (decision 0048): a NOC mission of coordinated turns through both
filters, with the turn's terms and without them, and the bank limit's count."""

from __future__ import annotations

import math

import numpy as np

from gcs_estimator.arrays import FloatArray
from gcs_estimator.config import load_config
from gcs_estimator.estimation.filters.core import FilterKind
from gcs_estimator.estimation.results import EstimatorResult
from gcs_estimator.model.channels import Channel
from gcs_estimator.runtime.session import run_recording
from sim.scenario import mission
from sim.truth import simulate

FAST = ['filter.structure_check="off"']
"""The structure check replays the pass per channel: not what these tests are about."""
PHI = Channel.PHI - Channel.ELEVATOR


def _z(result: EstimatorResult, truth: FloatArray, kind: FilterKind) -> FloatArray:
    f = result.filters[kind]
    z: FloatArray = (np.asarray(f.coefficients) - truth) / np.asarray(f.sigma)
    return z


def test_a_banked_flight_is_within_three_sigma_and_worse_without_the_turn() -> None:
    """80 s of the mission (six turns of 20-35 deg, multisteps, a climb and a descent on
    throttle, calm): with phi, p, r as inputs every coefficient of both filters lies
    within 3 sigma of the truth; the same data with the turn's inputs dropped (the
    wings-level model) miss it by far."""
    config = load_config("noc_uav", [*mission("none", 80.0), *FAST])
    flight = simulate(config, seed=2)
    assert flight.inputs.shape[1] == 6
    assert math.degrees(float(np.max(np.abs(flight.inputs[:, PHI])))) > 30.0
    turns = run_recording(config, flight.t_s, flight.inputs, flight.measurements).result
    level = run_recording(config, flight.t_s, flight.inputs[:, :3], flight.measurements).result
    kinds: tuple[FilterKind, ...] = ("EKF", "IEKF")
    for kind in kinds:
        z_turn = _z(turns, flight.truth, kind)
        z_level = _z(level, flight.truth, kind)
        print(
            f"{kind}: mean z^2 with the turn's terms {np.mean(z_turn**2):.2f} "
            f"(max |z| {np.max(np.abs(z_turn)):.2f}), without {np.mean(z_level**2):.1f} "
            f"(max |z| {np.max(np.abs(z_level)):.1f})"
        )
        assert np.all(np.abs(z_turn) < 3.0), z_turn
        assert np.mean(z_level**2) > 10.0 * max(float(np.mean(z_turn**2)), 1.0)
        assert turns.frames_banked_out == 0


def test_frames_beyond_the_bank_limit_are_counted_and_not_used() -> None:
    """With a bank limit of 27 deg, exactly the frames banked beyond it are left out of
    the update (counted); the result equals a run whose observations there are missing."""
    limit = 27.0
    overrides = [*mission("none", 40.0), *FAST]
    config = load_config("noc_uav", [*overrides, f"filter.bank_limit_deg={limit}"])
    flight = simulate(config, seed=4)
    beyond = np.abs(flight.inputs[:, PHI]) > math.radians(limit)
    assert beyond.sum() > 50
    run = run_recording(config, flight.t_s, flight.inputs, flight.measurements).result
    assert run.frames_banked_out == int(beyond.sum())
    blanked = flight.measurements.copy()
    blanked[beyond] = np.nan
    wide = load_config("noc_uav", [*overrides, "filter.bank_limit_deg=90"])
    same = run_recording(wide, flight.t_s, flight.inputs, blanked).result
    assert same.frames_banked_out == 0
    for kind in ("EKF", "IEKF"):
        np.testing.assert_array_equal(
            run.filters[kind].coefficients, same.filters[kind].coefficients
        )


def test_a_noise_free_mission_with_turns_lands_on_the_truth() -> None:
    """The simulator's noise-free signals of a 2-minute mission (two turns, a 3-2-1-1),
    through both filters: the drag and lift coefficients within a tenth of their own
    covariance sigma of the truth, every coefficient within one (the pitching moment's
    and CLq are off by up to 0.7 sigma with or without the turns; decision 0077). The
    autopilot's commands hold between samples, as the filters hold them; the bank moves
    between samples, and the filters take it linearly from one to the next. Before,
    the simulator flew the turn's commands as they moved between samples and the
    filters held the bank: CDde came out 7.4 sigmas off, CD0 3.5, CDa 3.3."""
    config = load_config("noc_uav", [*mission("none", 120.0), *FAST])
    flight = simulate(config, seed=1)
    y = flight.clean.copy()
    y[np.isnan(flight.measurements)] = np.nan
    assert np.ptp(flight.inputs[:, PHI]) > math.radians(20.0)
    result = run_recording(config, flight.t_s, flight.inputs, y).result
    for kind in ("EKF", "IEKF"):
        f = result.filters[kind]
        own = np.sqrt(np.diag(f.covariance))
        z = (f.coefficients - flight.truth) / own
        shown = (kind, dict(zip(result.names, np.round(z, 2), strict=True)))
        forces = [
            i for i, n in enumerate(result.names) if n.startswith(("CD", "CL")) and n != "CLq"
        ]
        assert np.max(np.abs(z[forces])) < 0.1, shown
        assert np.max(np.abs(z)) < 1.0, shown


def test_the_bank_goes_linearly_between_samples_whatever_the_hold() -> None:
    """core.input_path: under the zero-order hold of the commands ([data] input_hold =
    "previous") the elevator, throttle and density hold at the earlier sample, while the
    bank angle and the roll and yaw rates go to the later one; a missing input is held."""
    from gcs_estimator.estimation.filters.core import input_path

    before = np.array([0.01, 0.3, 1.2, 0.1, 0.2, 0.05])
    after = np.array([0.02, 0.4, 1.1, 0.2, np.nan, 0.06])
    start, end = input_path(before, after, False)
    assert np.array_equal(start, before)
    assert np.array_equal(end[:3], before[:3])
    assert end[3] == after[3] and end[5] == after[5]
    assert end[4] == before[4]
    _, linear = input_path(before, after, True)
    assert np.array_equal(linear[:4], after[:4]) and linear[4] == before[4]
