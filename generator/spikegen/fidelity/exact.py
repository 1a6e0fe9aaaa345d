"""Linear algebra of ``spikegen diagnose`` whose bits do not depend on the number of BLAS threads.

OpenBLAS splits long reductions over its threads, so ``A.T @ b`` and ``b @ b`` round differently
under ``OMP_NUM_THREADS=1`` and ``=2``: with the NumPy of this project's environment ``A.T @ b``
of 4096 rows and ``b @ b`` of 20000 entries differed in their last bits. One such bit in the rate
fit moved the fitted flicker depth, hence the diagnosis' own simulations, hence verdicts. The
functions here sum over pixels and frames with NumPy's own reductions (one thread, an order fixed
by the shapes alone); LAPACK sees only the small systems they produce (at most 4 unknowns).
"""
from __future__ import annotations

import numpy as np


def dot(a: np.ndarray, b: np.ndarray) -> float:
    """``sum(a * b)`` of two vectors."""
    return float(np.sum(np.asarray(a, dtype=np.float64) * b))


def matvec(A: np.ndarray, x) -> np.ndarray:
    """``A @ x`` for ``A [n, p]``, ``x [p]``: ``[n]``."""
    return (np.asarray(A, dtype=np.float64) * np.asarray(x, dtype=np.float64)[None, :]).sum(axis=1)


def rmatvec(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``A.T @ b`` for ``A [n, p]``, ``b [n]``: ``[p]``."""
    return (np.asarray(A, dtype=np.float64) * np.asarray(b, dtype=np.float64)[:, None]).sum(axis=0)


def gram(A: np.ndarray) -> np.ndarray:
    """``A.T @ A`` for ``A [n, p]``: ``[p, p]``."""
    A = np.asarray(A, dtype=np.float64)
    return (A[:, :, None] * A[:, None, :]).sum(axis=0)


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
