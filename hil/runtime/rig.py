"""The fixed geometry of the rig, from its configuration: where the arm stands, where the camera
sits on the flange, how the track carries the mock-up, and the limits the supervisor keeps."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from configuration.rig import RigConfig
from estimators.geometry import Pose


@dataclass(frozen=True, slots=True, eq=False)
class RigGeometry:
    """Arm base ``X_WB``, hand-eye ``X_EC``, and the track: its unit axis in W, the carriage pose
    ``X_WM0`` at position 0, its speed limit (m/s); for the supervisor, the track's soft limits
    (m) and maximum acceleration (m/s², what it brakes at) and the arm's model (UR kinematics
    for the singularity margin; None: not known, that rule is not checked)."""

    X_WB: Pose
    X_EC: Pose
    track_axis_W: np.ndarray
    X_WM0: Pose
    max_track_speed: float
    travel_min: float = -math.inf
    travel_max: float = math.inf
    max_track_acceleration: float = math.inf
    arm_model: str | None = None

    @staticmethod
    def of(rig: RigConfig) -> RigGeometry:
        return RigGeometry(
            X_WB=rig.arm.X_WB.pose,
            X_EC=rig.arm.X_EC.pose,
            track_axis_W=rig.track.axis_unit_W,
            X_WM0=rig.track.X_WM0.pose,
            max_track_speed=rig.track.max_speed,
            travel_min=rig.track.travel_min,
            travel_max=rig.track.travel_max,
            max_track_acceleration=rig.track.max_acceleration,
            arm_model=rig.arm.model,
        )

    def X_WM(self, track_position: float) -> Pose:
        return Pose(self.X_WM0.R, self.X_WM0.p + track_position * self.track_axis_W)

    def X_WC(self, X_BE: Pose) -> Pose:
        return self.X_WB @ X_BE @ self.X_EC

    def X_CM(self, X_BE: Pose, track_position: float) -> Pose:
        """Pose of the carriage in the camera — what fusion needs to map X_MT to X_CT."""
        return self.X_WC(X_BE).inverse() @ self.X_WM(track_position)
