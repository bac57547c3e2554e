"""The compiled backend keeps the step contract exactly as the numpy reference does.

Kernel level: one step from hypothesis-drawn states (random positive definite
covariances, missing channels, 1-20 iterations, the relinearisation gate, the turbulence
matching, near-singular and failing updates), both backends,
compared field by field. Flight level: both backends over the first 12 s of a flight.
"""

from __future__ import annotations

import math
from dataclasses import fields, replace
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gcs_estimator.config import AircraftConfig, load_config
from gcs_estimator.estimation.estimator import Estimator
from gcs_estimator.estimation.filters import core, fast, reference
from gcs_estimator.estimation.filters.core import FilterState, GustState, StepInfo, Tuning
from gcs_estimator.estimation.filters.lane import Lane, stepper
from gcs_estimator.model.aircraft import Model, build_model, trim
from gcs_estimator.model.channels import N_OBS
from sim.scenario import scenario_of
from sim.truth import simulate

# The two backends do the same arithmetic in a different order (fused loops, their own
# Cholesky, BLAS or not): agreement to a millionth of each state's sigma, and relative
# 1e-6 on covariances and statistics, is far below anything that matters and far above
# rounding.
PATHS_RTOL = 1e-6
# Over a flight: the zero start (prior sigma 100, posterior a thousandth) cancels all but
# 1e-10 of the prior in the first updates, so the order of the arithmetic shows there at
# a few millionths of a sigma; once the first restart's pass takes over, the two agree
# to rounding.
TRANSIENT_FRACTION = 1e-5
SETTLED_FRACTION = 1e-9

Aircraft = tuple[AircraftConfig, Model, np.ndarray]
Case = dict[str, Any]
KernelOut = tuple[FilterState, StepInfo, bool]


def _random_spd(rng: np.random.Generator, sigma: np.ndarray, correlation: float) -> np.ndarray:
    """A covariance with the given sigmas and random correlations of up to `correlation`."""
    n = sigma.size
    A = rng.standard_normal((n, n))
    C = A @ A.T + n * np.eye(n)
    d = np.sqrt(np.diag(C))
    C = C / np.outer(d, d)
    C = (1.0 - correlation) * np.eye(n) + correlation * C
    return np.asarray(C * np.outer(sigma, sigma))


def _state(model: Model, truth: np.ndarray, rng: np.random.Generator, spread: float) -> FilterState:
    tr = trim(model, truth)
    x = model.augment(tr.state, truth * (1.0 + spread * rng.standard_normal(truth.size)))
    sigma = np.zeros(model.n)
    sigma[model.flight] = [0.3, 0.01, 0.01, 0.01]
    sigma[model.gusts] = 0.5  # m/s, where the layout has gust states
    x[model.gusts] = rng.normal(0.0, 0.5, x[model.gusts].shape)
    sigma[model.coefficients] = np.abs(truth) * 0.1 + 1e-3
    P = _random_spd(rng, sigma, rng.uniform(0.0, 0.9))
    gust = GustState(
        var=float(rng.uniform(-0.05, 0.8)),
        info=float(rng.choice([0.0, rng.uniform(1.0, 1e4)])),
        gain=float(rng.uniform(0.0, 0.05)),
        pass_num=0.0,
        pass_den=0.0,
        sens=rng.uniform(0.0, 10.0, N_OBS),
        sens_age=int(rng.integers(0, core.GUST_SENSITIVITY_EVERY + 1)),
        input_ref=float(rng.choice([math.nan, rng.uniform(-0.05, 0.05)])),
        t_moved=float(rng.choice([-math.inf, rng.uniform(-5.0, 1.0)])),
        t_still=float(rng.choice([math.nan, rng.uniform(-12.0, 1.0)])),
    )
    return FilterState(x, P, 1.0, tr.inputs.copy(), gust)


