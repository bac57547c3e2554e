"""Small-matrix arithmetic for the compiled filter step (filters.fast), written as loops.

The matrices of one step are 7 x 15 to 15 x 15 (larger with bias states). At that size a
BLAS call costs more in its entry than in its arithmetic, and the observation Jacobian is
mostly zeros (the first four channels read one state each; the coefficients enter the
rest by axis). The functions here skip what is zero, allocate nothing but their results,
and loop over contiguous rows. tests/filters/test_small.py checks each against numpy.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from gcs_estimator.arrays import FloatArray, IntArray

FAST = {"contract", "reassoc"}
"""numba fastmath flags: fused multiply-adds and reordered sums, so that the row loops
vectorise. Not the flags that assume finite values: the step checks for NaN and inf."""


@njit(cache=True)
def nonzero_columns(H: FloatArray) -> tuple[IntArray, IntArray]:  # pragma: no cover
    """The non-zero pattern of H by rows, CSR-like: columns cols[start[i]:start[i+1]]."""
    rows, n = H.shape
    start = np.zeros(rows + 1, dtype=np.int64)
    cols = np.empty(rows * n, dtype=np.int64)
    c = 0
    for i in range(rows):
        for j in range(n):
            if H[i, j] != 0.0:
                cols[c] = j
                c += 1
        start[i + 1] = c
    return start, cols


@njit(cache=True, fastmath=FAST)
def sparse_times(
    H: FloatArray, start: IntArray, cols: IntArray, P: FloatArray
) -> FloatArray:  # pragma: no cover
    """H @ P over the non-zeros of H (pattern from nonzero_columns)."""
    rows = H.shape[0]
    n = P.shape[1]
    out = np.zeros((rows, n))
    for i in range(rows):
        out_i = out[i]
        for c in range(start[i], start[i + 1]):
            j = cols[c]
            h = H[i, j]
            P_j = P[j]
            for b in range(n):
                out_i[b] += h * P_j[b]
    return out


@njit(cache=True, fastmath=FAST)
def gram(A: FloatArray, B: FloatArray, R: FloatArray) -> FloatArray:  # pragma: no cover
    """A @ B.T + R for a product known to be symmetric (H P H^T + R, with A = H P and
    B = H): the lower triangle by row dot products, mirrored."""
    k, n = A.shape
    out = np.empty((k, k))
    for a in range(k):
        A_a = A[a]
        for b in range(a + 1):
            B_b = B[b]
            acc = 0.0
            for j in range(n):
                acc += A_a[j] * B_b[j]
            out[a, b] = acc + 0.5 * (R[a, b] + R[b, a])
            out[b, a] = out[a, b]
    return out


@njit(cache=True)
def cholesky(S: FloatArray, jitter: float) -> tuple[FloatArray, bool]:  # pragma: no cover
    """Lower Cholesky factor of S + jitter * max(1, max|S_ii|) I; False if that is not
    positive definite (or not finite)."""
    m = S.shape[0]
    scale = 1.0
    for i in range(m):
        scale = max(scale, abs(S[i, i]))
    jitter = jitter * scale
    L = np.zeros((m, m))
    for i in range(m):
        for j in range(i + 1):
            acc = S[i, j]
            for c in range(j):
                acc -= L[i, c] * L[j, c]
            if i != j:
                L[i, j] = acc / L[j, j]
                continue
            acc += jitter
            if not acc > 0.0:  # also catches NaN
                return L, False
            L[i, i] = math.sqrt(acc)
    return L, True


@njit(cache=True)
def cholesky_solve(L: FloatArray, B: FloatArray) -> FloatArray:  # pragma: no cover
    """(L L^T)^-1 B for lower-triangular L, by rows: forward then back substitution on
    whole rows of B, so the inner loops run along B's contiguous rows."""
    m = L.shape[0]
    n = B.shape[1]
    Z = B.copy()
    for i in range(m):
        for j in range(i):
            lij = L[i, j]
            for c in range(n):
                Z[i, c] -= lij * Z[j, c]
        inv = 1.0 / L[i, i]
        for c in range(n):
            Z[i, c] *= inv
    for i in range(m - 1, -1, -1):
        for j in range(i + 1, m):
            lji = L[j, i]
            for c in range(n):
                Z[i, c] -= lji * Z[j, c]
        inv = 1.0 / L[i, i]
        for c in range(n):
            Z[i, c] *= inv
    return Z


