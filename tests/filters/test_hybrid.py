"""Hybrid EKF and IEKF against exact results (spec style.md, point 10)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm

from gcs_estimator.arrays import FloatArray
from gcs_estimator.estimation.filters.hybrid import Belief, ekf_update, iekf_update, propagate

# RK4 with 1 ms steps on a system whose fastest mode is ~3 rad/s: local error ~(3e-3)^5,
# so the hybrid prediction matches the exact discretisation far below this tolerance.
EXACT_RTOL = 1e-9


def linear_system(seed: int) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    rng = np.random.default_rng(seed)
    n, m = 5, 3
    A = rng.normal(size=(n, n)) * 0.5 - np.eye(n)
    C = rng.normal(size=(m, n))
    Qc = np.diag(rng.uniform(0.01, 0.1, n))
    R = np.diag(rng.uniform(0.05, 0.2, m))
    return A, C, Qc, R


def exact_discretisation(A: FloatArray, Qc: FloatArray, dt: float) -> tuple[FloatArray, FloatArray]:
    """Van Loan: Phi = expm(A dt), Qd = int_0^dt Phi(s) Qc Phi(s)^T ds."""
    n = A.shape[0]
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n] = -A
    M[:n, n:] = Qc
    M[n:, n:] = A.T
    E = expm(M * dt)
    Phi = E[n:, n:].T
    return Phi, Phi @ E[:n, n:]


def kalman(x: FloatArray, P: FloatArray, y: FloatArray, C: FloatArray, R: FloatArray) -> Belief:
    used = np.isfinite(y)
    Cu, Ru, yu = C[used], R[np.ix_(used, used)], y[used]
    K = P @ Cu.T @ np.linalg.inv(Cu @ P @ Cu.T + Ru)
    return Belief(x + K @ (yu - Cu @ x), (np.eye(len(x)) - K @ Cu) @ P)


@pytest.mark.parametrize("iterations", [1, 2, 7, 20])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_equals_exact_kalman_filter_on_linear_model(iterations: int, seed: int) -> None:
    A, C, Qc, R = linear_system(seed)
    rng = np.random.default_rng(100 + seed)
    n = A.shape[0]
    x, P = np.zeros(n), np.eye(n)
    belief = Belief(x, P)
    dts = rng.uniform(0.02, 0.3, size=40)  # uneven measurement intervals
    for k, dt in enumerate(dts):
        y = np.asarray(rng.normal(size=C.shape[0]), dtype=float)
        if k % 4 == 1:
            y[rng.integers(C.shape[0])] = np.nan  # missing channels are normal
        Phi, Qd = exact_discretisation(A, Qc, dt)
        x, P = Phi @ x, Phi @ P @ Phi.T + Qd
        x, P = kalman(x, P, y, C, R)
        belief = propagate(lambda z, _s: (A @ z, A), belief, Qc, dt, max_step=1e-3)
        belief, info = iekf_update(lambda z: (C @ z, C), belief, y, R, iterations=iterations)
        assert info.used.sum() == np.isfinite(y).sum()
    np.testing.assert_allclose(belief.x, x, rtol=EXACT_RTOL, atol=1e-12)
    np.testing.assert_allclose(belief.P, P, rtol=EXACT_RTOL, atol=1e-12)


def test_a_coarse_step_on_stiff_non_normal_dynamics_keeps_p_positive_definite() -> None:
    """The aircraft's short period and pitch integrator (alpha drives q at 165 rad/s^2 per
    radian), from a tight, correlated theta under strong alpha noise: the case where
    integrating P' itself fails (docs/decisions/0002). The transition-matrix form stays
    positive definite and close to the exact discretisation."""
    A = np.array([[-4.5, 0.0, 1.0], [0.0, 0.0, 1.0], [-165.0, 0.0, -10.8]])
    sigma = np.array([2.5e-4, 1.2e-6, 5.3e-4])
    corr = np.array([[1.0, 0.75, 0.88], [0.75, 1.0, 0.43], [0.88, 0.43, 1.0]])
    P0 = corr * np.outer(sigma, sigma)
    Qc = np.diag([7e-3, 1e-9, 4e-6])
    Phi, Qd = exact_discretisation(A, Qc, 0.02)
    exact = Phi @ P0 @ Phi.T + Qd
    P = propagate(lambda z, _s: (A @ z, A), Belief(np.zeros(3), P0), Qc, 0.02, max_step=0.02).P
    assert np.linalg.eigvalsh(P).min() > 0.0
    np.testing.assert_allclose(np.diag(P), np.diag(exact), rtol=0.1)
    assert np.abs(P - exact).max() < 1e-3 * np.abs(exact).max()


def test_iekf_with_one_iteration_is_the_ekf() -> None:
    def h(x: FloatArray) -> tuple[FloatArray, FloatArray]:
        return np.array([np.sin(x[0]) * x[1], x[0] ** 2]), np.array(
            [[np.cos(x[0]) * x[1], np.sin(x[0])], [2 * x[0], 0.0]]
        )

    belief = Belief(np.array([0.3, 1.2]), np.array([[0.5, 0.1], [0.1, 0.3]]))
    y, R = np.array([0.7, 0.2]), np.diag([0.01, 0.02])
    a, ia = ekf_update(h, belief, y, R)
    b, ib = iekf_update(h, belief, y, R, iterations=1)
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.P, b.P)
    assert ia.nis == ib.nis and ia.iterations == ib.iterations == 1


def test_iekf_converges_to_the_map_with_the_prior_held_fixed() -> None:
    """The IEKF is Gauss-Newton on the single-measurement MAP problem; at convergence
    P-^-1 (x - x-) = H(x)^T R^-1 (y - h(x)). Feeding the posterior back as the prior (a
    known library bug) uses the measurement N times and misses this condition."""

    def h(x: FloatArray) -> tuple[FloatArray, FloatArray]:
        return np.array([x[0] * x[1], np.exp(0.3 * x[0])]), np.array(
            [[x[1], x[0]], [0.3 * np.exp(0.3 * x[0]), 0.0]]
        )

    prior = Belief(np.array([1.0, 2.0]), np.array([[0.4, 0.05], [0.05, 0.6]]))
    y, R = np.array([3.1, 1.5]), np.diag([0.05, 0.02])
    post, info = iekf_update(h, prior, y, R, iterations=50, tolerance=1e-13)
    assert info.iterations < 50
    hx, H = h(post.x)
    lhs = np.linalg.solve(prior.P, post.x - prior.x)
    rhs = H.T @ np.linalg.solve(R, y - hx)
    np.testing.assert_allclose(lhs, rhs, rtol=1e-8, atol=1e-10)

    # The feed-back variant (posterior as prior each time) lands elsewhere.
    fb = prior
    for _ in range(50):
        fb, _ = ekf_update(h, fb, y, R)
    assert np.max(np.abs(fb.x - post.x)) > 1e-3


def test_relinearisation_gate_keeps_the_ekf_near_the_solution_and_iterates_far() -> None:
    """relinearise > 0: the iterations are kept only when the first re-linearisation
    moves the estimate by at least that many EKF-posterior sigmas."""

    def h(x: FloatArray) -> tuple[FloatArray, FloatArray]:
        return np.array([x[0] * x[1]]), np.array([[x[1], x[0]]])

    R = np.diag([0.01])
    # Near the solution (a tight prior): re-linearising moves x by a small fraction of a
    # posterior sigma, so the EKF update comes back, bit for bit.
    near = Belief(np.array([1.0, 2.0]), np.diag([1e-3, 1e-3]))
    y_near = np.array([2.05])
    ekf, _ = ekf_update(h, near, y_near, R)
    gated, info = iekf_update(h, near, y_near, R, iterations=7, relinearise=1.0)
    assert info.iterations == 1
    np.testing.assert_array_equal(gated.x, ekf.x)
    np.testing.assert_array_equal(gated.P, ekf.P)
    # Far from it (a wide prior, a product far from the prior's): the iterations move x
    # by many sigma and are kept, equal to the ungated IEKF.
    far = Belief(np.array([0.1, 0.1]), np.diag([4.0, 4.0]))
    y_far = np.array([3.0])
    full, _ = iekf_update(h, far, y_far, R, iterations=7)
    kept, info = iekf_update(h, far, y_far, R, iterations=7, relinearise=1.0)
    assert info.iterations == 7
    np.testing.assert_array_equal(kept.x, full.x)
    ekf_far, _ = ekf_update(h, far, y_far, R)
    assert np.max(np.abs(kept.x - ekf_far.x) / np.sqrt(np.diag(ekf_far.P))) > 1.0


def test_no_channel_present_leaves_the_belief_unchanged() -> None:
    belief = Belief(np.array([1.0, 2.0]), np.eye(2))
    post, info = iekf_update(
        lambda x: (x.copy(), np.eye(2)), belief, np.array([np.nan, np.nan]), np.eye(2)
    )
    assert post is belief and info.iterations == 0 and info.nis == 0.0


def test_relinearisation_gate_judges_only_the_components_named() -> None:
    """With `judged`, only those components' moves keep the iterations: a measurement that
    moves an unjudged component (a state a gust moved) by many sigma on re-linearising,
    while the judged one (a coefficient) barely moves, gets the EKF update; judging every
    component, the same update iterates."""

    def h(x: FloatArray) -> tuple[FloatArray, FloatArray]:
        return np.array([x[0] ** 2 + x[1]]), np.array([[2.0 * x[0], 1.0]])

    R = np.diag([0.01])
    # x[0] a state with a wide prior, x[1] a coefficient known closely.
    prior = Belief(np.array([0.5, 1.0]), np.diag([4.0, 1e-4]))
    y = np.array([5.0])
    ekf, _ = ekf_update(h, prior, y, R)
    _, info_every = iekf_update(h, prior, y, R, iterations=7, relinearise=1.0)
    assert info_every.iterations == 7
    gated, info = iekf_update(h, prior, y, R, iterations=7, relinearise=1.0, judged=slice(1, 2))
    assert info.iterations == 1
    np.testing.assert_array_equal(gated.x, ekf.x)
    np.testing.assert_array_equal(gated.P, ekf.P)
