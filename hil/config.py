"""Typed, validated configuration: cameras, the mock-up, lighting and image noise.

Every model is frozen and rejects unknown keys; load one with ``load_camera``, ``load_mockup``
(or ``hil.configfile.load_config`` for any model). Sizes are metres, angles in fields ending
``_deg`` are degrees, colours are linear RGB reflectances in [0, 1].

Mock-up geometry, in the target frame T (DESIGN.md): origin at the centre of the marman ring's
front (interface) face, z out of the face. The bus face lies at z = −ring.protrusion; the centre
panel sits on it inside the ring; the thruster stands on it outside the ring.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_serializer, model_validator

from estimators.frame import CameraInfo
from estimators.fusion import FusionParams
from estimators.geometry import Pose, check_distortion, intrinsics_from_fov
from estimators.target import R_TC_FACING, Circle3D, PointFeature, TargetModel
from hil.configfile import load_config, resolve_config_path

PositiveM = Annotated[float, Field(gt=0.0)]
Unit = Annotated[float, Field(ge=0.0, le=1.0)]
RGB = tuple[Unit, Unit, Unit]
XY = tuple[float, float]


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


def gray(color: RGB) -> float:
    """Luma (Rec. 601) of a linear RGB colour — what a mono camera sees."""
    return 0.299 * color[0] + 0.587 * color[1] + 0.114 * color[2]


# --- cameras --------------------------------------------------------------------------------


class CameraConfig(Strict):
    """A camera profile: resolution and either a horizontal FOV or explicit intrinsics."""

    name: str
    width: Annotated[int, Field(ge=16, le=8192)]
    height: Annotated[int, Field(ge=16, le=8192)]
    hfov_deg: Annotated[float, Field(gt=1.0, lt=179.0)] | None = None
    fx: PositiveM | None = None
    fy: PositiveM | None = None
    cx: float | None = None
    cy: float | None = None
    distortion: list[float] = Field(default_factory=list)
    channels: Literal[1, 3] = 1
    fps: Annotated[float, Field(gt=0.0)] = 30.0

    @model_validator(mode="after")
    def _intrinsics_given_once(self) -> CameraConfig:
        explicit = [self.fx, self.fy, self.cx, self.cy]
        if self.hfov_deg is None and any(v is None for v in explicit):
            raise ValueError("give either hfov_deg or all of fx, fy, cx, cy")
        if self.hfov_deg is not None and any(v is not None for v in explicit):
            raise ValueError("give either hfov_deg or fx/fy/cx/cy, not both")
        check_distortion(np.array(self.distortion))
        return self

    def camera_info(self) -> CameraInfo:
        if self.hfov_deg is not None:
            K = intrinsics_from_fov(self.width, self.height, self.hfov_deg)
        else:
            K = np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])
        return CameraInfo(
            width=self.width,
            height=self.height,
            K=K,
            dist=np.array(self.distortion, dtype=float),
            model=self.name,
            channels=self.channels,
        )


# --- the mock-up ----------------------------------------------------------------------------


class BusFace(Strict):
    """The satellite's front face: a box whose front is the plane z = −ring.protrusion."""

    width: PositiveM = 1.6
    height: PositiveM = 1.6
    depth: PositiveM = 0.4
    color: RGB = (0.45, 0.36, 0.20)


class MarmanRing(Strict):
    """Launch-adapter ring: an annulus standing ``protrusion`` proud of the bus face."""

    outer_diameter: PositiveM = 0.60
    radial_width: PositiveM = 0.05
    protrusion: PositiveM = 0.06
    color: RGB = (0.76, 0.76, 0.78)
    segments: Annotated[int, Field(ge=64, le=4096)] = 512

    @model_validator(mode="after")
    def _width_fits(self) -> MarmanRing:
        if self.radial_width >= self.outer_diameter / 2:
            raise ValueError(
                f"radial_width {self.radial_width} m must be less than the outer radius "
                f"{self.outer_diameter / 2} m"
            )
        return self

    @property
    def outer_radius(self) -> float:
        return self.outer_diameter / 2

    @property
    def inner_radius(self) -> float:
        return self.outer_diameter / 2 - self.radial_width


class CentrePanel(Strict):
    """A square plate on the bus face, centred on the ring axis, edges along T's x and y."""

    side: PositiveM = 0.30
    thickness: PositiveM = 0.008
    color: RGB = (0.66, 0.66, 0.66)


class CirclePattern(Strict):
    radius: PositiveM
    count: Annotated[int, Field(ge=1, le=256)]
    phase_deg: float = 0.0


