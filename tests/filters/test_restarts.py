"""Restarts off the receive path: a restart's re-run catches up a few frames per new
frame, and ends exactly where a re-run done at once would."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.estimation.estimator import Estimator
from gcs_estimator.estimation.filters.lane import Lane
from gcs_estimator.estimation.restarts import GRACE_PER_PEER
from sim.scenario import scenario_of
from sim.truth import simulate


def _run(config: AircraftConfig, peers: int = 0) -> tuple[Estimator, list[int]]:
    """Both filters over a 15 s simulated flight, with `peers` other vehicles' restarts
    under way whenever one begins; kernel steps taken in each frame's call (one at a time
    or in a re-run's blocks)."""
    fl = simulate(config, seed=5)
    est = Estimator(config, peers_restarting=lambda: peers)
    calls = [0]
    step, block = Lane.step, Lane.block

    def counted(lane, *args, **kwargs):  # type: ignore[no-untyped-def]
        calls[0] += 1
        return step(lane, *args, **kwargs)

    def counted_block(lane, ts, *args, **kwargs):  # type: ignore[no-untyped-def]
        calls[0] += len(ts)  # the frames it steps
        return block(lane, ts, *args, **kwargs)

    per_frame = []
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(Lane, "step", counted)
        mp.setattr(Lane, "block", counted_block)
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
    assert at_once.restarts.done == spread.restarts.done == 2
    for kind, s in at_once.states.items():
        other = spread.states[kind]
        assert s is not None and other is not None
        np.testing.assert_array_equal(other.x, s.x)
        np.testing.assert_array_equal(other.P, s.P)
    # At once, a restart's frame steps every frame so far; spread, a bounded number.
    kinds = len(at_once.states)
    assert max(heavy) > 200 * kinds
    assert max(light) <= kinds * (1 + config.filter.restart_frames_per_step)


def _history(est: Estimator) -> dict[str, np.ndarray]:
    out = est.result()
    return {k: f.track.x for k, f in out.filters.items() if f.track is not None}


def test_work_done_ahead_in_idle_time_changes_nothing_but_when_it_is_done() -> None:
    """Idle time (Session.work_ahead) runs the warm start's fit and the re-run early, in
    uneven amounts; the swap stays at the frame the schedule fixes, so the history, not
    just the end, is the same as without: a replay swaps where the live run did."""
    config = load_config("noc_uav", ["simulation.manoeuvre.duration_s=15"])
    fl = simulate(config, seed=5)
    plain, ahead = Estimator(config), Estimator(config)
    rng = np.random.default_rng(3)
    done = 0
    for t, u, y in zip(fl.t_s, fl.inputs, fl.measurements, strict=True):
        done += ahead.restarts.work_ahead(int(rng.integers(0, 40)))
        plain.step(float(t), u, y)
        ahead.step(float(t), u, y)
    assert done > 300  # most of both re-runs was done in "idle time"
    assert plain.final_pass_from == ahead.final_pass_from
    a, b = _history(plain), _history(ahead)
    for kind in a:
        np.testing.assert_array_equal(a[kind], b[kind])


def test_a_grace_period_leaves_the_receive_path_alone_then_swaps_later_to_the_same_end() -> None:
    """A restart that begins while 10 other vehicles' are under way waits 10 turns
    (GRACE_PER_PEER frames each) before the receive path does any of its work."""
    config = load_config("noc_uav", ["simulation.manoeuvre.duration_s=15"])
    plain, _ = _run(config)
    spread, per_frame = _run(config, peers=10)
    grace = 10 * GRACE_PER_PEER
    kinds = len(plain.states)
    begin = round(config.filter.restart_times_s[0] * scenario_of(config).sample_rate_hz)
    # The restart's frame and the grace after it: the live step only, no fit, no re-run.
    assert set(per_frame[begin : begin + grace]) == {kinds}
    assert spread.final_pass_from > plain.final_pass_from
    for kind, s in plain.states.items():
        other = spread.states[kind]
        assert s is not None and other is not None
        np.testing.assert_array_equal(other.x, s.x)


