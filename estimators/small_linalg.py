"""Tiny dense arithmetic inside compiled per-pixel and per-point code, where a NumPy or LAPACK
call per feature would cost more than the arithmetic (and could not report a singular system
without raising): small solves, a rigid transform of one point, NumPy's maximum."""

from __future__ import annotations

import numpy as np

from estimators.compiled import compiled, compiled_inline


@compiled
def solve_small(H: np.ndarray, g: np.ndarray) -> np.ndarray:
    """H⁻¹·g for a small square H by Gaussian elimination with partial pivoting (NaN if
    singular)."""
    m = len(g)
    A = H.copy()
    x = g.copy()
    for col in range(m):
        pivot = col + np.argmax(np.abs(A[col:, col]))
        if A[pivot, col] == 0.0:
            return np.full(m, np.nan)
        if pivot != col:
            for j in range(m):
                A[col, j], A[pivot, j] = A[pivot, j], A[col, j]
            x[col], x[pivot] = x[pivot], x[col]
        for row in range(col + 1, m):
            f = A[row, col] / A[col, col]
            for j in range(col, m):
                A[row, j] -= f * A[col, j]
            x[row] -= f * x[col]
    for row in range(m - 1, -1, -1):
        acc = x[row]
        for j in range(row + 1, m):
            acc -= A[row, j] * x[j]
        x[row] = acc / A[row, row]
    return x


@compiled_inline
def rigid_transform(R: np.ndarray, p: np.ndarray, x: float, y: float, z: float):
    """R·(x, y, z) + p, as three scalars."""
    return (
        R[0, 0] * x + R[0, 1] * y + R[0, 2] * z + p[0],
        R[1, 0] * x + R[1, 1] * y + R[1, 2] * z + p[1],
        R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + p[2],
    )


@compiled_inline
def at_least(x: float, floor: float) -> float:
    """NumPy's maximum(x, floor): NaN stays NaN."""
    return x if x >= floor or x != x else floor