def _assert_same(
    a: KernelOut,
    b: KernelOut,
    rtol: float = PATHS_RTOL,
    P_atol: float = 0.0,
) -> None:
    """Same decisions; states within rtol of their sigma, covariances within rtol of
    sqrt(P_ii P_jj) (the scale each entry is judged on) or P_atol, statistics within rtol."""
    (sa, ia, ha), (sb, ib, hb) = a, b
    # Every field of every tuple, as its type declares them (the fast backend builds them
    # from their fields in order).
    for got, typ in ((sa, FilterState), (sa.gust, GustState), (ia, StepInfo)):
        assert type(got) is typ and len(got) == len(typ._fields)
    assert ha == hb
    assert ia.failed == ib.failed and ia.n_used == ib.n_used and ia.iterations == ib.iterations
    scale = np.sqrt(np.abs(np.diag(sb.P))) + 1e-300
    assert np.all(np.abs(sa.x - sb.x) <= rtol * scale + 1e-14)
    assert np.all(np.abs(sa.P - sb.P) <= rtol * np.outer(scale, scale) + P_atol)
    # A variance within P_atol gives a sigma within P_atol / (sigma_a + sigma_b).
    sigma_atol = P_atol / (ia.sigma + ib.sigma + 1e-300)
    assert np.all(np.abs(ia.sigma - ib.sigma) <= rtol * ib.sigma + sigma_atol)
    np.testing.assert_allclose(ia.innovation, ib.innovation, rtol=rtol, atol=1e-12)
    np.testing.assert_allclose(ia.innovation_sigma, ib.innovation_sigma, rtol=rtol)
    assert ia.nis == pytest.approx(ib.nis, rel=rtol, abs=1e-9, nan_ok=True)
    assert ia.gust_sigma == pytest.approx(ib.gust_sigma, rel=1e-12)
    assert ia.gust_pass_sigma == pytest.approx(ib.gust_pass_sigma, rel=PATHS_RTOL, abs=1e-12)
    assert ia.gust_pass_sigma == pytest.approx(math.sqrt(sa.gust.pass_average()), rel=1e-15)
    ga, gb = sa.gust, sb.gust
    assert ga.sens_age == gb.sens_age
    for field in ("var", "info", "gain", "pass_num", "pass_den"):
        assert getattr(ga, field) == pytest.approx(getattr(gb, field), rel=PATHS_RTOL, abs=1e-12)
    np.testing.assert_allclose(ga.sens, gb.sens, rtol=PATHS_RTOL)
    assert sa.t == sb.t
    np.testing.assert_array_equal(sa.u, sb.u)


@pytest.fixture(scope="module")
def noc(noc_config: AircraftConfig) -> Aircraft:
    return noc_config, build_model(noc_config), np.array(noc_config.truth)


@pytest.fixture(scope="module")
def hfb(hfb_config: AircraftConfig) -> Aircraft:
    return hfb_config, build_model(hfb_config), np.array(hfb_config.truth)


STEP_CASES = st.fixed_dictionaries(
    {
        "seed": st.integers(0, 2**31),
        "iterations": st.integers(1, 20),
        "relinearise": st.sampled_from([0.0, 0.5, 1.0, 3.0]),
        "adaptive": st.booleans(),
        "dt": st.sampled_from([0.0, 0.02, 0.05, 0.1]),
        "missing": st.lists(st.booleans(), min_size=N_OBS, max_size=N_OBS),
        "spread": st.sampled_from([0.0, 0.05, 0.5]),
    }
)


def _tuning(config: AircraftConfig, model: Model, case: Case) -> Tuning:
    base = core.tuning_of(config, model, "IEKF")
    return base._replace(
        iterations=case["iterations"],
        relinearise=case["relinearise"],
        adaptive=case["adaptive"],
    )


def _one_step(aircraft: Aircraft, case: Case) -> None:
    config, model, truth = aircraft
    rng = np.random.default_rng(case["seed"])
    state = _state(model, truth, rng, case["spread"])
    tuning = _tuning(config, model, case)
    u = state.u + np.array([rng.normal(0.0, 0.02), 0.0])
    h, _ = model.h(state.x, u)
    y = h + rng.standard_normal(N_OBS) * np.sqrt(np.diag(tuning.R)) * 3.0
    y[np.array(case["missing"])] = np.nan
    t = state.t + case["dt"]
    _assert_same(
        fast.kernel_step(state, t, u, y, tuning, model),
        reference.kernel_step(state, t, u, y, tuning, model),
    )


