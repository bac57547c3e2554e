"""A session's frames taken in blocks (Session(block_frames=...), Estimator.steps) give
what frame by frame gives, bit for bit: restarts, a gap, segments, the live gate, guessed
inputs, frames out of order, banked frames and a diverging step all act at the same
frame. The replays' likelihood summed from a block's rows is the frame-by-frame sum, and
the inputs computed for many frames at once are each frame's (decision 0065)."""

from __future__ import annotations

import math
import pickle
from collections.abc import Iterator, Mapping
from dataclasses import fields, replace
from typing import Any

import numpy as np
import pytest

from gcs_estimator.config import AircraftConfig
from gcs_estimator.estimation import history, passes
from gcs_estimator.estimation.estimator import Estimator, FilterKind, StepOutput
from gcs_estimator.estimation.filters import core
from gcs_estimator.estimation.filters.core import FILTER_KINDS
from gcs_estimator.estimation.passes import (
    Lanes,
    Runner,
    Tunings,
    _log_likelihood,
    _log_likelihoods,
)
from gcs_estimator.estimation.segments import Limits, Plan, Segment
from gcs_estimator.frames import Frame
from gcs_estimator.model.aircraft import build_model
from gcs_estimator.model.channels import BANK_INPUT, N_INPUTS, N_OBS, REQUIRED_INPUTS
from gcs_estimator.model.equations import RHO
from gcs_estimator.runtime.session import RecordingSource, Session
from gcs_estimator.stop import Stop
from gcs_estimator.uncertainty.result import VehicleResult
from sim.truth import simulate

N = 2400
"""Frames of the test flight (48 s at 50 Hz): both restarts (5 s, 10 s) and long after."""