class FastenerGroup(Strict):
    """Bolt heads or holes: small discs on a surface — point features for the corner system."""

    name: str
    surface: Literal["ring", "panel", "bus"]
    diameter: PositiveM
    height: Annotated[float, Field(gt=0.0, le=0.05)] = 0.0015
    color: RGB = (0.10, 0.10, 0.10)
    positions: list[XY] | None = None
    circle_pattern: CirclePattern | None = None

    @model_validator(mode="after")
    def _one_layout(self) -> FastenerGroup:
        if (self.positions is None) == (self.circle_pattern is None):
            raise ValueError("give exactly one of positions or circle_pattern")
        if self.positions is not None and len(self.positions) == 0:
            raise ValueError("positions is empty")
        return self

    def centers_xy(self) -> np.ndarray:
        if self.positions is not None:
            return np.array(self.positions, dtype=float).reshape(-1, 2)
        pattern = self.circle_pattern
        assert pattern is not None
        angles = (
            np.radians(pattern.phase_deg) + 2 * np.pi * np.arange(pattern.count) / pattern.count
        )
        return pattern.radius * np.column_stack([np.cos(angles), np.sin(angles)])


class Thruster(Strict):
    """A nozzle on the bus face; its exit rim is a circle off the ring axis (fixes roll)."""

    center: XY = (0.50, 0.42)
    exit_diameter: PositiveM = 0.12
    base_diameter: PositiveM = 0.07
    length: PositiveM = 0.10
    lip_width: PositiveM = 0.008
    color: RGB = (0.62, 0.60, 0.58)
    interior_color: RGB = (0.06, 0.06, 0.06)

    @model_validator(mode="after")
    def _sizes(self) -> Thruster:
        if self.lip_width >= self.exit_diameter / 2:
            raise ValueError("lip_width must be less than the exit radius")
        return self


class ModelFile(Strict):
    """The user's own URDF or OBJ export of the mock-up, used for rendering instead of the
    built-in geometry; ``xyz``/``rpy_deg`` place the file's frame in T (X_TF)."""

    path: Path
    xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale: PositiveM = 1.0

    @property
    def X_TF(self) -> Pose:
        return Pose.from_rpy(*np.radians(self.rpy_deg), np.array(self.xyz))