@settings(
    max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(case=STEP_CASES)
def test_one_step_equal_on_the_noc_structure(noc: Aircraft, case: Case) -> None:
    _one_step(noc, case)


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(case=STEP_CASES)
def test_one_step_equal_on_the_hfb320_structure(hfb: Aircraft, case: Case) -> None:
    """Measured thrust, V/V0 regressors, no CLq: another layout of the same state."""
    _one_step(hfb, case)


@settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(seed=st.integers(0, 2**31), scale=st.sampled_from([1e-6, 1e-9, 1e-12]))
def test_near_singular_innovation_covariance(noc: Aircraft, seed: int, scale: float) -> None:
    """A tiny measurement noise and a nearly rank-deficient P: S barely positive definite.
    The update cancels all but `scale` of the prior, so the covariances are judged on the
    prior's scale (1e-12 of its largest entry, rounding being 1e-16 of it) and the rest to
    1e-3 (rounding of 1e-16 times a condition number of up to 1e12)."""
    config, model, truth = noc
    rng = np.random.default_rng(seed)
    state = _state(model, truth, rng, 0.0)
    v = rng.standard_normal(model.n)
    P = scale * np.eye(model.n) + np.outer(v, v)  # rank one plus a whisper
    state = state._replace(P=P)
    tuning = core.tuning_of(config, model, "IEKF")._replace(R=tuning_r(scale))
    y, _ = model.h(state.x, state.u)
    _assert_same(
        fast.kernel_step(state, state.t, state.u, y, tuning, model),
        reference.kernel_step(state, state.t, state.u, y, tuning, model),
        rtol=1e-3,
        P_atol=1e-12 * float(np.max(np.abs(P))),
    )


def tuning_r(scale: float) -> np.ndarray:
    return np.asarray(scale * np.eye(N_OBS))


@pytest.mark.parametrize("iterations", [1, 7])
def test_a_covariance_that_is_not_positive_definite_fails_the_same_way(
    noc: Aircraft,
    iterations: int,
) -> None:
    """S not positive definite: both skip the update, keep the prediction, report NaN
    innovations and NIS and `failed`; the contract then repairs P."""
    config, model, truth = noc
    state = _state(model, truth, np.random.default_rng(1), 0.0)
    P = state.P.copy()
    P[1, 1] = -1.0  # alpha's variance negative: S for the vane is not positive definite
    state = state._replace(P=P)
    tuning = core.tuning_of(config, model, "IEKF")._replace(iterations=iterations)
    y, _ = model.h(state.x, state.u)
    a = fast.kernel_step(state, state.t, state.u, y, tuning, model)
    b = reference.kernel_step(state, state.t, state.u, y, tuning, model)
    _assert_same(a, b)
    for s, info, healthy in (a, b):
        assert info.failed and not healthy
        assert np.all(np.isnan(info.innovation)) and np.isnan(info.nis)
        np.testing.assert_array_equal(s.x, state.x)
    for backend in ("fast", "reference"):
        s, info = stepper(backend)(state, state.t, state.u, y, tuning, model)
        assert info.failed and info.repaired and np.linalg.eigvalsh(s.P).min() > 0.0


def test_a_non_finite_belief_starts_again_from_the_prior(noc: Aircraft) -> None:
    config, model, truth = noc
    state = _state(model, truth, np.random.default_rng(2), 0.0)
    x = state.x.copy()
    x[0] = np.nan
    tuning = core.tuning_of(config, model, "EKF")
    y, _ = model.h(state.x, state.u)
    for backend in ("fast", "reference"):
        s, info = stepper(backend)(state._replace(x=x), 2.0, state.u, y, tuning, model)
        assert info.diverged
        np.testing.assert_array_equal(s.x[model.coefficients], 0.0)  # the zero start
        assert s.t == 2.0


def _adaptive_off(config: AircraftConfig) -> AircraftConfig:
    tuning = config.filter
    return replace(
        config,
        filter=replace(
            tuning,
            relinearise_sigma=0.0,
            turbulence=replace(tuning.turbulence, adaptive=False, sigma_w_mps=0.3),
        ),
    )


@pytest.mark.parametrize("turbulence", ["noise", "states"])
def test_fast_equals_reference_over_a_flight(noc_config: AircraftConfig, turbulence: str) -> None:
    # The turbulence level adapts from the innovations, feeding each path's rounding back
    # into its process noise, and the iteration gate is a threshold: both fixed here so
    # that the flight compares the arithmetic (the kernel tests above cover both). With
    # gust states, the flight is flown through light turbulence.
    config = _adaptive_off(noc_config)
    if turbulence == "states":
        tuning = config.filter
        config = replace(
            config, filter=replace(tuning, turbulence=replace(tuning.turbulence, model="states"))
        )
    scenario = scenario_of(config)
    if turbulence == "states":
        scenario = replace(scenario, turbulence=replace(scenario.turbulence, sigma_w_mps=0.772))
    flight = simulate(config, seed=4, scenario=scenario)
    n = 600  # 12 s: both restarts and the first multisteps
    y = flight.measurements[:n].copy()
    y[::7, 4] = np.nan  # missing channels on some frames
    # Without the climb rate: its bounds on the zero start's rounding were measured on
    # the seven channels (the kernel tests above step with it).
    y[:, 7] = np.nan
    fast_est = Estimator(config, backend="fast")
    ref_est = Estimator(config, backend="reference")
    for i in range(n):
        a = fast_est.step(float(flight.t_s[i]), flight.inputs[i], y[i])
        b = ref_est.step(float(flight.t_s[i]), flight.inputs[i], y[i])
        # Through turbulence the zero start's transient amplifies rounding further: up to
        # 2e-5 sigma here, against 7e-13 sigma once restarted.
        transient = TRANSIENT_FRACTION * (10.0 if turbulence == "states" else 1.0)
        fraction = SETTLED_FRACTION if fast_est.restarts.done else transient
        for kind in a:
            ia, ib = a[kind].info, b[kind].info
            diff = np.abs(a[kind].x - b[kind].x)
            assert np.all(diff <= fraction * ib.sigma), (i, kind, diff / ib.sigma)
            np.testing.assert_allclose(ia.sigma, ib.sigma, rtol=PATHS_RTOL)
            assert ia.n_used == ib.n_used
            assert ia.nis == pytest.approx(ib.nis, rel=PATHS_RTOL, abs=1e-9, nan_ok=True)


def test_fast_equals_reference_with_the_iteration_gate(noc_config: AircraftConfig) -> None:
    """The gate is a threshold: where re-linearising moves the estimate by almost exactly
    `relinearise_sigma` posterior sigmas, rounding can tip the two paths apart, by less
    than that threshold. They take the same decision on nearly every frame and stay within
    a twentieth of a sigma: without turbulence noise the zero-start transient before the
    first restart amplifies rounding."""
    tuning = noc_config.filter
    config = replace(
        noc_config,
        filter=replace(tuning, turbulence=replace(tuning.turbulence, adaptive=False)),
    )
    flight = simulate(config, seed=4)
    fast_est = Estimator(config, backend="fast")
    ref_est = Estimator(config, backend="reference")
    same = frames = iterated = 0
    for i in range(600):
        a = fast_est.step(float(flight.t_s[i]), flight.inputs[i], flight.measurements[i])
        b = ref_est.step(float(flight.t_s[i]), flight.inputs[i], flight.measurements[i])
        frames += 1
        same += a["IEKF"].info.iterations == b["IEKF"].info.iterations
        iterated += b["IEKF"].info.iterations > 1
        for kind in a:
            diff = np.abs(a[kind].x - b[kind].x)
            assert np.all(diff <= 5e-2 * b[kind].info.sigma), (i, kind, diff / b[kind].info.sigma)
    assert same >= 0.99 * frames
    assert 0 < iterated < frames  # the gate both keeps and drops iterations here


def test_covariance_stays_symmetric_positive_definite(noc_config: AircraftConfig) -> None:
    flight = simulate(noc_config, seed=2)
    est = Estimator(noc_config, keep_history=False)
    worst_asym = 0.0
    for i in range(len(flight.t_s)):
        est.step(float(flight.t_s[i]), flight.inputs[i], flight.measurements[i])
        if est.restarts.pending:
            continue  # the zero-start transient is replaced at the restarts
        for state in est.states.values():
            assert state is not None
            P = state.P
            worst_asym = max(worst_asym, float(np.max(np.abs(P - P.T))))
            assert np.linalg.eigvalsh(P).min() > 0.0, f"P not positive definite at frame {i}"
    assert worst_asym == 0.0  # symmetrised after every step


def test_the_reference_backend_runs_without_the_compiler() -> None:
    """The numpy reference path (and the estimator built on it) imports no numba: it is
    the independent check of the compiled one."""
    import subprocess
    import sys

    code = (
        "import sys\n"
        "from gcs_estimator.config import load_config\n"
        "from gcs_estimator.estimation.estimator import Estimator\n"
        "from gcs_estimator.model.aircraft import trim\n"
        "import numpy as np\n"
        "est = Estimator(load_config('configs/noc_uav.toml'), backend='reference')\n"
        "t = trim(est.model, np.array(est.config.truth))\n"
        "out = est.step(0.0, t.inputs, np.concatenate([t.state, np.zeros(3)]))\n"
        "assert np.isfinite(out['IEKF'].x).all()\n"
        "print('numba' in sys.modules)\n"
    )
    from tests.conftest import ROOT

    done = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True
    )
    assert done.stdout.strip() == "False"