def test_idle_restart_work_stops_at_its_budget_and_takes_vehicles_in_turn() -> None:
    """Session.work_ahead checks its budget after every unit of work (a warm start's fit,
    or a few frames of one vehicle's re-run), not after a round of every vehicle: with
    many vehicles restarting together a round is many fits, and a packet arriving
    meanwhile would wait for all of them. The next call goes on with the next vehicle."""
    from gcs_estimator.runtime.session import Session

    config = load_config("noc_uav", ["simulation.manoeuvre.duration_s=8"])
    fl = simulate(config, seed=5)
    session = Session(config, keep_history=False)
    vehicles = (3, 7, 11)
    for sid in vehicles:  # as if 200 more vehicles were restarting: 1000 frames of grace
        session.estimators[sid] = Estimator(
            config, keep_history=False, peers_restarting=lambda: 200
        )
    begin = round(config.filter.restart_times_s[0] * scenario_of(config).sample_rate_hz)
    for t, u, y in zip(fl.t_s[: begin + 1], fl.inputs, fl.measurements, strict=False):
        for sid in vehicles:
            session.estimator(sid).step(float(t), u, y)
    ests = [session.estimators[sid] for sid in vehicles]
    assert all(e.restarts.under_way for e in ests)
    assert [e.restarts.worked_ahead for e in ests] == [0, 0, 0]
    turns = []
    for _ in range(6):
        before = [e.restarts.worked_ahead for e in ests]
        session.work_ahead(0.0)
        moved = [i for i, e in enumerate(ests) if e.restarts.worked_ahead != before[i]]
        assert len(moved) == 1  # one unit, then the spent budget stops it
        turns.append(moved[0])
    # Each vehicle's fit first, then its re-run's frames, in turn.
    assert turns == [0, 1, 2, 0, 1, 2]
    assert [e.restarts.worked_ahead for e in ests] == [1 + 5] * 3


def test_vehicles_restarting_together_take_turns_and_end_alike() -> None:
    """Each vehicle whose restart begins while others' are under way gets
    GRACE_PER_PEER more frames of grace for each of them: the receive path is not asked
    for every vehicle's re-run at once. The count comes from the frames the session was
    given, in their order (not from the machine's load), and the estimates end where a
    lone vehicle's do."""
    from gcs_estimator.runtime.session import Session

    config = load_config("noc_uav", ["simulation.manoeuvre.duration_s=15"])
    per_peer = GRACE_PER_PEER
    assert per_peer > 0
    fl = simulate(config, seed=5)
    lone, _ = _run(config)
    session = Session(config, keep_history=False)
    vehicles = (4, 9, 2)
    frames = list(zip(fl.t_s, fl.inputs, fl.measurements, strict=True))
    for t, u, y in frames:
        for sid in vehicles:
            session.estimator(sid).step(float(t), u, y)
    for sid in vehicles:
        session.estimators[sid].finish_restarts()
    swaps = [session.estimators[sid].final_pass_from for sid in vehicles]
    # Each later vehicle swaps later, by the grace its turn gave (a swap's frame moves
    # by whole re-run schedules, so by at least per_peer frames for each peer).
    assert swaps[0] == lone.final_pass_from
    assert swaps[0] < swaps[1] < swaps[2]
    assert swaps[2] - swaps[0] >= 2 * per_peer
    for sid in vehicles:
        for kind, s in lone.states.items():
            other = session.estimators[sid].states[kind]
            assert s is not None and other is not None
            np.testing.assert_array_equal(other.x, s.x)
    # Live, idle time between packets does restart work ahead; the turns and the swaps
    # stay where a replay (no idle time) puts them.
    again = Session(config, keep_history=False)
    for t, u, y in frames:
        for sid in vehicles:
            again.estimator(sid).step(float(t), u, y)
            again.work_ahead(0.0)
    assert sum(again.estimators[sid].restarts.worked_ahead for sid in vehicles) > 0
    for sid in vehicles:
        again.estimators[sid].finish_restarts()
    assert [again.estimators[sid].final_pass_from for sid in vehicles] == swaps
