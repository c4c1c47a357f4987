"""Standard viewpoints of the reference study: a camera square in front of the target, and the
target's maneuvers (±10 cm along x, y, z; 10° about x, y, z) as smooth motions over a sequence.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimators.geometry import Pose
from estimators.target import facing_camera


def target_offset(
    dx: float = 0.0,
    dy: float = 0.0,
    dz: float = 0.0,
    roll: float = 0.0,
    pitch: float = 0.0,
    yaw: float = 0.0,
) -> Pose:
    """``X_T0T``: the target displaced (m) and rotated (rad, about its own x, y, z) from its
    nominal pose T0."""
    return Pose.from_rpy(roll, pitch, yaw, np.array([dx, dy, dz]))


def camera_pose_for(distance_m: float, offset: Pose) -> tuple[Pose, Pose]:
    """(``X_WC``, ``X_CT``) with the target at the world origin (X_WT = I) moved by ``offset``
    from its nominal pose in front of a camera at ``distance_m``."""
    X_CT = facing_camera(distance_m).inverse() @ offset
    return X_CT.inverse(), X_CT


@dataclass(frozen=True, slots=True)
class Maneuver:
    """A target motion of the reference study, run as a sine over a sequence of frames."""

    name: str
    axis: int  # 0..2 translation x, y, z; 3..5 rotation about x, y, z; -1 none
    amplitude: float  # m or rad

    def offset(self, phase: float) -> Pose:
        """Target offset at ``phase`` in [0, 1] through the sequence (one full sine period)."""
        values = np.zeros(6)
        if self.axis >= 0:
            values[self.axis] = self.amplitude * np.sin(2.0 * np.pi * phase)
        return target_offset(*values)


MANEUVERS: tuple[Maneuver, ...] = (
    Maneuver("none", -1, 0.0),
    Maneuver("move_x_10cm", 0, 0.10),
    Maneuver("move_y_10cm", 1, 0.10),
    Maneuver("move_z_10cm", 2, 0.10),
    Maneuver("turn_x_10deg", 3, np.radians(10.0)),
    Maneuver("turn_y_10deg", 4, np.radians(10.0)),
    Maneuver("turn_z_10deg", 5, np.radians(10.0)),
)

#: Distances (m) of the reference study: far, close, near (grasping).
REFERENCE_DISTANCES_M: tuple[float, ...] = (3.0, 2.0, 1.2)
