"""The structure check's one-replay parts (gcs_estimator/uncertainty/weighting.py,
docs/decisions/0059): the final pass replayed with the inputs held the other way between
frames ("hold"), and, where the run read a channel's noise below the configured, at the
configured noise, counting how far the estimates moved ("noise_level") beside the
covariance's excess ("noise_floor")."""

from __future__ import annotations

import numpy as np

from gcs_estimator.config import load_config
from gcs_estimator.estimation.estimator import FILTER_KINDS
from gcs_estimator.outputs.diagnosis import trust_warnings
from gcs_estimator.outputs.results_json import results_dict
from gcs_estimator.outputs.table import final_table
from gcs_estimator.runtime.session import RecordingSource, Session, run_recording
from gcs_estimator.uncertainty import weighting
from gcs_estimator.uncertainty.result import VehicleResult
from gcs_estimator.uncertainty.weighting import UNIFORM_SHARE, Replay
from sim.truth import simulate

SHORT = ["simulation.manoeuvre.duration_s=12"]
NOISE_FREE = [
    f"simulation.sensors.noise_sigma.{c}=0"
    for c in ("V", "alpha", "theta", "q", "qdot", "a_x", "a_z")
]


def test_a_move_within_what_the_covariances_differ_by_adds_nothing() -> None:
    """The move beyond the variance the two covariances differ by counts (Hausman), as a
    quantity uniform between the run's value and the replay's (a third of its square);
    the floor is the replay's covariance excess, never negative."""
    b, s = np.array([1.0, 1.0, 1.0]), np.array([0.1, 0.1, 0.2])
    v, vs = np.array([1.05, 1.3, 1.0]), np.array([0.2, 0.1, 0.1])
    floor, moved = weighting._one_replay((b, s, np.nan), (v, vs, np.nan))
    # first: d^2 = 0.0025 below 0.04 - 0.01; second: equal covariances, the whole move.
    assert moved[0] == 0.0
    np.testing.assert_allclose(moved[1], 0.3 * np.sqrt(UNIFORM_SHARE))
    np.testing.assert_allclose(floor, [np.sqrt(0.03), 0.0, 0.0])


def test_the_hold_replay_takes_the_inputs_held_the_other_way() -> None:
    """The replay with the run's own hold ends where the run did; with the other hold it
    ends elsewhere (the simulator's inputs change between frames), and only the tunings'
    hold differs from the run's."""
    config = load_config("noc_uav", SHORT)
    fl = simulate(config, seed=1)
    session = Session(config)
    session.run(RecordingSource(fl.t_s, fl.inputs, fl.measurements))
    est = session.estimators[RecordingSource.SYSTEM_ID]
    t, u, y = est.frame_history.arrays()
    linear = est.tunings[FILTER_KINDS[0]].linear_inputs
    base = weighting._final(est, t, y, Replay(None, u))
    same = weighting._final(est, t, y, Replay(None, u, linear_inputs=linear))
    other = weighting._final(est, t, y, Replay(None, u, linear_inputs=not linear))
    for kind in FILTER_KINDS:
        np.testing.assert_array_equal(same[kind][0], base[kind][0])
        assert not np.array_equal(other[kind][0], base[kind][0]), kind
    assert est.tunings[FILTER_KINDS[0]].linear_inputs == linear  # the run left as it was


def test_a_noise_free_record_carries_the_hold_and_noise_level_parts() -> None:
    """On a noise-free record (its noise read far below the configured) the check holds
    the noise floor, the estimates' move at the configured noise and the hold's move, each
    per filter and coefficient, finite and not negative; the structure sigma is the root
    sum of squares of all parts. The simulator's model is exact: at the configured noise
    its estimates move no further than their covariances allow (a part well below the
    covariance sigma)."""
    config = load_config("noc_uav", [*SHORT, *NOISE_FREE])
    fl = simulate(config, seed=2)
    vehicle = run_recording(config, fl.t_s, fl.inputs, fl.measurements)
    check = vehicle.structure
    assert check is not None and not check.skipped
    assert {"noise_floor", "noise_level", "hold"} <= set(check.parts)
    for kind, summary in vehicle.summaries.items():
        for label in ("noise_floor", "noise_level", "hold"):
            part = check.parts[label][kind]
            assert np.all(np.isfinite(part)) and np.all(part >= 0.0), (label, kind)
        total = np.array([c.sigma_parts.structure for c in summary.coefficients])
        np.testing.assert_allclose(total, np.sqrt(sum(p[kind] ** 2 for p in check.parts.values())))
        cov = np.array([c.sigma_parts.covariance for c in summary.coefficients])
        assert float(np.median(check.parts["noise_level"][kind] / cov)) < 0.5, kind


