"""The approach: stand-off, servo law and its limits, grasp, and the supervisor's limits.

Every model is frozen and rejects unknown keys.
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
from pydantic import Field, model_validator

from configuration.base import XY, XYZ, PositiveM, Strict
from estimators.geometry import Pose
from estimators.target import R_TC_FACING


class StandoffConfig(Strict):
    """The pre-grasp stand-off: the camera ``distance_m`` in front of the ring face on the ring
    axis (shifted by ``offset_xy`` in T), optical axis along −z_T, image x along x_T."""

    distance_m: PositiveM = 0.5
    offset_xy: XY = (0.0, 0.0)
    position_tolerance_m: PositiveM = 0.003
    angle_tolerance_deg: Annotated[float, Field(gt=0.0, le=10.0)] = 0.3
    dwell_s: Annotated[float, Field(ge=0.0)] = 1.0
    #: A trial succeeds when the TRUE camera pose error at the declared stand-off is within these.
    success_position_m: PositiveM = 0.005
    success_angle_deg: Annotated[float, Field(gt=0.0, le=10.0)] = 0.5

    def X_TC_goal(self) -> Pose:
        return Pose(R_TC_FACING, np.array([self.offset_xy[0], self.offset_xy[1], self.distance_m]))


class ServoConfig(Strict):
    """PBVS gain and the limits of the commanded camera twist; speed is scheduled with range
    from ``slow_speed`` (at ≤ ``near_range_m``) up to ``max_speed`` (at ≥ ``far_range_m``)."""

    gain: Annotated[float, Field(gt=0.0, le=20.0)] = 0.8
    max_speed: PositiveM = 0.25
    slow_speed: PositiveM = 0.03
    max_angular_speed_deg: Annotated[float, Field(gt=0.0, le=180.0)] = 15.0
    max_acceleration: PositiveM = 0.4
    max_angular_acceleration_deg: Annotated[float, Field(gt=0.0, le=720.0)] = 40.0
    near_range_m: PositiveM = 0.6
    far_range_m: PositiveM = 1.8
    control_rate_hz: Annotated[float, Field(gt=1.0, le=1000.0)] = 125.0

    @model_validator(mode="after")
    def _ranges(self) -> ServoConfig:
        if self.far_range_m <= self.near_range_m:
            raise ValueError("far_range_m must be greater than near_range_m")
        if self.slow_speed > self.max_speed:
            raise ValueError("slow_speed must not exceed max_speed")
        return self


class GraspConfig(Strict):
    """The final guarded move along the optical axis, the grip, and the retreat."""

    advance_m: Annotated[float, Field(ge=0.0, le=0.4)] = 0.15
    speed: PositiveM = 0.03
    close_timeout_s: PositiveM = 3.0
    hold_s: Annotated[float, Field(ge=0.0)] = 0.5
    release_after_grasp: bool = True


class SupervisorConfig(Strict):
    """Checks run every tick; any failure stops the arm (and the track)."""

    #: Ages count from the frame's capture, latency included (see configs/sim.yaml).
    max_estimate_age_s: PositiveM = 0.4
    max_frame_age_s: PositiveM = 0.4
    #: A tick that starts this late, or whose work took this long, stops the arm (3 periods
    #: at 125 Hz: the arm would have run on its last twist for that long).
    max_tick_s: PositiveM = 0.024
    workspace_min_B: XYZ = (-1.4, -1.4, -0.2)
    workspace_max_B: XYZ = (1.4, 1.4, 1.6)
    approach_cone_deg: Annotated[float, Field(gt=0.0, lt=90.0)] = 30.0
    min_range_m: PositiveM = 0.25
    speed_margin: Annotated[float, Field(ge=1.0, le=3.0)] = 1.2
    stop_deceleration: PositiveM = 2.0
    reacquire: bool = True
    acquire_timeout_s: PositiveM = 15.0
    #: The estimate must stay healthy this long before the approach starts.
    lock_s: Annotated[float, Field(ge=0.0, le=10.0)] = 0.3


class ApproachConfig(Strict):
    standoff: StandoffConfig = StandoffConfig()
    servo: ServoConfig = ServoConfig()
    grasp: GraspConfig = GraspConfig()
    supervisor: SupervisorConfig = SupervisorConfig()

    @model_validator(mode="after")
    def _grasp_stays_outside_the_keep_out(self) -> ApproachConfig:
        closest = self.standoff.distance_m - self.grasp.advance_m
        if closest <= self.supervisor.min_range_m:
            raise ValueError(
                f"grasp.advance_m {self.grasp.advance_m} m brings the camera to {closest:.3f} m, "
                f"inside supervisor.min_range_m {self.supervisor.min_range_m} m"
            )
        return self
