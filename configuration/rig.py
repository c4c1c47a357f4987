"""The devices of the rig (``configs/rig.yaml``) and where they stand. Frames (DESIGN.md):
W world (the floor), B arm base (UR's ``base``), E flange (``tool0``), C camera optical frame,
M track carriage, T target (ring face, z out).

Every model is frozen and rejects unknown keys.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import Field, model_validator

from configuration.base import Positive, PositiveM, Strict, Unit, Vec3, Vec6
from configuration.files import load_config
from estimators.geometry import Pose


class PoseConfig(Strict):
    """A rigid transform ``X_AB``: translation ``xyz`` (m) and ``rpy_deg`` (deg, about fixed
    x, y, z: R = Rz(yaw)·Ry(pitch)·Rx(roll), as ``Pose.from_rpy``)."""

    xyz: Vec3 = (0.0, 0.0, 0.0)
    rpy_deg: Vec3 = (0.0, 0.0, 0.0)

    @property
    def pose(self) -> Pose:
        return Pose.from_rpy(*np.radians(self.rpy_deg), np.array(self.xyz, dtype=float))


class ModbusEndpoint(Strict):
    """Where a Modbus TCP device answers: host, port, device (unit/slave) id, reply timeout."""

    host: str = "127.0.0.1"
    port: Annotated[int, Field(ge=1, le=65535)] = 502
    device_id: Annotated[int, Field(ge=0, le=247)] = 1
    timeout_s: Positive = 0.5


#: Joint ranges of every UR e-Series arm (deg): ±360 except the elbow, which the upper arm
#: physically stops at ±180.
UR_JOINT_RANGE_DEG = (360.0, 360.0, 180.0, 360.0, 360.0, 360.0)


class ArmConfig(Strict):
    """The arm: which UR model, where its base stands (``X_WB``), its start joints, the
    controller's limits and the hand-eye pose of the camera on the flange (``X_EC``)."""

    model: Literal["ur3e", "ur5e", "ur10e", "ur16e"] = "ur10e"
    X_WB: PoseConfig = PoseConfig()
    q0_deg: Vec6
    #: None: the model's published maximum joint speeds (a lower value caps them).
    joint_speed_limit_deg_s: (
        tuple[Positive, Positive, Positive, Positive, Positive, Positive] | None
    ) = None
    joint_acceleration_limit_deg_s2: Positive = 300.0
    #: Cap on the flange's linear speed (m/s); a faster command is scaled down, direction kept.
    tcp_speed_limit: Positive = 1.0
    #: Ramp of the commanded twist, like speedL's ``acc`` (m/s², and deg/s² for rotation).
    tcp_acceleration: Positive = 1.0
    tcp_angular_acceleration_deg_s2: Positive = 120.0
    #: Deceleration (m/s² and, numerically the same, rad/s²) of halts and the watchdog stop.
    stop_deceleration: Positive = 2.0
    joint_limit_margin_deg: Annotated[float, Field(ge=0.0, le=30.0)] = 5.0
    control_rate_hz: Annotated[float, Field(ge=10.0, le=2000.0)] = 500.0
    watchdog_s: Positive = 0.1
    #: Damped least squares: damping starts below this smallest singular value of J …
    singularity_sigma: Positive = 0.05
    #: … and reaches this damping factor at the singularity.
    damping_max: Positive = 0.05
    X_EC: PoseConfig = PoseConfig()

    @model_validator(mode="after")
    def _start_inside_limits(self) -> ArmConfig:
        for i, (q, limit) in enumerate(zip(self.q0_deg, UR_JOINT_RANGE_DEG, strict=True)):
            if abs(q) > limit - self.joint_limit_margin_deg:
                raise ValueError(
                    f"q0_deg[{i}] = {q}° is outside the joint range ±{limit}° less the "
                    f"{self.joint_limit_margin_deg}° margin"
                )
        return self


