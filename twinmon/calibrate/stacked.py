"""Linear algebra on stacks of small matrices: a unit's trend models solve thousands of
systems of 2 to 8 unknowns at once (one per sigma point, year or design), on which LAPACK's
per-matrix calls cost several times the arithmetic. Each routine works over the whole stack
one entry or row at a time, and falls back to LAPACK where that is no cheaper.

Used by :mod:`.gaussian_trend`, :mod:`.shape_screen` and the forecast's trend-fit check
(:mod:`twinmon.forecast.trendfit`); tests/unit/test_calibrate_shapes.py and
tests/unit/test_calibrate_laplace.py check each against numpy's LAPACK.
"""
from __future__ import annotations

import numpy as np

#: Fewest matrices of a stack that :func:`small_cholesky` factors entry by entry (fewer:
#: LAPACK's calls cost no more).
CHOLESKY_STACK = 64
#: Fewest systems that :func:`chol_solve` serves by substitution rather than LAPACK's solve
#: (measured: 100 systems of 6, 33 against 61 us; 512, 236 against 168 us; 16 x 512 of 8,
#: 3.8 against 1.2 ms).
SOLVE_STACK = 256


def inv_logdet(V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverses and log-determinants of stacked symmetric positive definite matrices
    ``V`` [..., d, d]; closed form for d <= 2 (the usual case)."""
    d = V.shape[-1]
    if d == 1:
        return 1.0 / V, np.log(V[..., 0, 0])
    if d == 2:
        a, b, c = V[..., 0, 0], V[..., 0, 1], V[..., 1, 1]
        det = a * c - b * b
        inv = np.stack([np.stack([c, -b], -1), np.stack([-b, a], -1)], -2) / det[..., None, None]
        return inv, np.log(det)
    L = np.linalg.cholesky(V)
    return np.linalg.inv(V), 2.0 * np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum(axis=-1)


def inv_chol(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverses of stacked symmetric positive definite matrices ``A`` [..., d, d] and the
    inverses' Cholesky factors; closed form for d = 2 (a unit's draws are thousands of
    2 x 2 matrices, for which LAPACK's calls cost ten times the arithmetic)."""
    if A.shape[-1] != 2:
        G = np.linalg.inv(A)
        return G, np.linalg.cholesky(G)
    a, b, c = A[..., 0, 0], A[..., 0, 1], A[..., 1, 1]
    det = a * c - b * b
    g00, g01, g11 = c / det, -b / det, a / det
    G = np.stack([np.stack([g00, g01], -1), np.stack([g01, g11], -1)], -2)
    l00 = np.sqrt(g00)
    l10 = g01 / l00
    L = np.zeros_like(G)
    L[..., 0, 0], L[..., 1, 0], L[..., 1, 1] = l00, l10, np.sqrt(g11 - l10 * l10)
    return G, L


def small_cholesky(V: np.ndarray) -> np.ndarray:
    """Cholesky factors of stacked symmetric positive definite matrices ``V`` [..., n, n],
    entry by entry over the whole stack when they are small and many (n <= 4, at least
    :data:`CHOLESKY_STACK` of them), else LAPACK's (which also raises on a matrix that is
    not positive definite)."""
    n = V.shape[-1]
    if n > 4 or V.size < CHOLESKY_STACK * n * n:
        return np.linalg.cholesky(V)
    L = np.zeros_like(V)
    for j in range(n):
        acc = V[..., j, j].copy()
        for m in range(j):
            acc -= L[..., j, m] ** 2
        L[..., j, j] = np.sqrt(acc)
        for i in range(j + 1, n):
            acc = V[..., i, j].copy()
            for m in range(j):
                acc -= L[..., i, m] * L[..., j, m]
            L[..., i, j] = acc / L[..., j, j]
    if not np.all(np.einsum("...ii->...i", L) > 0):
        return np.linalg.cholesky(V)
    return L


def forward_solve(L: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``L^-1 B`` for stacked lower-triangular ``L`` [..., n, n] and ``B`` [..., n, m], by
    forward substitution over the ``n`` rows, each an operation on the whole stack."""
    n = L.shape[-1]
    Y = np.empty(np.broadcast_shapes(L.shape[:-2], B.shape[:-2]) + B.shape[-2:])
    for i in range(n):
        acc = B[..., i, :].copy()
        for j in range(i):
            acc -= L[..., i, j, None] * Y[..., j, :]
        Y[..., i, :] = acc / L[..., i, i, None]
    return Y


def back_solve(L: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """``L^-T Y`` for stacked lower-triangular ``L`` [..., n, n] and ``Y`` [..., n, m], by
    back substitution over the ``n`` rows (:func:`forward_solve`'s counterpart)."""
    n = L.shape[-1]
    X = np.empty(np.broadcast_shapes(L.shape[:-2], Y.shape[:-2]) + Y.shape[-2:])
    for i in range(n - 1, -1, -1):
        acc = Y[..., i, :].copy()
        for j in range(i + 1, n):
            acc -= L[..., j, i, None] * X[..., j, :]
        X[..., i, :] = acc / L[..., i, i, None]
    return X


def chol_solve(P: np.ndarray, L: np.ndarray, b: np.ndarray, want_x: bool = True):
    """``y = L^-1 b`` and ``x = P^-1 b`` for stacked symmetric positive definite ``P``
    [..., n, n] with Cholesky factor ``L`` and vectors ``b`` [..., n]: ``b' P^-1 b = |y|^2``
    and the solution from the factor already taken for a log-determinant, by substitution
    for :data:`SOLVE_STACK` systems or more, by LAPACK's solve below that (``y`` is then
    None). Returns ``(y, x)``, ``x`` None without ``want_x``."""
    if want_x and b[..., 0].size < SOLVE_STACK:
        return None, np.linalg.solve(P, b[..., None])[..., 0]
    y = forward_solve(L, b[..., None])
    return y[..., 0], (back_solve(L, y)[..., 0] if want_x else None)