class MockupConfig(Strict):
    name: str
    bus_face: BusFace = BusFace()
    marman_ring: MarmanRing = MarmanRing()
    centre_panel: CentrePanel = CentrePanel()
    fasteners: list[FastenerGroup] = Field(default_factory=list)
    thruster: Thruster | None = Thruster()
    model_file: ModelFile | None = None

    @model_validator(mode="after")
    def _geometry_consistent(self) -> MockupConfig:
        ring, panel, face = self.marman_ring, self.centre_panel, self.bus_face
        if panel.side / math.sqrt(2) >= ring.inner_radius:
            raise ValueError(
                f"centre_panel.side {panel.side} m: the panel's corners must lie inside the "
                f"ring's inner radius {ring.inner_radius:.3f} m"
            )
        if panel.thickness >= ring.protrusion:
            raise ValueError("centre_panel.thickness must be less than marman_ring.protrusion")
        if ring.outer_radius > min(face.width, face.height) / 2:
            raise ValueError("marman_ring.outer_diameter exceeds the bus face")
        if self.thruster is not None:
            t = self.thruster
            cx, cy = t.center
            r_max = max(t.exit_diameter, t.base_diameter) / 2
            if abs(cx) + r_max > face.width / 2 or abs(cy) + r_max > face.height / 2:
                raise ValueError("thruster.center: the nozzle must stand on the bus face")
            if math.hypot(cx, cy) - r_max <= ring.outer_radius:
                raise ValueError("thruster.center: the nozzle overlaps the marman ring")
        for i, group in enumerate(self.fasteners):
            self._check_fastener_group(i, group)
        if sum(len(g.centers_xy()) for g in self.fasteners) < 8:
            raise ValueError("fasteners: at least 8 point features are needed")
        return self

    def _check_fastener_group(self, index: int, group: FastenerGroup) -> None:
        r = group.diameter / 2
        where = f"fasteners.{index} ({group.name})"
        for x, y in group.centers_xy():
            rho = math.hypot(x, y)
            if group.surface == "ring":
                ring = self.marman_ring
                ok = ring.inner_radius + r < rho < ring.outer_radius - r
            elif group.surface == "panel":
                ok = max(abs(x), abs(y)) + r < self.centre_panel.side / 2
            else:
                face = self.bus_face
                on_face = abs(x) + r < face.width / 2 and abs(y) + r < face.height / 2
                ok = on_face and rho - r > self.marman_ring.outer_radius
            if not ok:
                raise ValueError(
                    f"{where}: a fastener at ({x:.3f}, {y:.3f}) is off its {group.surface}"
                )

    # --- derived geometry in T ----------------------------------------------------------
    @property
    def z_bus(self) -> float:
        """z of the bus face's front plane in T."""
        return -self.marman_ring.protrusion

    def surface_z(self, surface: str) -> float:
        if surface == "ring":
            return 0.0
        if surface == "panel":
            return self.z_bus + self.centre_panel.thickness
        return self.z_bus

    def target_model(self) -> TargetModel:
        """The feature geometry the estimators track, derived from this mock-up."""
        ring, panel = self.marman_ring, self.centre_panel
        h = panel.side / 2
        z_panel = self.surface_z("panel")
        corners = np.array([[h, h, z_panel], [-h, h, z_panel], [-h, -h, z_panel], [h, -h, z_panel]])
        panel_gray = gray(panel.color)
        points = [
            PointFeature(
                f"panel_corner_{i}", c, 0.0, "corner", panel_gray > gray(self.bus_face.color)
            )
            for i, c in enumerate(corners)
        ]
        surface_color = {"ring": ring.color, "panel": panel.color, "bus": self.bus_face.color}
        for group in self.fasteners:
            z = self.surface_z(group.surface) + group.height
            brighter = gray(group.color) > gray(surface_color[group.surface])
            for i, (x, y) in enumerate(group.centers_xy()):
                points.append(
                    PointFeature(
                        f"{group.name}_{i}", np.array([x, y, z]), group.diameter, "disc", brighter
                    )
                )
        z_axis = np.array([0.0, 0.0, 1.0])
        circles = [
            Circle3D("ring_outer", np.zeros(3), z_axis, ring.outer_radius),
            Circle3D("ring_inner", np.zeros(3), z_axis, ring.inner_radius),
        ]
        if self.thruster is not None:
            t = self.thruster
            center = np.array([t.center[0], t.center[1], self.z_bus + t.length])
            circles.append(Circle3D("thruster_exit", center, z_axis, t.exit_diameter / 2))
            circles.append(
                Circle3D("thruster_inner", center, z_axis, t.exit_diameter / 2 - t.lip_width)
            )
        w, hh = self.bus_face.width / 2, self.bus_face.height / 2
        outline = np.array(
            [[w, hh, self.z_bus], [-w, hh, self.z_bus], [-w, -hh, self.z_bus], [w, -hh, self.z_bus]]
        )
        return TargetModel(
            name=self.name,
            panel_corners_T=corners,
            outline_corners_T=outline,
            point_features=tuple(points),
            circles=tuple(circles),
        )


# --- rendering ------------------------------------------------------------------------------


class Lighting(Strict):
    """Ambient + a sun-like directional light (Lambertian)."""

    ambient: Unit = 0.45
    diffuse: Unit = 0.55
    specular: Unit = 0.0
    #: Direction from the target toward the sun, in T (normalised on use).
    sun_direction_T: tuple[float, float, float] = (-0.25, 0.35, 1.0)
    shadows: bool = False


class NoiseConfig(Strict):
    """Image noise. ``preset`` gives the reference study's additive Gaussian levels
    (variance 0 / 0.05 / 0.1 on [0,1] intensities, clipped); ``sensor`` adds shot and read
    noise from a photon-transfer model instead."""

    preset: Literal["none", "low", "high", "sensor"] = "none"
    variance: Annotated[float, Field(ge=0.0, le=1.0)] | None = None
    full_well_e: Annotated[float, Field(gt=0.0)] = 10000.0
    read_noise_e: Annotated[float, Field(ge=0.0)] = 8.0
    motion_blur: bool = False
    exposure_s: Annotated[float, Field(ge=0.0, le=1.0)] = 0.008

    @property
    def gaussian_variance(self) -> float:
        """Variance of the additive Gaussian noise on [0, 1] intensities (0 for ``sensor``)."""
        if self.variance is not None:
            return self.variance
        return {"none": 0.0, "low": 0.05, "high": 0.1, "sensor": 0.0}[self.preset]


class RenderConfig(Strict):
    lighting: Lighting = Lighting()
    supersample: Annotated[int, Field(ge=1, le=4)] = 1
    near_m: PositiveM = 0.05
    far_m: PositiveM = 30.0


def load_camera(name_or_path: str | Path) -> CameraConfig:
    return load_config(name_or_path, CameraConfig, "cameras")