def _frames_of(config: AircraftConfig, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    flight = simulate(config, seed=6)
    u = flight.inputs[:n].astype(float)
    y = flight.measurements[:n].copy()
    y[::5, 3] = np.nan  # a channel missing now and then
    return flight.t_s[:n].astype(float), u, y


@pytest.mark.parametrize("kind", ["EKF", "IEKF"])
def test_the_kernel_unpacks_every_field_as_packed(noc_config: AircraftConfig, kind: str) -> None:
    """pack lays out Tuning and ModelArrays from their fields (no offset written by hand);
    the kernel's _unpack gives back every field, value and type, bit for bit. Each
    scalar is set to a value of its own, so that a field read from another's place
    shows."""
    model = build_model(noc_config)
    tuning = core.tuning_of(noc_config, model, kind)  # type: ignore[arg-type]
    distinct: dict[str, Any] = {
        name: 0.125 + slot
        for slot, name in enumerate(Tuning._fields)
        if isinstance(getattr(tuning, name), float)
    }
    tuning = tuning._replace(**distinct)
    for m in (model.arrays, build_model(load_config("hfb320")).arrays):
        tf, ti = fast.pack(tuning, m)
        tun, arrays = fast._unpack(tf, ti)
        for got, want in ((tun, tuning), (arrays, m)):
            assert type(got) is type(want)
            for name, a, b in zip(want._fields, got, want, strict=True):
                if isinstance(b, np.ndarray):
                    assert isinstance(a, np.ndarray), name
                    assert a.dtype == b.dtype and a.shape == b.shape, name
                else:
                    assert type(a) is type(b), name
                np.testing.assert_array_equal(a, b, err_msg=name)


@pytest.mark.parametrize("kind", ["EKF", "IEKF"])
def test_a_lane_is_the_step_contract_bit_for_bit(noc_config: AircraftConfig, kind: str) -> None:
    """The runner's lane (the belief kept in one buffer, stepped in place) and its blocks
    give the guarded contract's beliefs and outputs bit for bit, through a step that
    leaves the belief unhealthy and is answered as the contract answers it."""
    model = build_model(noc_config)
    tuning = core.tuning_of(noc_config, model, kind)  # type: ignore[arg-type]
    t, raw, y = _frames_of(noc_config, 120)
    u = np.array([model.inputs(v) for v in raw])
    y[90, 0] = 1e12  # an airspeed no aircraft flies: the belief runs away at frame 90
    state = core.initial_state(model, tuning, t[0], u[0], y[0])
    step = stepper("fast")
    one, lane = state, Lane(state, "fast")
    counts = np.zeros(3, dtype=int)
    for k in range(1, 120):
        one, info = step(one, t[k], u[k], y[k], tuning, model)
        row, status = lane.step(t[k], u[k], y[k], tuning, model)
        np.testing.assert_array_equal(row, core.output_row(one.x, info))
        flags = core.flags_of_row(row, lane.n)
        assert bool(status) == bool(flags.any())
        counts += flags
        if k == 90:
            assert info.diverged and status
    for a, b in zip(lane.state[:-1], one[:-1], strict=True):
        np.testing.assert_array_equal(a, b)
    for ga, gb in zip(lane.state.gust, one.gust, strict=True):
        np.testing.assert_array_equal(ga, gb)
    np.testing.assert_array_equal(lane.x, one.x)
    np.testing.assert_array_equal(lane.P, one.P)

    # The same frames in blocks of 30: the last outputs, the counts and the belief.
    blocked = Lane(state, "fast")
    totals = np.zeros(3, dtype=int)
    for a in range(1, 120, 30):
        last, got = blocked.block(t[a : a + 30], u[a : a + 30], y[a : a + 30], tuning, model)
        totals += got
    np.testing.assert_array_equal(last, row)
    np.testing.assert_array_equal(totals, counts)
    assert totals[2] >= 1  # the run-away frame started the belief again
    np.testing.assert_array_equal(blocked.P, lane.P)
    np.testing.assert_array_equal(blocked.gust.sens, lane.gust.sens)

    # The reference backend's lane keeps the same contract (to its own rounding).
    ref = Lane(state, "reference")
    for k in range(1, 60):
        ref_row, _ = ref.step(t[k], u[k], y[k], tuning, model)
    mid = Lane(state, "fast")
    fast_row, _ = mid.block(t[1:60], u[1:60], y[1:60], tuning, model)
    np.testing.assert_allclose(ref_row, fast_row, rtol=1e-6, atol=1e-9)
    # A belief read out and put back steps on exactly as the one kept in place.
    moved = Lane(mid.state, "fast")
    r1, _ = mid.step(t[60], u[60], y[60], tuning, model)
    r2, _ = moved.step(t[60], u[60], y[60], tuning, model)
    np.testing.assert_array_equal(r1, r2)


def test_a_re_run_in_blocks_is_the_re_run_frame_by_frame(noc_config: AircraftConfig) -> None:
    """The estimator's re-runs step runs of frames in one call; a pass's first frame, a
    frame with guessed inputs and a belief the contract restarts go one at a time, and
    every output, health count and final belief is the same as frame by frame."""
    t, u, y = _frames_of(noc_config, 700)  # both restarts (5 s, 10 s) and beyond
    y[300, 0] = 1e12  # buffered before the second restart: its re-run diverges there
    runs = []
    for blocks in (True, False):
        est = Estimator(noc_config)
        est.runner.blocks = blocks
        for k in range(len(t)):
            est.step(t[k], u[k], y[k], inputs_known=k != 200)
        est.finish_restarts()
        runs.append(est)
    a, b = runs
    assert a.restarts.done == b.restarts.done == 2
    for kind in ("EKF", "IEKF"):
        assert a.health[kind] == b.health[kind]
        assert a.health[kind].divergences > 0  # the restart path was exercised
        ta, tb = a.tracks()[kind], b.tracks()[kind]
        for field in fields(ta):
            np.testing.assert_array_equal(getattr(ta, field.name), getattr(tb, field.name))
        sa, sb = a.states[kind], b.states[kind]
        assert sa is not None and sb is not None
        np.testing.assert_array_equal(sa.x, sb.x)
        np.testing.assert_array_equal(sa.P, sb.P)
