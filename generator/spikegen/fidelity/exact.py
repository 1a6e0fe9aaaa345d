"""Linear algebra of ``spikegen diagnose`` whose bits do not depend on the number of BLAS threads.

OpenBLAS splits long reductions over its threads, so ``A.T @ b`` and ``b @ b`` round differently
under ``OMP_NUM_THREADS=1`` and ``=2``: with the NumPy of this project's environment ``A.T @ b``
of 4096 rows and ``b @ b`` of 20000 entries differed in their last bits. One such bit in the rate
fit moved the fitted flicker depth, hence the diagnosis' own simulations, hence verdicts. The
functions here sum over pixels and frames with NumPy's own reductions (one thread, an order fixed
by the shapes alone); LAPACK sees only the small systems they produce (at most 4 unknowns).

NumPy sums an axis that is not the last (``X.sum(axis=0)`` of ``[n, k]``, ``k >= 2``) one row
after another, and the short last axis of :func:`matvec` (``p <= 7``) one column after another.
:func:`gram` sums each product of two columns once (not the ``p x p`` of them) in one such
reduction, :func:`normal_equations` the products of :func:`gram` and :func:`rmatvec` together,
from the columns, without stacking the matrix; :func:`matvec` adds the columns in order: the
same additions in the same order as the plain reductions, so the same bits
(tests/test_diagnose.py compares them).
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


def rmatvec(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``A.T @ b`` for ``A [n, p]``, ``b [n]``: ``[p]``."""
    return (np.asarray(A, dtype=np.float64) * np.asarray(b, dtype=np.float64)[:, None]).sum(axis=0)


def gram(A: np.ndarray) -> np.ndarray:
    """``A.T @ A`` for ``A [n, p]``: ``[p, p]``."""
    A = np.asarray(A, dtype=np.float64)
    if A.shape[1] < 2:  # a single column is summed pairwise
        return (A[:, :, None] * A[:, None, :]).sum(axis=0)
    return _pair_sums([A[:, j] for j in range(A.shape[1])], A.shape[0])[0]


def normal_equations(cols: list, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(gram(A), rmatvec(A, b))`` of the matrix ``A`` whose columns are ``cols`` (``[n]`` each,
    at least two), the same bits, without stacking ``A``."""
    return _pair_sums(cols, len(b), b)


def _pair_sums(cols: list, n: int, b: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(gram of the columns, their products with b summed)``: every product of two columns (each
    pair once) and of each column with ``b`` in one ``[n, k]`` array, summed over its rows by one
    reduction (NumPy adds row after row, as :func:`gram` and :func:`rmatvec` do)."""
    p = len(cols)
    pairs = [(i, j) for i in range(p) for j in range(i, p)]
    prod = np.empty((n, len(pairs) + (p if b is not None else 0)))
    for k, (i, j) in enumerate(pairs):
        np.multiply(cols[i], cols[j], out=prod[:, k])
    if b is not None:
        for k, col in enumerate(cols):
            np.multiply(col, b, out=prod[:, len(pairs) + k])
    sums = prod.sum(axis=0)
    M = np.empty((p, p))
    for k, (i, j) in enumerate(pairs):
        M[i, j] = M[j, i] = sums[k]
    return M, sums[len(pairs):]


def matvec_columns(cols: list, x) -> np.ndarray:
    """:func:`matvec` of the matrix whose columns are ``cols`` (one to seven), the same bits."""
    out = cols[0] * x[0]
    for j in range(1, len(cols)):
        out += cols[j] * x[j]
    return out


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
