"""Robust Gauss–Newton for small geometric fits (ellipse parameters, circle and target poses).

Residuals come in groups (one per edge set); each group has its own noise scale, estimated from
its residuals by the median absolute deviation, and Huber weights (k = 1.345 σ) bound the pull
of outliers — iteratively reweighted least squares (Huber 1964; Holland & Welsch 1977). The
Jacobian is taken by forward differences on a parameter increment, which lets the caller keep
rotations and unit normals on their manifolds (the increment is applied by ``commit``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

_JACOBIAN_STEP = 1e-6
HUBER_K = 1.345


def robust_sigma(residuals: np.ndarray, floor: float = 0.05) -> float:
    """Noise scale of residuals: 1.4826 × median absolute deviation, at least ``floor``."""
    r = np.asarray(residuals, dtype=float)
    if len(r) == 0:
        return 1.0
    return float(max(1.4826 * np.median(np.abs(r - np.median(r))), floor))


def huber_weights(residuals: np.ndarray, sigma: float) -> np.ndarray:
    """Huber IRLS weights (1 inside k·σ, k·σ/|r| outside), divided by σ²."""
    a = np.abs(residuals) / (HUBER_K * sigma)
    return np.where(a <= 1.0, 1.0, 1.0 / np.maximum(a, 1e-12)) / sigma**2


@dataclass(frozen=True, slots=True, eq=False)
class Solution:
    """``information`` (JᵀWJ at the solution), the final residual groups, their noise scales,
    and the iteration count."""

    information: np.ndarray
    residuals: tuple[np.ndarray, ...]
    sigmas: tuple[float, ...]
    iterations: int


def gauss_newton(
    residuals: Callable[[np.ndarray], list[np.ndarray]],
    n_params: int,
    commit: Callable[[np.ndarray], None],
    *,
    iterations: int = 8,
    sigma_floor: float = 0.05,
    tolerance: float = 0.05,
    jacobian: Callable[[], np.ndarray] | None = None,
    group_weights: Sequence[float] | None = None,
    sigma_floors: Sequence[float] | None = None,
) -> Solution:
    """Minimise Σ_groups Σ ρ_Huber(r/σ_g) over a parameter increment.

    ``residuals(delta)`` returns the residual groups at the current state moved by ``delta``
    (without changing the state); ``commit(delta)`` moves the state. ``jacobian()``, when
    given, returns ∂r/∂delta at the current state (rows in group order); otherwise forward
    differences are used. Iterates until an increment is smaller than ``tolerance`` standard
    deviations (its Mahalanobis length under the current information), or ``iterations`` are
    done. ``group_weights`` scale each group's information (e.g. below 1 for samples that are
    not independent); ``sigma_floors`` replace ``sigma_floor`` per group (1 for residuals
    already whitened by a covariance that is trusted as a lower bound).
    """

    def noise_scales(groups: list[np.ndarray]) -> list[float]:
        floors = sigma_floors if sigma_floors is not None else [sigma_floor] * len(groups)
        return [robust_sigma(r, f) for r, f in zip(groups, floors, strict=True)]

    weights = list(group_weights) if group_weights is not None else None
    information = np.eye(n_params)
    sigmas: list[float] = []
    done = 0
    for _ in range(iterations):
        done += 1
        groups = residuals(np.zeros(n_params))
        flat = np.concatenate(groups) if groups else np.zeros(0)
        if len(flat) < n_params:
            break
        if jacobian is not None:
            J = jacobian()
        else:
            J = np.empty((len(flat), n_params))
            for j in range(n_params):
                step = np.zeros(n_params)
                step[j] = _JACOBIAN_STEP
                J[:, j] = (np.concatenate(residuals(step)) - flat) / _JACOBIAN_STEP
        sigmas = noise_scales(groups)
        w = np.concatenate(
            [
                huber_weights(r, s) * (1.0 if weights is None else weights[g])
                for g, (r, s) in enumerate(zip(groups, sigmas, strict=True))
            ]
        )
        information = J.T @ (J * w[:, None])
        gradient = J.T @ (w * flat)
        # A touch of Levenberg damping keeps nearly unobservable directions from exploding.
        damped = information + np.diag(np.diag(information)) * 1e-9 + np.eye(n_params) * 1e-12
        try:
            delta = -np.linalg.solve(damped, gradient)
        except np.linalg.LinAlgError:
            break
        if not np.all(np.isfinite(delta)):
            break
        commit(delta)
        if float(delta @ information @ delta) < tolerance**2:
            break
    groups = residuals(np.zeros(n_params))
    if not sigmas or len(sigmas) != len(groups):
        sigmas = noise_scales(groups)
    return Solution(information, tuple(groups), tuple(sigmas), done)


def marginal_covariance(information: np.ndarray, keep: int) -> np.ndarray:
    """Covariance of the first ``keep`` parameters: that block of the inverse information."""
    try:
        covariance = np.linalg.inv(information)
    except np.linalg.LinAlgError:
        covariance = np.linalg.pinv(information)
    covariance = covariance[:keep, :keep]
    return 0.5 * (covariance + covariance.T)
