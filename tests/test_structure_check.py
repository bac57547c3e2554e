"""The structure check (gcs_estimator/uncertainty/weighting.py, docs/decisions/0017): the
run's final pass replayed with each channel trusted half as much; how far the estimates move beyond
their covariance widens the sigma to trust. Small where the model holds, large enough where
it does not to cover an error the movement correction (0008) leaves uncovered."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from gcs_estimator.config import load_config
from gcs_estimator.estimation.estimator import Estimator, FilterKind
from gcs_estimator.outputs.results_json import results_dict
from gcs_estimator.outputs.table import final_table
from gcs_estimator.runtime.session import RecordingSource, Session, run_recording
from gcs_estimator.uncertainty import weighting
from gcs_estimator.uncertainty.result import VehicleResult
from gcs_estimator.uncertainty.weighting import VARIANCE_FACTOR, structure_check
from sim.truth import Flight, simulate

WELL_EXCITED = ("CL0", "CLa", "CLde", "Cm0", "Cma", "Cmq", "Cmde")


def _z(vehicle: VehicleResult, kind: FilterKind) -> np.ndarray:
    """Errors of the well-excited coefficients in their sigmas to trust."""
    return np.array(
        [
            (c.estimate - (c.truth or 0.0)) / c.sigma
            for c in vehicle.summaries[kind].coefficients
            if c.name in WELL_EXCITED
        ]
    )


def test_the_final_pass_replayed_from_the_history_ends_where_the_run_did() -> None:
    """The check's base: the run's final pass replayed over its history in compiled
    blocks (Estimator.replay_final_pass) ends bit for bit where the run, frame by frame
    with its restarts, did; across a gap longer than filters.core.MAX_GAP_S too."""
    config = load_config("noc_uav", ["simulation.manoeuvre.duration_s=25"])
    fl = simulate(config, seed=4)
    keep = (fl.t_s < 14.0) | (fl.t_s > 17.0)  # a 3 s gap: the flight states start afresh
    t, u, y = fl.t_s[keep], fl.inputs[keep], fl.measurements[keep]
    session = Session(config)
    session.run(RecordingSource(t, u, y))
    est = session.estimators[RecordingSource.SYSTEM_ID]
    assert est.gaps == 1 and est.restarts.done == 2
    again = Estimator(config, keep_history=False)
    again.replay_final_pass(est, *est.frame_history.arrays())
    for kind, state in est.states.items():
        other = again.states[kind]
        assert state is not None and other is not None
        np.testing.assert_array_equal(other.x, state.x)
        np.testing.assert_array_equal(other.P, state.P)
    # one filter alone (a fit that replays one filter's pass many times) ends alike
    ekf = Estimator(config, keep_history=False)
    ekf.replay_final_pass(est, *est.frame_history.arrays(), kinds=("EKF",))
    alone, run = ekf.states["EKF"], est.states["EKF"]
    assert alone is not None and run is not None and ekf.states["IEKF"] is None
    np.testing.assert_array_equal(alone.x, run.x)
    np.testing.assert_array_equal(alone.P, run.P)


def test_a_channel_trusted_less_has_its_variance_scaled_in_every_pass() -> None:
    config = load_config("noc_uav", ["simulation.manoeuvre.duration_s=12"])
    fl = simulate(config, seed=1)
    scale = np.ones(7)
    scale[3] = VARIANCE_FACTOR
    plain = Estimator(config, keep_history=False)
    less = Estimator(config, keep_history=False, noise_scale=scale)
    for est in (plain, less):
        for row in zip(fl.t_s, fl.inputs, fl.measurements, strict=True):
            est.step(*row)
        assert est.restarts.done == 2  # the final pass's settings came from the data
    for kind in plain.tunings:
        ratio = np.diag(less.tunings[kind].R) / np.diag(plain.tunings[kind].R)
        np.testing.assert_allclose(ratio[: len(scale)], scale)  # h_dot's, unnamed: 1
    replayed = Estimator(config, keep_history=False, noise_scale=scale)
    replayed.replay_final_pass(plain, fl.t_s, fl.inputs, fl.measurements)
    for kind in plain.tunings:
        np.testing.assert_array_equal(replayed.tunings[kind].R, less.tunings[kind].R)


@pytest.fixture(scope="module")
def unstated_vane() -> Flight:
    """Calm air; the vane 1 m ahead of the CG, and the airframe file read by the filters
    does not say so: alpha reads alpha + q x / V, a model error that stays put."""
    return simulate(load_config("noc_uav", ["sensors.vane_x_m=1.0"]), seed=1)


def test_an_error_the_channels_disagree_on_is_covered_by_the_structure_sigma(
    unstated_vane: Flight,
) -> None:
    fl = unstated_vane
    without = run_recording(
        load_config("noc_uav", ['filter.structure_check="off"']),
        fl.t_s,
        fl.inputs,
        fl.measurements,
    )
    checked = run_recording(load_config("noc_uav"), fl.t_s, fl.inputs, fl.measurements)
    assert without.structure is not None and without.structure.skipped
    assert checked.structure is not None and not checked.structure.skipped
    for kind in checked.summaries:
        # The estimates settle on the error, so how they moved over the run misses it.
        assert np.abs(_z(without, kind)).max() > 2.5, kind
        z = _z(checked, kind)
        assert np.mean(z**2) < 1.5, (kind, z.round(1))
        assert np.all(np.abs(z) < 2.5), (kind, z.round(1))
        # Estimates unchanged: only their sigmas.
        for a, b in zip(
            without.summaries[kind].coefficients, checked.summaries[kind].coefficients, strict=True
        ):
            assert a.estimate == b.estimate
            assert b.sigma >= a.sigma
    # The vane's error is in alpha, so alpha and the normal acceleration disagree on
    # the lift: trusting either less pulls CLde (its worst error) the other way.
    moves = checked.structure.moves["EKF"]
    clde = checked.result.names.index("CLde")
    sigma = checked.result.filters["EKF"].sigma[clde]
    alpha = moves[checked.structure.channels.index("alpha"), clde] / sigma
    a_z = moves[checked.structure.channels.index("a_z"), clde] / sigma
    assert alpha * a_z < 0.0 and min(abs(alpha), abs(a_z)) > 1.0, (alpha, a_z)


def test_where_the_model_holds_the_structure_sigma_is_small() -> None:
    """On the simulator's flight (the model exact, the inputs on time, the sensors where
    the airframe file says): the channels' weights move the estimates no further than
    their covariance allows, and the likelihood puts the inputs' timing and the sensor
    positions near the configured (decision 0047)."""
    config = load_config("noc_uav")
    fl = simulate(config, seed=3)
    vehicle = run_recording(config, fl.t_s, fl.inputs, fl.measurements)
    check = vehicle.structure
    assert check is not None and not check.skipped
    well = [i for i, n in enumerate(vehicle.result.names) if n in WELL_EXCITED]
    for kind, s in vehicle.summaries.items():
        cov = np.array([c.sigma_parts.covariance for c in s.coefficients])
        ratio = check.parts["weights"][kind][well] / cov[well]
        assert np.all(np.isfinite(ratio)), kind
        assert float(np.median(ratio)) < 0.5, (kind, ratio.round(2))
        total = np.array([c.sigma_parts.structure for c in s.coefficients])
        parts = np.sqrt(sum(p[kind] ** 2 for p in check.parts.values()))
        np.testing.assert_allclose(total, parts)
    assert set(check.found) == {"input_delay_s", "vane_x_m", "accel_x_m", "accel_z_m"}
    # The timing pinned far more tightly than its tolerance, and placed by the close pair
    # (decision 0073) within 3 of the likelihood's sigmas of where it is (the parabola
    # through the +-tolerance replays alone puts it several of them out); the positions
    # within 3 of their sigmas.
    delay, spread = check.found.pop("input_delay_s")
    assert spread * weighting.PROFILE_LOCAL < check.tolerances["timing"]
    assert abs(delay) < 3.0 * spread, (delay, spread)
    for key, (offset, sigma) in check.found.items():
        assert abs(offset) < 3.0 * sigma, key


def test_the_check_is_in_the_results_and_says_why_when_it_was_not_made() -> None:
    config = load_config("noc_uav", ["simulation.manoeuvre.duration_s=12"])
    fl = simulate(config, seed=2)
    vehicle = run_recording(config, fl.t_s, fl.inputs, fl.measurements)
    d = results_dict(vehicle)
    check = d["diagnostics"]["structure_check"]
    assert check["skipped"] is None and check["variance_factor"] == VARIANCE_FACTOR
    assert check["channels"] == ["V", "alpha", "theta", "q", "qdot", "a_x", "a_z"]
    assert set(check["moves"]["EKF"]["q"]) == set(vehicle.result.names)
    for est in d["filters"]["IEKF"]["estimates"].values():
        structure = est["sigma_parts"]["structure"]
        assert structure is not None and structure >= 0.0
        assert est["sigma"] >= structure
    assert "with each of V, alpha, theta, q, qdot, a_x, a_z trusted half" in final_table(vehicle)

    frames = len(fl.t_s)
    short = load_config(
        "noc_uav",
        ["simulation.manoeuvre.duration_s=12", f"filter.structure_check_max_frames={frames - 1}"],
    )
    skipped = run_recording(short, fl.t_s, fl.inputs, fl.measurements)
    reason = results_dict(skipped)["diagnostics"]["structure_check"]["skipped"]
    assert "structure_check_max_frames" in reason and str(frames) in reason
    assert all(np.isnan(c.sigma_parts.structure) for c in skipped.summaries["EKF"].coefficients)
    assert "structure check: not made" in final_table(skipped)
    forced = load_config(
        "noc_uav",
        [
            "simulation.manoeuvre.duration_s=12",
            f"filter.structure_check_max_frames={frames - 1}",
            'filter.structure_check="on"',
        ],
    )
    assert not run_recording(forced, fl.t_s, fl.inputs, fl.measurements).structure.skipped  # type: ignore[union-attr]


def test_the_reference_backend_checks_the_same_structure() -> None:
    """The numpy backend has no block step: its replays go frame by frame, to the same
    structure sigma as the compiled backend's."""
    config = load_config("noc_uav", ["simulation.manoeuvre.duration_s=7"])
    fl = simulate(config, seed=6)
    fast = run_recording(config, fl.t_s, fl.inputs, fl.measurements)
    numpy = run_recording(config, fl.t_s, fl.inputs, fl.measurements, backend="reference")
    for kind, s in fast.summaries.items():
        a = np.array([c.sigma_parts.structure for c in s.coefficients])
        b = np.array([c.sigma_parts.structure for c in numpy.summaries[kind].coefficients])
        assert np.all(np.isfinite(a)) and np.any(a > 0.0), kind
        np.testing.assert_allclose(b, a, rtol=1e-4, atol=1e-9 * float(np.abs(a).max()))


