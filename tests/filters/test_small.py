"""The compiled step's small-matrix loops (filters.small) against numpy, on matrices shaped
and patterned like the step's: a 7 x n observation Jacobian with unit rows and zeros, a
covariance with correlations, a gain from the same S."""

from __future__ import annotations

import numpy as np
import pytest

from gcs_estimator.estimation.filters import small


def _problem(seed: int, n: int = 15, k: int = 7) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((n, n))
    P = A @ A.T + np.eye(n)
    H = np.zeros((k, n))
    for a in range(min(4, k)):
        H[a, a] = 1.0  # the channels that read one state
    for a in range(4, k):
        cols = rng.choice(n, size=rng.integers(3, n), replace=False)
        H[a, cols] = rng.standard_normal(cols.size)
    R = np.diag(rng.uniform(0.01, 1.0, k))
    return {"P": P, "H": H, "R": R, "D": rng.standard_normal((4, n))}


@pytest.mark.parametrize("seed", range(5))
def test_products_match_numpy(seed: int) -> None:
    p = _problem(seed)
    P, H, R = p["P"], p["H"], p["R"]
    start, cols = small.nonzero_columns(H)
    assert start[-1] == np.count_nonzero(H)
    HP = small.sparse_times(H, start, cols, P)
    np.testing.assert_allclose(HP, H @ P, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(small.times(H, P), H @ P, rtol=1e-13, atol=1e-13)
    S = small.gram(HP, H, R)
    np.testing.assert_allclose(S, H @ P @ H.T + R, rtol=1e-13)
    assert np.array_equal(S, S.T)


@pytest.mark.parametrize("seed", range(5))
def test_cholesky_and_solve_match_numpy(seed: int) -> None:
    p = _problem(seed)
    S = p["H"] @ p["P"] @ p["H"].T + p["R"]
    L, ok = small.cholesky(S, 0.0)
    assert ok
    np.testing.assert_allclose(L, np.linalg.cholesky(S), rtol=1e-12, atol=1e-14)
    B = p["H"] @ p["P"]
    np.testing.assert_allclose(small.cholesky_solve(L, B), np.linalg.solve(S, B), rtol=1e-10)


def test_cholesky_refuses_what_is_not_positive_definite() -> None:
    assert not small.cholesky(np.array([[1.0, 2.0], [2.0, 1.0]]), 0.0)[1]
    assert not small.cholesky(np.array([[np.nan]]), 0.0)[1]


@pytest.mark.parametrize("seed", range(5))
def test_joseph_matches_the_textbook_form(seed: int) -> None:
    """For the optimal gain and for a gain off by 10 %: the same covariance as
    (I - K H) P (I - K H)^T + K R K^T, and symmetric."""
    p = _problem(seed)
    P, H, R = p["P"], p["H"], p["R"]
    S = H @ P @ H.T + R
    for scale in (1.0, 1.1):
        K = scale * np.linalg.solve(S, H @ P).T
        I_KH = np.eye(P.shape[0]) - K @ H
        expected = I_KH @ P @ I_KH.T + K @ R @ K.T
        got = small.joseph(P, np.ascontiguousarray(K.T), H, H @ P, R)
        np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-12 * np.abs(P).max())
        assert np.array_equal(got, got.T)


@pytest.mark.parametrize("seed", range(5))
def test_congruence_with_a_transition_that_differs_from_identity_in_its_top_rows(
    seed: int,
) -> None:
    p = _problem(seed)
    P, D = p["P"].copy(), p["D"]
    Phi = np.eye(P.shape[0])
    Phi[: D.shape[0]] += D
    expected = Phi @ P @ Phi.T
    small.congruence(P, D)
    np.testing.assert_allclose(P, expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())
    small.symmetrise(P)
    assert np.array_equal(P, P.T)
