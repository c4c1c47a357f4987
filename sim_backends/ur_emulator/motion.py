"""Position commands (servoL, moveL) turned into flange twists for the twist-driven arm model.

The emulated controller moves the arm only through ``SimArm``'s speedL semantics, so every
command drives the same kinematics, limits and singularity handling. Position commands become
twists here:

* servoL: first-order tracking of the newest target, ``V = e / τ`` with e = [Δp, Δθ] the pose
  error in B and τ the command's ``lookahead_time`` — UR documents that the lookahead smooths the
  trajectory and that servoL lags the target by about that time; UR's ``gain`` is accepted
  and logged but not modelled;
* moveL: a trapezoidal speed profile with equal thirds (Biagiotti & Melchiorri, "Trajectory
  Planning for Automatic Machines and Robots", 2008, §3.2) along the straight line and the
  rotation axis from the start pose, tracked with feedforward plus a proportional correction.

These run every 2 ms period, so they take 4×4 matrices ``T_BE`` (what ``SimArm.T_BE`` gives)
rather than building ``Pose`` objects.
"""

from __future__ import annotations

import math

import numpy as np

from estimators.so3 import exp_so3, log_so3

#: Time constant (s) of the proportional correction around a moveL reference.
MOVE_TRACKING_TIME_S = 0.05


def pose_error_matrix(T_current: np.ndarray, T_target: np.ndarray) -> np.ndarray:
    """[Δp, Δθ] in B taking ``T_current`` to ``T_target``: ``ur_kinematics.pose_error`` on
    4×4 matrices, with the SO(3) log of ``estimators.so3`` (~10× faster than scipy's ``Rotation``)."""
    dtheta = log_so3(T_target[:3, :3] @ T_current[:3, :3].T)
    return np.concatenate([T_target[:3, 3] - T_current[:3, 3], dtheta])


def servo_twist(T_BE: np.ndarray, T_BE_target: np.ndarray, time_constant_s: float) -> np.ndarray:
    """Twist [v, ω] in B that closes the pose error with time constant ``time_constant_s``."""
    return pose_error_matrix(T_BE, T_BE_target) / max(time_constant_s, 1e-3)


def trapezoid(distance: float, duration: float, t: float) -> tuple[float, float]:
    """Position and speed at ``t`` of the symmetric trapezoid covering ``distance`` from rest to
    rest in ``duration``, its acceleration, cruise and deceleration phases a third each (so the
    cruise speed is 1.5·D/T and the acceleration 4.5·D/T²)."""
    if duration <= 0 or distance <= 0:
        return distance, 0.0
    t = min(max(t, 0.0), duration)
    ramp = duration / 3.0
    cruise = distance / (duration - ramp)
    acceleration = cruise / ramp
    if t < ramp:
        return 0.5 * acceleration * t * t, acceleration * t
    if t <= duration - ramp:
        return 0.5 * acceleration * ramp * ramp + cruise * (t - ramp), cruise
    remaining = duration - t
    return distance - 0.5 * acceleration * remaining * remaining, acceleration * remaining


class LinearMove:
    """moveL's reference: from ``T_start`` to ``T_goal`` in a straight line (and about one
    rotation axis) with a trapezoidal profile whose speed and acceleration stay within
    ``speed`` (m/s; rad/s for the rotation) and ``acceleration`` (m/s²; rad/s²)."""

    def __init__(self, T_start: np.ndarray, T_goal: np.ndarray, speed: float, acceleration: float):
        if not (speed > 0 and acceleration > 0):
            raise ValueError(f"moveL needs speed and acceleration > 0; got {speed}, {acceleration}")
        self.T_start = np.array(T_start, dtype=float)
        self.T_goal = np.array(T_goal, dtype=float)
        self._dp = self.T_goal[:3, 3] - self.T_start[:3, 3]
        self._dtheta = pose_error_matrix(self.T_start, self.T_goal)[3:]
        # one profile for both: the duration that keeps the longer one within the limits
        lengths = (float(np.linalg.norm(self._dp)), float(np.linalg.norm(self._dtheta)))
        self.duration = max(
            max(1.5 * d / speed, math.sqrt(4.5 * d / acceleration)) for d in lengths
        )

    def reference(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(T_BE_ref, feedforward twist [v, ω] in B) at ``t`` seconds after the start."""
        s, s_dot = trapezoid(1.0, self.duration, t) if self.duration > 0 else (1.0, 0.0)
        T_ref = np.eye(4)
        T_ref[:3, :3] = exp_so3(s * self._dtheta) @ self.T_start[:3, :3]
        T_ref[:3, 3] = self.T_start[:3, 3] + s * self._dp
        return T_ref, s_dot * np.concatenate([self._dp, self._dtheta])

    def twist(self, T_BE: np.ndarray, t: float) -> np.ndarray:
        """Feedforward plus a proportional correction toward the reference at ``t``."""
        T_ref, V_ff = self.reference(t)
        return V_ff + pose_error_matrix(T_BE, T_ref) / MOVE_TRACKING_TIME_S