def _flight(
    config: AircraftConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A simulated flight with what makes frames special: a channel missing now and then,
    a bank input beyond the limit for a while, a gap, a frame out of order, guessed
    inputs (one while a restart is under way), a step the filters must restart from."""
    flight = simulate(config, seed=6)
    n = min(N, len(flight.t_s))
    t = flight.t_s[:n].astype(float)
    u = np.full((n, BANK_INPUT + 1), np.nan)
    u[:, :2] = flight.inputs[:n]
    u[:, BANK_INPUT] = 0.0
    u[1300:1340, BANK_INPUT] = math.radians(70.0)  # beyond the bank limit
    y = flight.measurements[:n].copy()
    y[::5, 3] = np.nan
    y[300, 0] = 1e12  # the live pass diverges there (the second restart's re-run too)
    y[1700, 0] = 1e12  # and long after the restarts
    t[900:] += 3.0  # a gap longer than core.MAX_GAP_S
    t[1200] = t[1199] - 0.01  # a frame out of order
    known = np.ones(n, bool)
    known[[260, 1100, 2000]] = False  # the first while the first restart catches up
    return t, u, y, known


def _run(
    config: AircraftConfig,
    block: int,
    plan: Plan | None = None,
    gate: Limits | None = None,
    structure: str = "off",
) -> tuple[Session, VehicleResult]:
    config = replace(config, filter=replace(config.filter, structure_check=structure))
    t, u, y, known = _flight(config)
    session = Session(config, block_frames=block, gate=gate)
    session.run(RecordingSource(t, u, y, known, plan=plan))
    return session, session.results()[RecordingSource.SYSTEM_ID]


def _assert_same(a: tuple[Session, VehicleResult], b: tuple[Session, VehicleResult]) -> None:
    (sa, va), (sb, vb) = a, b
    ea, eb = sa.estimators[1], sb.estimators[1]
    for name in ("frames", "gaps", "out_of_order", "banked_out", "final_pass_from"):
        assert getattr(ea, name) == getattr(eb, name), name
    assert ea.restarts.done == eb.restarts.done == 2
    assert ea.pieces.fresh_frames == eb.pieces.fresh_frames
    ra, rb = va.result, vb.result
    for kind in ("EKF", "IEKF"):
        assert ea.health[kind] == eb.health[kind]
        la, lb = ea.states[kind], eb.states[kind]
        assert la is not None and lb is not None
        np.testing.assert_array_equal(la.x, lb.x)
        np.testing.assert_array_equal(la.P, lb.P)
        np.testing.assert_array_equal(la.gust.sens, lb.gust.sens)
        ta, tb = ra.filters[kind].track, rb.filters[kind].track
        assert ta is not None and tb is not None
        for field in fields(ta):
            np.testing.assert_array_equal(getattr(ta, field.name), getattr(tb, field.name))
        np.testing.assert_array_equal(ra.filters[kind].coefficients, rb.filters[kind].coefficients)
        np.testing.assert_array_equal(ra.filters[kind].sigma, rb.filters[kind].sigma)
    assert pickle.dumps(va.summaries) == pickle.dumps(vb.summaries)
    assert pickle.dumps(va.structure) == pickle.dumps(vb.structure)


@pytest.fixture(scope="module")
def frame_by_frame(noc_config: AircraftConfig) -> tuple[Session, VehicleResult]:
    return _run(noc_config, 0)


@pytest.mark.parametrize("block", [5, 256])
def test_blocks_give_the_frame_by_frame_run(
    noc_config: AircraftConfig,
    frame_by_frame: tuple[Session, VehicleResult],
    block: int,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Blocks of 5 (a boundary almost everywhere) and of 256 (most frames in one call):
    every counter, history row, health count and final belief as frame by frame; the
    history's rows also cross to disk (a small chunk) in the middle of blocks."""
    monkeypatch.setattr(history, "HISTORY_CHUNK", 300)
    _assert_same(frame_by_frame, _run(noc_config, block))
    est = frame_by_frame[0].estimators[1]
    assert est.gaps == 1 and est.out_of_order == 1 and est.banked_out == 40
    assert any(est.health[k].divergences for k in ("EKF", "IEKF"))


def test_blocks_with_segments_and_flights_from_a_plan(noc_config: AircraftConfig) -> None:
    """A recording's plan leaves frames out and starts segments afresh: the segments'
    first frames go alone, the rest in blocks, as frame by frame."""
    t = _flight(noc_config)[0]
    segments = (Segment(100, 700, t[100], t[699]), Segment(760, 2300, t[760], t[2299]))
    plan = Plan(len(t), segments)
    a, b = _run(noc_config, 0, plan=plan), _run(noc_config, 64, plan=plan)
    _assert_same(a, b)
    assert len(a[0].estimators[1].pieces.fresh_frames) == 1


def test_blocks_under_the_live_gate(noc_config: AircraftConfig) -> None:
    """The live gate judges each frame (Estimator.steps then takes each alone): the
    frames left out and the segments begun as frame by frame."""
    gate = Limits(trim_airspeed_mps=noc_config.airframe.trim_airspeed_mps, min_segment_s=0.5)
    a, b = _run(noc_config, 0, gate=gate), _run(noc_config, 128, gate=gate)
    _assert_same(a, b)
    left_a, left_b = a[1].result.segments, b[1].result.segments
    assert left_a is not None and left_b is not None
    assert left_a["left_out_frames"] == left_b["left_out_frames"]


@pytest.mark.parametrize("delay_s", [0.0, 0.05])
def test_estimator_steps_equal_admit_and_step(noc_config: AircraftConfig, delay_s: float) -> None:
    """Estimator.steps over the whole record (known inputs) against admit and step frame
    by frame, with and without the gate, with and without an input delay."""
    config = replace(noc_config, data=replace(noc_config.data, input_delay_s=delay_s))
    t, u, y, _ = _flight(config)
    gate = Limits(trim_airspeed_mps=config.airframe.trim_airspeed_mps)
    for g in (None, gate):
        a, b = Estimator(config, gate=g), Estimator(config, gate=g)
        for k in range(len(t)):
            if a.admit(float(t[k]), y[k], float(u[k, BANK_INPUT])):
                a.step(float(t[k]), u[k], y[k])
        for start in range(0, len(t), 333):
            b.steps(t[start : start + 333], u[start : start + 333], y[start : start + 333])
        a.finish_restarts()
        b.finish_restarts()
        assert (a.frames, a.gaps, a.out_of_order, a.banked_out) == (
            b.frames,
            b.gaps,
            b.out_of_order,
            b.banked_out,
        )
        for kind in ("EKF", "IEKF"):
            ta, tb = a.tracks()[kind], b.tracks()[kind]
            for field in fields(ta):
                np.testing.assert_array_equal(getattr(ta, field.name), getattr(tb, field.name))


def test_the_structure_check_in_blocks(
    noc_config: AircraftConfig,
) -> None:
    """The structure check's replays (the likelihood summed from the block's rows) on a
    run in blocks and frame by frame: the same sigma and parts."""
    a = _run(noc_config, 0, structure="on")
    b = _run(noc_config, 256, structure="on")
    _assert_same(a, b)
    check = a[1].structure
    assert check is not None and not check.skipped


def test_a_replays_likelihood_is_its_frames_sum(
    noc_config: AircraftConfig, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Runner.replay with the likelihood summed (compiled calls of up to ROWS_FRAMES
    frames, every row kept; 100 here) against the same frames stepped one at a time and
    each step's -2 log likelihood added in order (_log_likelihood): the same sums and
    beliefs, bit for bit, a diverging step included."""
    monkeypatch.setattr(passes, "ROWS_FRAMES", 100)
    model = build_model(noc_config)
    t, u, y, _ = _flight(noc_config)
    t, u, y = t[:800], model.inputs_of(u[:800]), y[:800]
    tunings: Tunings = {k: core.tuning_of(noc_config, model, k) for k in FILTER_KINDS}
    blocked = Runner(model, "fast")
    blocked.likelihood = {}
    lanes_a: Lanes = dict.fromkeys(FILTER_KINDS)
    blocked.replay(lanes_a, t, u, y, tunings, core.MAX_GAP_S)
    single = Runner(model, "fast")
    lanes_b: Lanes = dict.fromkeys(FILTER_KINDS)
    sums = dict.fromkeys(FILTER_KINDS, 0.0)
    for k in range(len(t)):
        for kind in FILTER_KINDS:
            out = single.one(kind, lanes_b, float(t[k]), u[k], y[k], True, tunings[kind])
            sums[kind] = sums[kind] + _log_likelihood(out.row, out.n)
    assert blocked.likelihood == sums
    for kind in FILTER_KINDS:
        assert blocked.health[kind] == single.health[kind]
        assert blocked.health[kind].divergences >= 1
        lane_a, lane_b = lanes_a[kind], lanes_b[kind]
        assert lane_a is not None and lane_b is not None
        np.testing.assert_array_equal(lane_a.P, lane_b.P)


def test_each_rows_likelihood_as_alone() -> None:
    """_log_likelihoods of many rows (grouped by the channels they used) against
    _log_likelihood of each row: sigmas of every size, NaN, zero and negative, NIS
    non-finite, no channel used."""
    rng = np.random.default_rng(3)
    n = 9
    width = 2 * n + 4 + 2 * N_OBS + 4
    rows = rng.normal(size=(4000, width))
    sig = rng.lognormal(0.0, 4.0, size=(4000, N_OBS))
    sig[rng.random(sig.shape) < 0.2] = np.nan
    sig[rng.random(sig.shape) < 0.05] = 0.0
    sig[rng.random(sig.shape) < 0.05] = -1.0
    sig[:50] = np.nan
    rows[:, 2 * n + 4 + N_OBS : 2 * n + 4 + 2 * N_OBS] = sig
    rows[:, 2 * n] = rng.chisquare(3.0, size=4000)
    rows[60:80, 2 * n] = np.nan
    rows[80:90, 2 * n] = np.inf
    got = _log_likelihoods(rows, n)
    want = [_log_likelihood(row, n) for row in rows]
    assert got == want


def _inputs_before(k_rho: float, u: np.ndarray) -> np.ndarray:
    """Model.inputs as it was written before this round (one frame, numpy throughout)."""
    out = np.zeros(N_INPUTS)
    out[:REQUIRED_INPUTS] = u[:REQUIRED_INPUTS]
    rho = float(u[2]) if u.shape[0] > 2 else math.nan
    out[2] = rho if math.isfinite(rho) and rho > 0.0 else k_rho
    lateral = np.asarray(u[3:N_INPUTS], float)
    out[3 : 3 + lateral.shape[0]] = np.where(np.isfinite(lateral), lateral, 0.0)
    return out


@pytest.mark.parametrize("width", [2, 3, 4, 6, 8])
def test_inputs_of_a_frame_and_of_many(noc_config: AircraftConfig, width: int) -> None:
    """Model.inputs (a frame) and Model.inputs_of (rows at once) against the numpy
    formula per frame: densities missing, NaN, zero, negative; laterals NaN and inf."""
    model = build_model(noc_config)
    rng = np.random.default_rng(width)
    u = rng.normal(size=(500, width))
    u[rng.random(u.shape) < 0.2] = np.nan
    if width > 3:
        u[rng.random(500) < 0.1, 3] = np.inf
    if width > 2:
        u[::7, 2] = 0.0
        u[::11, 2] = -1.0
        u[::13, 2] = 1.1
    want = np.array([_inputs_before(float(model.k[RHO]), row) for row in u])
    np.testing.assert_array_equal(np.array([model.inputs(row) for row in u]), want)
    np.testing.assert_array_equal(model.inputs_of(u), want)
    np.testing.assert_array_equal(model.inputs(list(u[0])), want[0])


class _Broken:
    """A source whose frames stop with an error after `n` (a link lost mid-run)."""

    def __init__(self, config: AircraftConfig, n: int) -> None:
        t, u, y, known = _flight(config)
        self.recording = RecordingSource(t, u, y, known)
        self.n = n

    def frames(self, stop: Stop) -> Iterator[Frame | None]:
        for k, frame in enumerate(self.recording.frames(stop)):
            if k == self.n:
                raise RuntimeError("the link went away")
            yield frame

    def link_stats(self) -> dict[str, Any] | None:
        return None

    def close(self) -> None:
        pass


class _Finished:
    """A sink that keeps what the run finished with."""

    def __init__(self) -> None:
        self.results: Mapping[int, VehicleResult] | None = None

    def on_frame(self, frame: Frame, outs: Mapping[FilterKind, StepOutput]) -> None:
        pass

    def tick(self) -> None:
        pass

    def finish(self, results: Mapping[int, VehicleResult], link: Mapping[str, Any] | None) -> None:
        self.results = results


def test_an_error_in_the_source_still_steps_the_frames_kept(noc_config: AircraftConfig) -> None:
    """The source fails in the middle of a block: the frames kept for it are stepped and
    the sinks finished with them, as frame by frame had."""
    config = replace(noc_config, filter=replace(noc_config.filter, structure_check="off"))
    frames: list[int | bytes] = []
    for block in (0, 256):
        sink = _Finished()
        session = Session(config, sinks=[sink], block_frames=block)
        with pytest.raises(RuntimeError, match="link went away"):
            session.run(_Broken(config, 700))
        assert sink.results is not None
        frames.append(sink.results[1].result.frames)
        track = sink.results[1].result.filters["IEKF"].track
        assert track is not None
        frames.append(track.x.tobytes())
    assert frames[0] == frames[2] == 700
    assert frames[1] == frames[3]


class _TwoVehicles:
    """Two vehicles' frames interleaved in runs of 37 (one link, two system ids), their
    restarts under way together at times (each one's grace counts the other's)."""

    def __init__(self, config: AircraftConfig) -> None:
        self.t, self.u, self.y, self.known = _flight(config)

    def frames(self, stop: Stop) -> Iterator[Frame | None]:
        n = 1600
        for a in range(0, n, 37):
            for sid, lag in ((1, 0), (2, 11)):
                for k in range(a + lag, min(a + lag + 37, n)):
                    t = float(self.t[k])
                    yield Frame(sid, t, t, self.u[k], self.y[k], inputs_known=bool(self.known[k]))
            yield None  # the link idle between runs

    def link_stats(self) -> dict[str, Any] | None:
        return None

    def close(self) -> None:
        pass


def test_two_vehicles_in_blocks(noc_config: AircraftConfig) -> None:
    """Two vehicles on one link: each block holds one vehicle's consecutive frames, so each
    estimator's calls come in the order frame by frame gives, restarts included."""
    config = replace(noc_config, filter=replace(noc_config.filter, structure_check="off"))
    runs = []
    for block in (0, 256):
        session = Session(config, block_frames=block)
        session.run(_TwoVehicles(config))
        runs.append(session)
    a, b = runs
    assert list(a.estimators) == list(b.estimators) == [1, 2]
    for sid in (1, 2):
        ea, eb = a.estimators[sid], b.estimators[sid]
        assert (ea.frames, ea.out_of_order, ea.restarts.done) == (
            eb.frames,
            eb.out_of_order,
            eb.restarts.done,
        )
        assert ea.restarts.done == 2
        for kind in FILTER_KINDS:
            ta, tb = ea.tracks()[kind], eb.tracks()[kind]
            for field in fields(ta):
                np.testing.assert_array_equal(getattr(ta, field.name), getattr(tb, field.name))
