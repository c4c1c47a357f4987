"""Typed, validated configuration: cameras, the mock-up, lighting and image noise.

Every model is frozen and rejects unknown keys; load one with ``load_camera``, ``load_mockup``
(or ``hil.configfile.load_config`` for any model). Sizes are metres, angles in fields ending
``_deg`` are degrees, colours are linear RGB reflectances in [0, 1].

Mock-up geometry, in the target frame T (DESIGN.md): origin at the centre of the marman ring's
front (interface) face, z out of the face. The bus face lies at z = −ring.protrusion; the centre
panel sits on it inside the ring; the thruster stands on it outside the ring.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from drivers.base import CameraInfo
from estimators.geometry import Pose, check_distortion, intrinsics_from_fov
from estimators.target import Circle3D, PointFeature, TargetModel
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