def test_a_record_whose_clock_restarted_is_not_checked() -> None:
    config = load_config("noc_uav", ["simulation.manoeuvre.duration_s=8"])
    fl = simulate(config, seed=2)
    t = np.concatenate([fl.t_s, fl.t_s[:50]])
    u = np.concatenate([fl.inputs, fl.inputs[:50]])
    y = np.concatenate([fl.measurements, fl.measurements[:50]])
    est = Estimator(config, keep_history=False)
    check = structure_check(est, t, u, y)
    assert "clock restarted" in check.skipped and not check.sigma


def test_the_frame_budget_is_shared_by_the_vehicles_of_a_run() -> None:
    """With structure_check = auto, filter.structure_check_max_frames bounds the frames
    checked over all the vehicles, so a station with many stops in seconds: the vehicles
    that would go past it are not checked, and their results say why."""
    config = load_config("noc_uav", ["simulation.manoeuvre.duration_s=7"])
    fl = simulate(config, seed=2)
    frames = len(fl.t_s)
    budget = replace(
        config, filter=replace(config.filter, structure_check_max_frames=2 * frames - 1)
    )
    session = Session(budget)
    for sid in (4, 5):
        for row in zip(fl.t_s, fl.inputs, fl.measurements, strict=True):
            session.estimator(sid).step(*row)
    results = session.results()
    first, second = results[4].structure, results[5].structure
    assert first is not None and not first.skipped
    assert second is not None and f"with the {frames} of the vehicles checked before" in (
        second.skipped
    )
    assert np.isnan(results[5].summaries["EKF"].coefficients[0].sigma_parts.structure)


def test_a_close_pair_places_a_quantity_only_in_one_valley() -> None:
    """Decision 0073: a close pair's parabola is taken where it predicts the wide pair's
    rises (one valley), not where the likelihood is rugged and least elsewhere. The
    figures are of two replays measured: the NOC mission's timing (wide ends +426,077 and
    +458,312 at +-10 ms; the close pair's least -7 us, width 18.5 us) and a JSBSim
    mission's thrust factor (wide ends +5,969 and -3,749 at +-0.26; the close pair's least
    +0.011, width 0.0002)."""
    assert weighting._one_valley((-7.09e-6, 1.85e-5), (426_077.0, 458_312.0), 0.01, 4.3e-5)
    assert not weighting._one_valley((0.0105, 2.1e-4), (5_969.0, -3_749.0), 0.26, 0.023)
    # both ends rising, but far less than the close parabola says: a dip, not the valley
    assert not weighting._one_valley((-5.6e-4, 1.24e-5), (16_181.0, 3_740.0), 0.04, 1.2e-3)
    # a least beyond the close pair's ends is not placed by it
    assert not weighting._one_valley((1e-4, 1.85e-5), (426_077.0, 458_312.0), 0.01, 4.3e-5)
