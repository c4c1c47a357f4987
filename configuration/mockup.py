"""The satellite mock-up (``configs/mockup*.yaml``) and the feature geometry derived from it.

Mock-up geometry, in the target frame T (DESIGN.md): origin at the centre of the marman ring's
front (interface) face, z out of the face. The bus face lies at z = −ring.protrusion; the centre
panel sits on it inside the ring (centred on the ring's axis, or off it); the thruster stands on
it outside the ring; fasteners and markers (small discs) sit on the ring, the panel or anywhere
on the bus face — inside the ring too — where nothing else stands. Sizes are metres, colours
linear RGB reflectances in [0, 1]; what the estimators expect to see (which part is brighter
than which) is derived from the colours, never assumed.

Every model is frozen and rejects unknown keys.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import Field, model_validator

from configuration.base import RGB, XY, PositiveM, Strict
from configuration.files import load_config, relative_to_file, resolve_config_path
from estimators.geometry import Pose
from estimators.target import Circle3D, PointFeature, TargetModel


def gray(color: RGB) -> float:
    """Luma (Rec. 601) of a linear RGB colour — what a mono camera sees."""
    return 0.299 * color[0] + 0.587 * color[1] + 0.114 * color[2]


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
    """A square plate on the bus face inside the ring, edges along T's x and y, its centre at
    ``center`` (x, y) — on the ring's axis by default; off it, it breaks the mock-up's
    four-fold symmetry."""

    side: PositiveM = 0.30
    thickness: PositiveM = 0.008
    color: RGB = (0.66, 0.66, 0.66)
    center: XY = (0.0, 0.0)

    def contains(self, x: float, y: float, margin: float = 0.0) -> bool:
        """Whether (x, y) lies on the panel at least ``margin`` inside its edges."""
        cx, cy = self.center
        return max(abs(x - cx), abs(y - cy)) + margin < self.side / 2


class CirclePattern(Strict):
    radius: PositiveM
    count: Annotated[int, Field(ge=1, le=256)]
    phase_deg: float = 0.0


class FastenerGroup(Strict):
    """Bolt heads, holes or painted markers: small discs on a surface — point features for the
    corner system (and, on the ring's face, for the ellipse system). On ``bus`` they may stand
    anywhere on the face that the ring, the panel and the thruster leave free, inside the ring
    included. ``height``: how far the disc stands proud of its surface (a marker: a fraction of
    a millimetre)."""

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
        h = panel.side / 2
        cx, cy = panel.center
        if max(math.hypot(cx + sx * h, cy + sy * h) for sx in (-1, 1) for sy in (-1, 1)) >= (
            ring.inner_radius
        ):
            raise ValueError(
                f"centre_panel.side {panel.side} m at {panel.center}: the panel's corners must "
                f"lie inside the ring's inner radius {ring.inner_radius:.3f} m"
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
        self._check_fasteners_apart()
        if sum(len(g.centers_xy()) for g in self.fasteners) < 8:
            raise ValueError("fasteners: at least 8 point features are needed")
        return self

    def _check_fastener_group(self, index: int, group: FastenerGroup) -> None:
        r = group.diameter / 2
        where = f"fasteners.{index} ({group.name})"
        ring, panel = self.marman_ring, self.centre_panel
        for x, y in group.centers_xy():
            rho = math.hypot(x, y)
            if group.surface == "ring":
                ok = ring.inner_radius + r < rho < ring.outer_radius - r
                problem = "off its ring"
            elif group.surface == "panel":
                ok = panel.contains(x, y, r)
                problem = "off its panel"
            else:
                face = self.bus_face
                on_face = abs(x) + r < face.width / 2 and abs(y) + r < face.height / 2
                # Free face: inside the ring's bore or outside it, never under the panel or
                # the thruster.
                free = rho + r < ring.inner_radius or rho - r > ring.outer_radius
                free &= not panel.contains(x, y, -r)
                if self.thruster is not None:
                    t = self.thruster
                    reach = max(t.exit_diameter, t.base_diameter) / 2 + r
                    free &= math.hypot(x - t.center[0], y - t.center[1]) > reach
                ok = on_face and free
                problem = (
                    "off its bus" if not on_face else "on the bus under the ring, panel or thruster"
                )
            if not ok:
                raise ValueError(f"{where}: a fastener at ({x:.3f}, {y:.3f}) is {problem}")

    def _check_fasteners_apart(self) -> None:
        """Two fasteners on one surface must not overlap (they would image as one blob)."""
        placed: list[tuple[str, float, float, float, str]] = []
        for i, group in enumerate(self.fasteners):
            for x, y in group.centers_xy():
                for other, ox, oy, o_r, surface in placed:
                    if surface == group.surface and math.hypot(x - ox, y - oy) < (
                        group.diameter / 2 + o_r
                    ):
                        raise ValueError(
                            f"fasteners.{i} ({group.name}): a fastener at ({x:.3f}, {y:.3f}) "
                            f"overlaps one of {other}"
                        )
                placed.append((group.name, x, y, group.diameter / 2, group.surface))

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
        cx, cy = panel.center
        corners = np.array(
            [
                [cx + h, cy + h, z_panel],
                [cx - h, cy + h, z_panel],
                [cx - h, cy - h, z_panel],
                [cx + h, cy - h, z_panel],
            ]
        )
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
                        f"{group.name}_{i}",
                        np.array([x, y, z]),
                        group.diameter,
                        "disc",
                        brighter,
                        group.height,
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
            panel_thickness=panel.thickness,
            ring_brighter=gray(ring.color) > gray(self.bus_face.color),
        )


def load_mockup(name_or_path: str | Path) -> MockupConfig:
    """Load a mock-up by path or built-in name (``default`` is ``configs/mockup.yaml``;
    ``random:SEED`` is ``configuration.random_mockup.random_mockup(SEED)``).

    A relative ``model_file.path`` is taken relative to the YAML file that names it.
    """
    if str(name_or_path).startswith("random:"):
        from configuration.random_mockup import random_mockup, seed_of

        return random_mockup(seed_of(str(name_or_path)))
    name = "mockup" if str(name_or_path) == "default" else name_or_path
    path = resolve_config_path(name)
    mockup = load_config(path, MockupConfig)
    model = mockup.model_file
    if model is not None and not model.path.is_absolute():
        model = model.model_copy(update={"path": relative_to_file(model.path, path)})
        mockup = mockup.model_copy(update={"model_file": model})
    return mockup
