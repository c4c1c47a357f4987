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
    #: The fused roll about the ring's axis counts as measured while its 1σ is below this. A
    #: track that saw only the ring — or a square panel with nothing in view to tell its
    #: quarter turns apart — holds a roll it guessed (σ ≈ 57°): the arm then servoes without
    #: turning about the ring's axis, the stand-off waits for the roll up to the supervisor's
    #: ``acquire_timeout_s``, and the grasp is refused if it does not come.
    max_roll_sigma_deg: Annotated[float, Field(gt=0.0, le=45.0)] = 2.0


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
    #: Margin on speed limits: the commanded flange and track speeds against the servo's and
    #: the track's maxima, and the camera's speed against the range schedule
    #: (``hil.runtime.servo.speed_limit``); the flange moves faster than the camera when turning.
    speed_margin: Annotated[float, Field(ge=1.0, le=3.0)] = 1.2
    #: Margin on the commanded accelerations (against the previous command, over one period)
    #: over the servo's limits: the limits hold for the camera twist in C, and the flange's twist
    #: in B also changes as the camera turns (ω × v, ≈ 0.07 m/s² at 15°/s and 0.25 m/s).
    acceleration_margin: Annotated[float, Field(ge=1.0, le=5.0)] = 1.5
    #: Measured accelerations (between successive states): above what a stop brakes at
    #: (``stop_deceleration``: 2 m/s² and 2 rad/s² = 115°/s²), below a collision or a runaway.
    max_measured_acceleration: PositiveM = 2.5
    max_measured_angular_acceleration_deg: Annotated[float, Field(gt=0.0)] = 150.0
    stop_deceleration: PositiveM = 2.0
    #: The track must be able to stop, braking at its maximum acceleration, this far inside its
    #: soft limits — checked on the measured and on the commanded velocity, one period ahead.
    track_limit_margin_m: Annotated[float, Field(ge=0.0)] = 0.005
    #: The flange may turn this far about each of its start axes (the components of the rotation
    #: vector of R_E0ᵀ·R_E, E0 the flange at the trial's start). The rig allows ±10° about its
    #: nominal pose; a random start turns the camera by up to 10° about each axis and the mount
    #: is off by up to 1°, so undoing it takes up to 10.7° about one axis (200 sampled starts).
    max_flange_rotation_deg: Annotated[float, Field(gt=0.0, le=90.0)] = 12.0
    #: Stop this far inside each joint's range (the simulated arm brakes at the rig's
    #: ``joint_limit_margin_deg``, 5°: the supervisor acts first).
    joint_margin_deg: Annotated[float, Field(ge=0.0, le=60.0)] = 10.0
    #: Stop when the smallest singular value of the arm's Jacobian falls below this (the rig's
    #: approach keeps it ≥ 0.26; the simulated arm's damping starts at 0.05).
    min_singular_value: Annotated[float, Field(ge=0.0)] = 0.1
    #: The fused estimate's angular rate of the target: above this the arm and the track hold
    #: still; still above it after ``target_rate_abort_s`` the trial aborts. A mock-up on its
    #: mount shows ≈ 0.2°/s of estimate noise; a tumbling one is never chased.
    max_target_rate_deg_s: Annotated[float, Field(gt=0.0)] = 1.0
    target_rate_abort_s: Annotated[float, Field(ge=0.0)] = 3.0
    #: Contact: the wrench the arm reports at the TCP (N, N·m), where it reports one.
    max_contact_force: PositiveM = 30.0
    max_contact_torque: PositiveM = 5.0
    #: The arm's own base is never part of the workspace: the flange stays out of this vertical
    #: cylinder about the base's z axis (radius, and height above the base).
    base_keepout_radius_m: Annotated[float, Field(ge=0.0)] = 0.3
    base_keepout_height_m: Annotated[float, Field(ge=0.0)] = 0.6
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
    def _grasp_within_the_slow_speed(self) -> ApproachConfig:
        # The guarded advance runs inside the slow-down distance when the stand-off is inside
        # it; the supervisor holds the camera to the range schedule there.
        servo = self.servo
        near = self.standoff.distance_m <= servo.near_range_m
        if near and self.grasp.speed > servo.slow_speed:
            raise ValueError(
                f"grasp.speed {self.grasp.speed} m/s exceeds servo.slow_speed "
                f"{servo.slow_speed} m/s, the limit inside the slow-down distance"
            )
        return self

    @model_validator(mode="after")
    def _grasp_stays_outside_the_keep_out(self) -> ApproachConfig:
        closest = self.standoff.distance_m - self.grasp.advance_m
        if closest <= self.supervisor.min_range_m:
            raise ValueError(
                f"grasp.advance_m {self.grasp.advance_m} m brings the camera to {closest:.3f} m, "
                f"inside supervisor.min_range_m {self.supervisor.min_range_m} m"
            )
        return self