@njit(cache=True, fastmath=FAST)
def joseph(
    P: FloatArray, Kt: FloatArray, H: FloatArray, HP: FloatArray, R: FloatArray
) -> FloatArray:  # pragma: no cover
    """The Joseph-form covariance (I - K H) P (I - K H)^T + K R K^T from the gain's
    transpose Kt = K^T [k x n] and HP = H @ P:

        A = P - K (H P),   (I - K H) P (I - K H)^T + K R K^T = A - (A H^T - K R) K^T.

    With K = K* + dK, K* the optimal gain, this is P* + dK S dK^T: second order in the
    gain's rounding error, as the Joseph form is. A = P* - dK H P is not symmetric, so it
    is formed whole; the result is, so only its lower triangle is formed and mirrored:
    n^2 k for each product instead of n^3."""
    n = P.shape[0]
    k = Kt.shape[0]
    A = P.copy()
    _less_outer(A, Kt, HP, False)
    # B^T = H A^T - R K^T (R symmetric), over the non-zeros of H and R.
    Bt = np.zeros((k, n))
    for b in range(k):
        Bt_b = Bt[b]
        for j in range(n):
            h = H[b, j]
            if h == 0.0:
                continue
            for i in range(n):
                Bt_b[i] += h * A[i, j]
        for a in range(k):
            r = R[b, a]
            if r == 0.0:
                continue
            Kt_a = Kt[a]
            for i in range(n):
                Bt_b[i] -= r * Kt_a[i]
    _less_outer(A, Bt, Kt, True)
    return A


@njit(cache=True, fastmath=FAST)
def _less_outer(
    A: FloatArray, Ut: FloatArray, V: FloatArray, symmetric: bool
) -> None:  # pragma: no cover
    """A <- A - Ut^T V. For a result known to be symmetric only the lower triangle of A
    is updated, then mirrored onto the upper."""
    n = A.shape[0]
    for i in range(n):
        A_i = A[i]
        stop = i + 1 if symmetric else A.shape[1]
        for a in range(Ut.shape[0]):
            u = Ut[a, i]
            V_a = V[a]
            for j in range(stop):
                A_i[j] -= u * V_a[j]
    if symmetric:
        _mirror(A)


@njit(cache=True)
def _mirror(A: FloatArray) -> None:  # pragma: no cover
    """Copy the lower triangle of A onto the upper."""
    n = A.shape[0]
    for i in range(n):
        for j in range(i):
            A[j, i] = A[i, j]


@njit(cache=True)
def symmetrise(P: FloatArray) -> None:  # pragma: no cover
    """P <- (P + P^T) / 2 in place."""
    n = P.shape[0]
    for i in range(n):
        for j in range(i):
            v = 0.5 * (P[i, j] + P[j, i])
            P[i, j] = v
            P[j, i] = v


@njit(cache=True)
def times(A: FloatArray, B: FloatArray) -> FloatArray:  # pragma: no cover
    """A @ B, skipping the zeros of A, along B's rows."""
    m, c_n = A.shape
    n = B.shape[1]
    out = np.zeros((m, n))
    for i in range(m):
        for c in range(c_n):
            a = A[i, c]
            if a == 0.0:
                continue
            for j in range(n):
                out[i, j] += a * B[c, j]
    return out


@njit(cache=True)
def congruence(P: FloatArray, D: FloatArray) -> None:  # pragma: no cover
    """P <- (I + E) P (I + E)^T in place for symmetric P, where E is zero but for its
    first d rows, D [d x n]: P + E P + P E^T + E P E^T at d x n x n instead of n^3."""
    d = D.shape[0]
    DP = times(D, P)
    DPD = np.zeros((d, d))
    n = D.shape[1]
    for i in range(d):
        for j in range(d):
            acc = 0.0
            for c in range(n):
                acc += DP[i, c] * D[j, c]
            DPD[i, j] = acc
    for i in range(d):
        for j in range(n):
            P[i, j] += DP[i, j]
            P[j, i] += DP[i, j]
        for j in range(d):
            P[i, j] += DPD[i, j]
