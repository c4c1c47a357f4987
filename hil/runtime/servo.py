"""Position-based visual servoing toward the stand-off pose (pure functions).

The camera is driven so that its pose error decays exponentially while it moves on a straight
line in the goal frame — the "t_c*c, θu" PBVS law (Chaumette & Hutchinson, "Visual servo
control, Part I: basic approaches", IEEE Robotics & Automation Magazine, 2006, §V):

    X_C*C = X_TC*⁻¹ · X_TC            (current camera C seen from the goal camera C*)
    v_C = −λ · R_C*Cᵀ · p_C*C,   ω_C = −λ · θu(R_C*C)

then saturated keeping its direction, speed-scheduled with range, acceleration-limited, and
split between the linear track (the along-track part of the closing motion) and the arm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from configuration.approach import ServoConfig
from estimators.geometry import Pose
from estimators.so3 import log_so3


@dataclass(frozen=True, slots=True)
class ServoLimits:
    """Limits of the commanded camera twist (m/s, rad/s, m/s², rad/s²)."""

    max_speed: float
    max_angular_speed: float
    max_acceleration: float
    max_angular_acceleration: float


@dataclass(frozen=True, slots=True)
class PoseError:
    """Camera pose error relative to the goal, expressed in the goal camera frame C*."""

    translation_m: np.ndarray  # p_C*C
    rotation_rad: np.ndarray  # θu of R_C*C

    @property
    def distance_m(self) -> float:
        return float(np.linalg.norm(self.translation_m))

    @property
    def angle_rad(self) -> float:
        return float(np.linalg.norm(self.rotation_rad))


def pose_error(X_TC: Pose, X_TC_goal: Pose) -> PoseError:
    """Error of the camera pose ``X_TC`` with respect to the goal ``X_TC_goal``."""
    X_goal_C = X_TC_goal.inverse() @ X_TC
    return PoseError(X_goal_C.p.copy(), log_so3(X_goal_C.R))


def pbvs_twist(X_TC: Pose, X_TC_goal: Pose, gain: float) -> np.ndarray:
    """Camera twist [v, ω] expressed in C that drives C to the goal (exponential decay)."""
    error = pose_error(X_TC, X_TC_goal)
    X_goal_C = X_TC_goal.inverse() @ X_TC
    v_C = -gain * (X_goal_C.R.T @ error.translation_m)
    w_C = -gain * error.rotation_rad
    return np.concatenate([v_C, w_C])


def goal_keeping_roll(X_TC: Pose, X_TC_goal: Pose) -> Pose:
    """The goal turned about T's z axis (the ring's) to the camera's present roll about it.

    Servoing to it brings the camera onto its place and its optical axis onto the goal's
    direction without turning about the ring's axis: for a target whose roll is not measured
    (only the ring seen, or a square panel with nothing to tell its quarter turns apart), where
    the estimate's roll is a guess the arm must not chase (issue 13). The roll is the turn about
    z_T that carries the goal's image x axis, projected on T's xy plane, onto the camera's."""

    def planar(x_T: np.ndarray) -> np.ndarray:
        return np.array([x_T[0], x_T[1], 0.0])

    goal_x, camera_x = planar(X_TC_goal.R[:, 0]), planar(X_TC.R[:, 0])
    if min(np.linalg.norm(goal_x), np.linalg.norm(camera_x)) < 1e-6:
        return X_TC_goal  # image x along the ring's axis: no roll to keep
    angle = math.atan2(float(np.cross(goal_x, camera_x)[2]), float(goal_x @ camera_x))
    c, s = math.cos(angle), math.sin(angle)
    R_z = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return Pose(R_z @ X_TC_goal.R, R_z @ X_TC_goal.p)


def saturate(twist: np.ndarray, max_speed: float, max_angular_speed: float) -> np.ndarray:
    """Scale the whole twist so that both parts are within their limits (direction kept)."""
    v, w = np.asarray(twist[:3], float), np.asarray(twist[3:], float)
    scale = 1.0
    speed, angular = np.linalg.norm(v), np.linalg.norm(w)
    if speed > max_speed:
        scale = min(scale, max_speed / speed)
    if angular > max_angular_speed:
        scale = min(scale, max_angular_speed / angular)
    return np.concatenate([v, w]) * scale


def limit_acceleration(
    twist: np.ndarray, previous: np.ndarray, dt: float, max_acc: float, max_angular_acc: float
) -> np.ndarray:
    """Move from ``previous`` toward ``twist`` by at most the acceleration limits over ``dt``,
    along the straight line between them (the change keeps its direction)."""
    delta = np.asarray(twist, float) - np.asarray(previous, float)
    return np.asarray(previous, float) + saturate(delta, max_acc * dt, max_angular_acc * dt)


