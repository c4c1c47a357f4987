"""The randomised start of a simulated approach, as in the reference study: where the camera
begins relative to the mock-up, how the mock-up sits on its carriage, and the arm's joints."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from configuration.rig import PoseConfig, RigConfig
from configuration.simulation import StartConfig
from drivers.ur_kinematics import solve_ik, ur_model
from estimators.geometry import Pose
from estimators.target import facing_camera


def _pose_config(pose: Pose) -> PoseConfig:
    rpy = np.degrees(Rotation.from_matrix(pose.R).as_euler("xyz"))
    return PoseConfig(xyz=tuple(pose.p.tolist()), rpy_deg=tuple(rpy.tolist()))


@dataclass(frozen=True, slots=True)
class TrialStart:
    """A sampled start: the rig with the mock-up's sampled mount misalignment, the arm's start
    joints (rad) and the camera's start pose relative to the target."""

    rig: RigConfig
    start_q: np.ndarray
    X_TC: Pose


def sample_start(start: StartConfig, rig: RigConfig, rng: np.random.Generator) -> TrialStart:
    """The camera ``distance_m`` from the face, off-centre by up to ``max_offset_m`` and turned by
    up to ``max_rotation_deg`` about each axis; the mock-up misaligned on its carriage by up to
    ``mount_misalignment_deg``. The joints come from inverse kinematics continued from the rig's
    start joints."""
    tilt = np.radians(rng.uniform(-start.mount_misalignment_deg, start.mount_misalignment_deg, 3))
    X_MT = rig.track.X_MT.pose @ Pose.from_rotvec(tilt, np.zeros(3))
    rig = rig.model_copy(
        update={"track": rig.track.model_copy(update={"X_MT": _pose_config(X_MT)})}
    )
    dx, dy = rng.uniform(-start.max_offset_m, start.max_offset_m, 2)
    rpy = np.radians(rng.uniform(-start.max_rotation_deg, start.max_rotation_deg, 3))
    X_TC = (
        Pose(np.eye(3), np.array([dx, dy, 0.0]))
        @ facing_camera(start.distance_m)
        @ Pose.from_rpy(*rpy, np.zeros(3))
    )
    track = rig.track
    X_WM = Pose(track.X_WM0.pose.R, track.X_WM0.pose.p + track.start_position * track.axis_unit_W)
    X_WT = X_WM @ X_MT
    X_BE = rig.arm.X_WB.pose.inverse() @ X_WT @ X_TC @ rig.arm.X_EC.pose.inverse()
    q, converged = solve_ik(ur_model(rig.arm.model), X_BE, np.radians(rig.arm.q0_deg))
    if not converged:
        raise ValueError(f"start pose out of the arm's reach (offset {dx:.2f}, {dy:.2f} m)")
    return TrialStart(rig, q, X_TC)