def load_mockup(name_or_path: str | Path) -> MockupConfig:
    """Load a mock-up by path or built-in name (``default`` is ``configs/mockup.yaml``).

    A relative ``model_file.path`` is taken relative to the YAML file that names it.
    """
    name = "mockup" if str(name_or_path) == "default" else name_or_path
    path = resolve_config_path(name)
    mockup = load_config(path, MockupConfig)
    model = mockup.model_file
    if model is not None and not model.path.is_absolute():
        model = model.model_copy(update={"path": (path.parent / model.path).resolve()})
        mockup = mockup.model_copy(update={"model_file": model})
    return mockup


# --- approach: stand-off, servo law, grasp, supervisor -----------------------------------------

XYZ = tuple[float, float, float]


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

    max_estimate_age_s: PositiveM = 0.25
    max_frame_age_s: PositiveM = 0.3
    max_tick_s: PositiveM = 0.05
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


# --- rig ------------------------------------------------------------------------------------
# The devices of the rig (configs/rig.yaml) and where they stand. Frames (DESIGN.md): W world
# (the floor), B arm base (UR's ``base``), E flange (``tool0``), C camera optical frame,
# M track carriage, T target (ring face, z out).

Vec3 = tuple[float, float, float]
Vec6 = tuple[float, float, float, float, float, float]
Positive = Annotated[float, Field(gt=0.0)]  # a positive quantity in the unit its name gives


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


# --- a simulated trial -----------------------------------------------------------------------


class StartConfig(Strict):
    """Randomised start of a simulated approach, as in the reference study: the camera
    ``distance_m`` in front of the ring face, up to ``max_offset_m`` off the ring axis
    (sideways and up/down) and turned up to ``max_rotation_deg`` about each of its axes; the
    mock-up sits on its carriage misaligned by up to ``mount_misalignment_deg``."""

    distance_m: PositiveM = 2.5
    max_offset_m: Annotated[float, Field(ge=0.0, le=1.0)] = 0.3
    max_rotation_deg: Annotated[float, Field(ge=0.0, le=30.0)] = 10.0
    mount_misalignment_deg: Annotated[float, Field(ge=0.0, le=10.0)] = 1.0


class SimulationConfig(Strict):
    """Everything a simulated trial needs (``configs/sim.yaml``). ``mockup``, ``camera`` and
    ``rig`` name built-in configurations or YAML files."""

    name: str
    mockup: str = "default"
    camera: str = "reference"
    rig: str = "rig"
    #: Estimators: corners, lines, ellipses (or a "module:factory" path for experiments).
    systems: list[str] = Field(default_factory=lambda: ["corners", "lines", "ellipses"])
    noise: NoiseConfig = NoiseConfig(preset="low")
    render: RenderConfig = RenderConfig()
    camera_fps: Annotated[float, Field(gt=0.0, le=120.0)] = 15.0
    #: How the track and gripper drivers reach their simulated devices: in-process register
    #: access ("direct") or a real pymodbus server on 127.0.0.1 ("tcp").
    links: Literal["direct", "tcp"] = "direct"
    fusion: FusionParams = Field(default_factory=FusionParams)
    approach: ApproachConfig = ApproachConfig()
    start: StartConfig = StartConfig()
    #: Capture range of the (compliant) gripper around the grasp pose, and the object's width.
    grasp_capture_m: PositiveM = 0.01
    grasp_capture_deg: Annotated[float, Field(gt=0.0, le=20.0)] = 3.0
    grasp_object_width_m: PositiveM = 0.05
    max_duration_s: PositiveM = 150.0
    #: Camera frames kept in the trial log (one every this many seconds; 0 keeps none).
    log_frames_every_s: Annotated[float, Field(ge=0.0)] = 1.0

    @field_serializer("fusion")
    def _fusion_as_dict(self, fusion: FusionParams) -> dict:
        values = {f.name: getattr(fusion, f.name) for f in dataclasses.fields(fusion)}
        values["covariance_scale"] = dict(fusion.covariance_scale)  # read-only mappings
        values["covariance_floor"] = {k: list(v) for k, v in fusion.covariance_floor.items()}
        return values

    @model_validator(mode="after")
    def _systems(self) -> SimulationConfig:
        if not self.systems:
            raise ValueError("systems: name at least one estimator")
        unknown = [
            s for s in self.systems if s not in ("corners", "lines", "ellipses") and ":" not in s
        ]
        if unknown:
            raise ValueError(
                f"systems: unknown estimator {unknown[0]!r} (corners, lines or ellipses)"
            )
        if len(set(self.systems)) != len(self.systems):
            raise ValueError("systems: each estimator at most once")
        return self


def load_simulation(name_or_path: str | Path = "sim") -> SimulationConfig:
    """Load a simulated-trial configuration (``sim`` is ``configs/sim.yaml``)."""
    return load_config(name_or_path, SimulationConfig)