def scheduled_speed(
    range_m: float, *, near_m: float, far_m: float, slow: float, fast: float
) -> float:
    """Speed limit growing linearly with range from ``slow`` (≤ near_m) to ``fast`` (≥ far_m)."""
    if far_m <= near_m:
        raise ValueError("scheduled_speed needs far_m > near_m")
    fraction = np.clip((range_m - near_m) / (far_m - near_m), 0.0, 1.0)
    return float(slow + fraction * (fast - slow))


def speed_limit(range_m: float, servo: ServoConfig) -> float:
    """The camera's speed limit (m/s) ``range_m`` from the ring face: ``slow_speed`` inside
    ``near_range_m`` (the slow-down distance), ``max_speed`` beyond ``far_range_m``, linear in
    between. The one schedule the sequencer proposes with and the supervisor enforces."""
    return scheduled_speed(
        range_m,
        near_m=servo.near_range_m,
        far_m=servo.far_range_m,
        slow=servo.slow_speed,
        fast=servo.max_speed,
    )


def limit_command(
    twist: np.ndarray,
    track_velocity: float,
    previous_twist: np.ndarray,
    previous_track_velocity: float,
    dt: float,
    servo: ServoConfig,
) -> tuple[np.ndarray, float]:
    """The camera twist and the track velocity one control period ``dt`` after the previous
    ones, changed by at most the servo's acceleration limits (the twist along the straight line
    between them, the track by ``max_acceleration``·dt)."""
    limited = limit_acceleration(
        twist,
        previous_twist,
        dt,
        servo.max_acceleration,
        math.radians(servo.max_angular_acceleration_deg),
    )
    step = servo.max_acceleration * dt
    track = float(
        np.clip(track_velocity, previous_track_velocity - step, previous_track_velocity + step)
    )
    return limited, track


def camera_twist_to_flange(twist_C: np.ndarray, X_BE: Pose, X_EC: Pose) -> np.ndarray:
    """The flange twist [v_E, ω] in B (UR speedL) that moves the camera with ``twist_C``.

    ω is shared by every point of the rigid body; the flange origin moves with
    v_E = v_C + ω × (p_BE − p_BC).
    """
    X_BC = X_BE @ X_EC
    w_B = X_BC.R @ twist_C[3:]
    v_C_B = X_BC.R @ twist_C[:3]
    v_E_B = v_C_B + np.cross(w_B, X_BE.p - X_BC.p)
    return np.concatenate([v_E_B, w_B])


def flange_twist_to_camera(V_BE: np.ndarray, X_BE: Pose, X_EC: Pose) -> np.ndarray:
    """Inverse of ``camera_twist_to_flange``: the camera twist in C for a flange twist in B."""
    X_BC = X_BE @ X_EC
    w_B = V_BE[3:]
    v_C_B = V_BE[:3] + np.cross(w_B, X_BC.p - X_BE.p)
    return np.concatenate([X_BC.R.T @ v_C_B, X_BC.R.T @ w_B])


@dataclass(frozen=True, slots=True)
class MotionSplit:
    """A relative camera motion shared between the track and the arm."""

    camera_twist_C: np.ndarray  # what the arm must do, camera twist in C
    track_velocity: float  # carriage velocity along the track axis (m/s)


def split_along_track(
    twist_C: np.ndarray, R_WC: np.ndarray, axis_W: np.ndarray, max_track_speed: float
) -> MotionSplit:
    """Give the along-track part of a desired camera-relative-to-target twist to the track.

    Moving the carriage (and target) with velocity u along ``axis_W`` moves the camera relative
    to the target by −u·axis. The along-track component of the desired relative velocity is
    taken by the track; if the track cannot go that fast the whole twist is scaled down so the
    camera still moves on its straight line, and the arm does the rest.
    """
    axis = np.asarray(axis_W, float) / np.linalg.norm(axis_W)
    v_W = R_WC @ twist_C[:3]
    along = float(v_W @ axis)
    scale = 1.0 if abs(along) <= max_track_speed else max_track_speed / abs(along)
    twist = np.asarray(twist_C, float) * scale
    v_W = R_WC @ twist[:3]
    along = float(v_W @ axis)
    arm_v_W = v_W - along * axis
    return MotionSplit(np.concatenate([R_WC.T @ arm_v_W, twist[3:]]), -along)
