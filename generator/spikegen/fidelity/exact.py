"""Linear algebra of ``spikegen diagnose`` whose bits do not depend on the number of BLAS threads.

OpenBLAS splits long reductions over its threads, so ``A.T @ b`` and ``b @ b`` round differently
under ``OMP_NUM_THREADS=1`` and ``=2``: with the NumPy of this project's environment ``A.T @ b``
of 4096 rows and ``b @ b`` of 20000 entries differed in their last bits. One such bit in the rate
fit moved the fitted flicker depth, hence the diagnosis' own simulations, hence verdicts. The
functions here sum over pixels and frames with NumPy's own reductions (one thread, an order fixed
by the shapes alone); LAPACK sees only the small systems they produce (at most 4 unknowns).

NumPy sums an axis that is not the last (``A.sum(axis=0)`` of ``[n, p]``, ``p >= 2``) one row
after another, which is the order of a running sum (``np.cumsum``), and the short last axis of
:func:`matvec` (``p <= 7``) one column after another. :func:`gram` and :func:`rmatvec` take the
last entry of a running sum of each column (a tight loop, several times faster than the
reduction, whose inner loop is only ``p`` long), :func:`matvec` adds the columns in order: the
same additions in the same order, so the same bits (tests/test_diagnose.py compares them with
the reductions).
"""
from __future__ import annotations

import numpy as np


def dot(a: np.ndarray, b: np.ndarray) -> float:
    """``sum(a * b)`` of two vectors."""
    return float(np.sum(np.asarray(a, dtype=np.float64) * b))


def matvec(A: np.ndarray, x) -> np.ndarray:
    """``A @ x`` for ``A [n, p]``, ``x [p]``: ``[n]``."""
    A, x = np.asarray(A, dtype=np.float64), np.asarray(x, dtype=np.float64)
    if not 1 <= A.shape[1] <= 7:  # NumPy sums 8 or more pairwise
        return (A * x[None, :]).sum(axis=1)
    out = A[:, 0] * x[0]
    for j in range(1, A.shape[1]):
        out += A[:, j] * x[j]
    return out


def _running_total(a: np.ndarray, b: np.ndarray) -> float:
    """``sum(a * b)`` added in order, first to last (as NumPy sums an outer axis)."""
    return float(np.cumsum(a * b)[-1]) if a.size else 0.0


def rmatvec(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``A.T @ b`` for ``A [n, p]``, ``b [n]``: ``[p]``."""
    A, b = np.asarray(A, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if A.shape[1] < 2:  # a single column is summed pairwise
        return (A * b[:, None]).sum(axis=0)
    return np.array([_running_total(A[:, j], b) for j in range(A.shape[1])])


def gram(A: np.ndarray) -> np.ndarray:
    """``A.T @ A`` for ``A [n, p]``: ``[p, p]``."""
    A = np.asarray(A, dtype=np.float64)
    p = A.shape[1]
    if p < 2:  # a single column is summed pairwise
        return (A[:, :, None] * A[:, None, :]).sum(axis=0)
    cols = [np.ascontiguousarray(A[:, j]) for j in range(p)]
    M = np.empty((p, p))
    for i in range(p):
        for j in range(i, p):
            M[i, j] = M[j, i] = _running_total(cols[i], cols[j])
    return M


def lstsq(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Least-squares ``x`` minimising ``|A x - b|`` for ``A [n, p]`` with small ``p``: the normal
    equations, columns scaled to unit norm, solved by LAPACK's minimum-norm least squares (so a
    rank-deficient design still gives a solution with the same fitted values)."""
    return solve_normal(gram(A), rmatvec(A, b))


def solve_normal(M: np.ndarray, v: np.ndarray) -> np.ndarray:
    """:func:`lstsq` from its normal equations ``M = gram(A)``, ``v = rmatvec(A, b)``."""
    s = np.sqrt(np.diag(M))
    s = np.where(s > 0, s, 1.0)
    y = np.linalg.lstsq(M / np.outer(s, s), v / s, rcond=None)[0]
    return y / s


def interpolate(weights: np.ndarray, X: np.ndarray) -> np.ndarray:
    """``weights @ X`` for ``weights [T, K]`` (sensor.interpolation_weights: at most two nonzero
    per row) and ``X [K, N]``: ``[T, N]``, summed over ``k`` in order."""
    X = np.asarray(X, dtype=np.float64)
    out = np.zeros((weights.shape[0], X.shape[1]))
    for k in range(X.shape[0]):
        w = weights[:, k]
        rows = np.flatnonzero(w)
        if rows.size:
            out[rows] += w[rows, None] * X[k][None, :]
    return out
