"""SO(3): the exponential and logarithm maps and the left Jacobians, for rotation vectors in rad,
and the pose error these define.

The one home of these maps (STYLE.md, "one SO(3) module"). Conventions follow Solà, Deray &
Atchuthan 2018, "A micro Lie theory for state estimation in robotics": Exp(φ) is the rotation
by |φ| about φ/|φ|, and the left Jacobian J_l relates a perturbation of φ to a rotation applied
on the left, Exp(φ + δ) ≈ Exp(J_l(φ)·δ)·Exp(φ).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from estimators.geometry import Pose, skew


def exp_so3(phi: np.ndarray) -> np.ndarray:
    """Rotation matrix Exp(φ) of a rotation vector φ (rad), by Rodrigues' formula."""
    phi = np.asarray(phi, dtype=float)
    angle = math.sqrt(float(phi @ phi))
    W = skew(phi)
    if angle < 1e-8:
        return np.eye(3) + W + 0.5 * (W @ W)
    return np.eye(3) + math.sin(angle) / angle * W + (1.0 - math.cos(angle)) / angle**2 * (W @ W)


def log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation vector Log(R) (rad), the inverse of ``exp_so3`` (angle in [0, π])."""
    R = np.asarray(R, dtype=float)
    cos_angle = 0.5 * (float(np.trace(R)) - 1.0)
    if cos_angle < -0.99:  # near π the antisymmetric part vanishes: let scipy handle the axis
        return Rotation.from_matrix(R).as_rotvec()
    w = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    sin_angle = math.sqrt(float(w @ w))
    angle = math.atan2(sin_angle, min(cos_angle, 1.0))
    if angle < 1e-6:
        return w * (1.0 + angle * angle / 6.0)
    return w * (angle / sin_angle)


def so3_left_jacobian(phi: np.ndarray) -> np.ndarray:
    """Left Jacobian J_l(φ) of SO(3): Exp(φ + δ) ≈ Exp(J_l(φ)·δ)·Exp(φ) (Solà et al. 2018, (145))."""
    phi = np.asarray(phi, dtype=float)
    angle = float(np.linalg.norm(phi))
    W = skew(phi)
    if angle < 1e-6:
        return np.eye(3) + 0.5 * W + W @ W / 6.0
    return (
        np.eye(3)
        + (1.0 - math.cos(angle)) / angle**2 * W
        + (angle - math.sin(angle)) / angle**3 * (W @ W)
    )


def so3_left_jacobian_inverse(phi: np.ndarray) -> np.ndarray:
    """J_l(φ)⁻¹: Log(Exp(δ)·Exp(φ)) ≈ φ + J_l(φ)⁻¹·δ (Solà et al. 2018, (146))."""
    phi = np.asarray(phi, dtype=float)
    angle = float(np.linalg.norm(phi))
    W = skew(phi)
    if angle < 1e-6:
        return np.eye(3) - 0.5 * W + W @ W / 12.0
    coefficient = 1.0 / angle**2 - (1.0 + math.cos(angle)) / (2.0 * angle * math.sin(angle))
    return np.eye(3) - 0.5 * W + coefficient * (W @ W)


def pose_error_C(X_true: Pose, X_est: Pose) -> np.ndarray:
    """Error [δθ, δp] (6,) of a pose estimate in the Measurement convention:
    R_true = Exp(δθ)·R_est, p_true = p_est + δp (rad, m; in the frame both are expressed in) —
    the δ with ``X_true = planar_pose.retract(X_est, δ)``."""
    return np.concatenate([log_so3(X_true.R @ X_est.R.T), X_true.p - X_est.p])