class TrackConfig(Strict):
    """The linear axis carrying the mock-up, its soft limits and dynamics, where its carriage
    is at position 0 (``X_WM0``), where the mock-up sits on it (``X_MT``), an optional slow
    drift/tumble of the mock-up on its mount, and its Modbus endpoint.

    Position s (m) moves the carriage along ``axis_W``: X_WM(s) = Translate(s·axis)·X_WM0.
    Drift: the mount slides at ``drift_velocity_M`` (m/s, in M) and the mock-up turns at
    ``drift_rate_deg_s`` about its own axes (deg/s, in T):
    X_MT(t) = Translate(v·t)·X_MT0·Rot(ω·t).
    """

    axis_W: Vec3 = (-1.0, 0.0, 0.0)
    travel_min: float = 0.0
    travel_max: float = 2.05
    start_position: float = 0.0
    max_speed: Positive = 0.25
    max_acceleration: Positive = 0.5
    position_tolerance: PositiveM = 0.0005
    X_WM0: PoseConfig = PoseConfig()
    X_MT: PoseConfig = PoseConfig()
    drift_velocity_M: Vec3 = (0.0, 0.0, 0.0)
    drift_rate_deg_s: Vec3 = (0.0, 0.0, 0.0)
    #: The device stops and faults when no Modbus request came for this long (0: off).
    watchdog_s: Annotated[float, Field(ge=0.0)] = 0.5
    control_rate_hz: Annotated[float, Field(ge=10.0, le=5000.0)] = 250.0
    modbus: ModbusEndpoint = ModbusEndpoint(port=5020, device_id=1)

    @model_validator(mode="after")
    def _consistent(self) -> TrackConfig:
        if np.linalg.norm(self.axis_W) < 1e-9:
            raise ValueError("axis_W must be a non-zero direction")
        if not self.travel_min < self.travel_max:
            raise ValueError(
                f"travel_min ({self.travel_min} m) must be less than travel_max ({self.travel_max} m)"
            )
        if not self.travel_min <= self.start_position <= self.travel_max:
            raise ValueError(
                f"start_position {self.start_position} m is outside the travel "
                f"[{self.travel_min}, {self.travel_max}] m"
            )
        return self

    @property
    def axis_unit_W(self) -> np.ndarray:
        axis = np.array(self.axis_W, dtype=float)
        return axis / np.linalg.norm(axis)


class GripperConfig(Strict):
    """A Robotiq 2F-85-style gripper: finger stroke (m), finger speed range (m/s) for rSP
    0…255, activation time, the width of the object between the fingers in simulation (None:
    nothing there), the driver's grip speed/force (0…1), and its Modbus endpoint."""

    stroke: PositiveM = 0.085
    max_speed: Positive = 0.15
    min_speed: Positive = 0.02
    activation_s: Positive = 0.5
    object_width: PositiveM | None = None
    grip_speed: Unit = 1.0
    grip_force: Unit = 0.5
    modbus: ModbusEndpoint = ModbusEndpoint(port=5021, device_id=9)

    @model_validator(mode="after")
    def _consistent(self) -> GripperConfig:
        if self.min_speed > self.max_speed:
            raise ValueError("min_speed must not exceed max_speed")
        if self.object_width is not None and self.object_width >= self.stroke:
            raise ValueError(
                f"object_width {self.object_width} m does not fit the stroke {self.stroke} m"
            )
        return self


class RigConfig(Strict):
    """The whole rig: arm with its camera, the track carrying the mock-up, the gripper."""

    name: str
    arm: ArmConfig
    track: TrackConfig
    gripper: GripperConfig = GripperConfig()

    @model_validator(mode="after")
    def _distinct_endpoints(self) -> RigConfig:
        track, gripper = self.track.modbus, self.gripper.modbus
        if (track.host, track.port, track.device_id) == (
            gripper.host,
            gripper.port,
            gripper.device_id,
        ):
            raise ValueError("track.modbus and gripper.modbus name the same device")
        return self


def load_rig(name_or_path: str | Path = "rig") -> RigConfig:
    """Load a rig by path or built-in name (``rig`` is ``configs/rig.yaml``)."""
    return load_config(name_or_path, RigConfig)