def test_the_likelihood_decides_the_hold_part_in_three_cases() -> None:
    """The hold's part (decision 0071) from the run's and the replay's -2 log
    likelihoods: the other hold decisively likelier, the whole move; the run's held
    inputs decisively likelier, none; the run's linear inputs likelier, or no decision,
    the move as uniform between the two (a step between samples is not where the linear
    hold puts it)."""
    b, s = np.array([1.0, 2.0]), np.array([0.01, 0.01])
    v = np.array([1.3, 2.0])
    _, uniform = weighting._one_replay((b, s, 100.0), (v, s, 100.0))
    tie = weighting.LIKELIHOOD_TIE

    def part(change: float, linear: bool) -> np.ndarray:
        out, (kept, _) = weighting._hold_part(
            (b, s, 100.0), (v, s, 100.0 + change), uniform, linear
        )
        assert kept == change
        return out

    for linear in (True, False):
        np.testing.assert_allclose(part(-2.0 * tie, linear), [0.3, 0.0])
        np.testing.assert_allclose(part(0.5 * tie, linear), uniform)
        np.testing.assert_allclose(part(-0.5 * tie, linear), uniform)
    np.testing.assert_allclose(part(2.0 * tie, True), uniform)
    np.testing.assert_array_equal(part(2.0 * tie, False), [0.0, 0.0])
    nan, (kept, _) = weighting._hold_part((b, s, np.nan), (v, s, 1.0), uniform, False)
    np.testing.assert_array_equal(nan, uniform)
    assert np.isnan(kept)


def test_inputs_that_change_at_the_samples_decide_the_hold() -> None:
    """The simulator's commands change at the samples: run with them held (its config),
    the likelihood rejects the linear hold by far and the hold adds nothing to the sigma;
    run with them linear, it prefers the held inputs, the whole move counts, and the
    warnings name the setting to change."""
    held = run_recording_short([])
    check = held.structure
    assert check is not None and not check.skipped
    assert not check.linear_inputs and check.hold_preferred == "previous"
    assert check.hold_change > 100.0 * weighting.LIKELIHOOD_TIE
    for kind in FILTER_KINDS:
        np.testing.assert_array_equal(check.parts["hold"][kind], 0.0)
    assert not [w for w in trust_warnings(held) if "input_hold" in w]
    assert "the likelihood prefers the run's: the move does not count" in final_table(held)
    linear = run_recording_short(['data.input_hold="linear"'])
    other = linear.structure
    assert other is not None and other.linear_inputs
    assert other.hold_preferred == "previous" and other.hold_change < -weighting.LIKELIHOOD_TIE
    assert np.all(other.parts["hold"][FILTER_KINDS[0]] >= 0.0)
    assert np.any(other.parts["hold"][FILTER_KINDS[0]] > 0.0)
    assert "the likelihood prefers previous: the whole move counts" in final_table(linear)
    warned = [w for w in trust_warnings(linear) if "input_hold" in w]
    assert len(warned) == 1 and 'input_hold = "previous"' in warned[0], warned
    data = results_dict(linear)["diagnostics"]["structure_check"]["hold"]
    assert data["input_hold"] == "linear" and data["preferred"] == "previous"
    assert data["likelihood_change"] == other.hold_change


def run_recording_short(overrides: list[str]) -> VehicleResult:
    config = load_config("noc_uav", [*SHORT, *overrides])
    fl = simulate(config, seed=3)
    return run_recording(config, fl.t_s, fl.inputs, fl.measurements)
