"""Errors of a measurement against simulator ground truth (the only judge of accuracy)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from estimators.conics import circle_plane_basis
from estimators.geometry import (
    Pose,
    normal_angle,
    rotation_error_geodesic,
    rotation_error_rpy_norm,
    translation_error,
)
from estimators.measurement import Measurement
from estimators.target import TargetModel

NAN = float("nan")


@dataclass(frozen=True, slots=True)
class MeasurementError:
    """Errors of one measurement (NaN where it does not apply or nothing was estimated).

    6-DOF: ``translation_m`` (‖p_true − p_est‖), ``rotation_rad`` (norm of the roll/pitch/yaw
    of R_true·R_estᵀ, the reference's metric) and ``rotation_geodesic_rad``. 5-DOF: the circle's
    ``center_m`` and ``normal_rad``. When both exist, ``roll_rad`` is the 6-DOF rotation error
    about the circle's normal. ``nees_pose`` and ``nees_circle`` are the normalised estimation
    errors squared under the measurement's own covariances (χ² with 6 and 5 degrees of freedom
    when the covariances are honest). ``offset_C``: estimate minus truth (m, along the camera's
    x, y, z) of the target's origin (6-DOF) or else of the circle's centre — its mean over many
    frames is the estimator's bias.
    """

    translation_m: float = NAN
    rotation_rad: float = NAN
    rotation_geodesic_rad: float = NAN
    center_m: float = NAN
    normal_rad: float = NAN
    roll_rad: float = NAN
    nees_pose: float = NAN
    nees_circle: float = NAN
    offset_C: tuple[float, float, float] = (NAN, NAN, NAN)

    @property
    def position_m(self) -> float:
        """Translation error if 6-DOF, else the circle centre error."""
        return self.translation_m if not math.isnan(self.translation_m) else self.center_m

    @property
    def attitude_rad(self) -> float:
        """Rotation error if 6-DOF, else the normal error."""
        return self.rotation_rad if not math.isnan(self.rotation_rad) else self.normal_rad


def measurement_error(m: Measurement, X_CT_true: Pose, target: TargetModel) -> MeasurementError:
    """Errors of ``m`` given the true pose of the target in the camera."""
    if not m.valid:
        return MeasurementError()
    values: dict = {}
    if m.X_CT is not None:
        values["offset_C"] = tuple(float(v) for v in m.X_CT.p - X_CT_true.p)
        values["translation_m"] = translation_error(X_CT_true, m.X_CT)
        values["rotation_rad"] = rotation_error_rpy_norm(X_CT_true, m.X_CT)
        values["rotation_geodesic_rad"] = rotation_error_geodesic(X_CT_true, m.X_CT)
        values["nees_pose"] = pose_nees(m, X_CT_true)
    if m.center_C is not None and m.normal_C is not None and m.circle is not None:
        circle = target.circle(m.circle)
        center_true = X_CT_true.apply(circle.center_T)
        normal_true = X_CT_true.R @ circle.normal_T
        values["center_m"] = float(np.linalg.norm(m.center_C - center_true))
        values.setdefault("offset_C", tuple(float(v) for v in m.center_C - center_true))
        values["normal_rad"] = normal_angle(normal_true, m.normal_C)
        if m.covariance_5dof is not None:
            u, v = circle_plane_basis(m.normal_C)
            dn = normal_true - m.normal_C
            delta = np.concatenate([center_true - m.center_C, [dn @ u, dn @ v]])
            values["nees_circle"] = _nees(delta, m.covariance_5dof)
        if m.X_CT is not None:
            values["roll_rad"] = roll_error(X_CT_true, m.X_CT, circle.normal_T)
    return MeasurementError(**values)


def _nees(delta: np.ndarray, covariance: np.ndarray) -> float:
    try:
        return float(delta @ np.linalg.solve(covariance, delta))
    except np.linalg.LinAlgError:
        return math.inf


def pose_nees(m: Measurement, X_CT_true: Pose) -> float:
    """Normalised estimation error squared of a 6-DOF measurement: δᵀ·P⁻¹·δ with δ = [δθ, δp]
    the true pose's offset from the estimate in the measurement's convention (R_true =
    Exp(δθ)·R_est, p_true = p_est + δp). Its mean over many frames is 6 when the covariance is
    honest. NaN without a 6-DOF pose."""
    if not m.valid or m.X_CT is None or m.covariance is None:
        return NAN
    rotvec = Rotation.from_matrix(X_CT_true.R @ m.X_CT.R.T).as_rotvec()
    return _nees(np.concatenate([rotvec, X_CT_true.p - m.X_CT.p]), m.covariance)


def roll_error(X_CT_true: Pose, X_CT_est: Pose, axis_T: np.ndarray) -> float:
    """Rotation error (rad) about ``axis_T`` (e.g. a circle's normal): the twist part of the
    swing–twist decomposition of R_estᵀ·R_true."""
    R = X_CT_est.R.T @ X_CT_true.R
    w = np.sqrt(max(0.0, 1.0 + np.trace(R))) / 2.0
    if w < 1e-9:
        return math.pi
    vector = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / (4.0 * w)
    axis = np.asarray(axis_T, dtype=float) / np.linalg.norm(axis_T)
    return abs(2.0 * math.atan2(float(vector @ axis), w))
