"""The geometry of what the estimators track, in the target frame T (metres).

Built from the mock-up configuration (``configuration.mockup.MockupConfig.target_model``) so that the same
estimators track any square panel, point-feature layout or circular feature.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from estimators.geometry import Pose


def _frozen_vector(values: np.ndarray, size: int, name: str) -> np.ndarray:
    array = np.array(values, dtype=float).reshape(-1)
    if array.shape != (size,) or not np.all(np.isfinite(array)):
        raise ValueError(f"{name} must be {size} finite numbers; got {values!r}")
    array.flags.writeable = False
    return array


@dataclass(frozen=True, slots=True, eq=False)
class PointFeature:
    """A point feature: a panel corner, or the centre of a bolt head/hole disc.

    ``brighter`` says whether the feature is brighter than the surface around it. A disc's
    ``p_T`` is the centre of its top; ``height`` (m) is how far it stands proud of its surface
    (along T's z), so that its wall may show beside it.
    """

    name: str
    p_T: np.ndarray
    diameter: float
    kind: Literal["corner", "disc"]
    brighter: bool
    height: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "p_T", _frozen_vector(self.p_T, 3, f"{self.name}.p_T"))


@dataclass(frozen=True, slots=True, eq=False)
class Circle3D:
    """A circle of ``radius`` centred at ``center_T`` in the plane with unit normal ``normal_T``."""

    name: str
    center_T: np.ndarray
    normal_T: np.ndarray
    radius: float

    def __post_init__(self) -> None:
        object.__setattr__(
            self, "center_T", _frozen_vector(self.center_T, 3, f"{self.name}.center_T")
        )
        normal = _frozen_vector(self.normal_T, 3, f"{self.name}.normal_T")
        if abs(np.linalg.norm(normal) - 1.0) > 1e-9:
            raise ValueError(f"{self.name}.normal_T must be a unit vector")
        object.__setattr__(self, "normal_T", normal)
        if not self.radius > 0:
            raise ValueError(f"{self.name}.radius must be positive")


@dataclass(frozen=True, slots=True, eq=False)
class TargetModel:
    """Feature geometry of one mock-up.

    ``panel_corners_T`` (4,3): the square panel's front corners, counter-clockwise seen from +z,
    starting at (+x, +y). ``point_features`` lists the panel corners first, then the fasteners.
    ``circles``: ``ring_outer``, ``ring_inner`` and, when the mock-up has a thruster,
    ``thruster_exit`` and ``thruster_inner``. ``outline_corners_T`` (4,3), optional: the
    corners of the face the panel sits on (the mock-up's outline against the background), in
    the panel's corner order — a large, high-contrast rectangle that helps find the target.
    ``panel_thickness`` (m): how far the panel's front stands proud of the face behind it (its
    sides show beside its edges when seen from the side). ``ring_brighter``: whether the
    ring's front is brighter than the face around it (from the colours; None: not known).
    """

    name: str
    panel_corners_T: np.ndarray
    point_features: tuple[PointFeature, ...]
    circles: tuple[Circle3D, ...]
    outline_corners_T: np.ndarray | None = None
    panel_thickness: float = 0.0
    ring_brighter: bool | None = None

    def __post_init__(self) -> None:
        corners = np.array(self.panel_corners_T, dtype=float)
        if corners.shape != (4, 3):
            raise ValueError(f"panel_corners_T must be 4x3; got {corners.shape}")
        corners.flags.writeable = False
        object.__setattr__(self, "panel_corners_T", corners)
        if self.outline_corners_T is not None:
            outline = np.array(self.outline_corners_T, dtype=float)
            if outline.shape != (4, 3):
                raise ValueError(f"outline_corners_T must be 4x3; got {outline.shape}")
            outline.flags.writeable = False
            object.__setattr__(self, "outline_corners_T", outline)

    @property
    def panel_side(self) -> float:
        return float(np.linalg.norm(self.panel_corners_T[1] - self.panel_corners_T[0]))

    def circle(self, name: str) -> Circle3D:
        for c in self.circles:
            if c.name == name:
                return c
        raise KeyError(
            f"target {self.name!r} has no circle {name!r}; it has {[c.name for c in self.circles]}"
        )

    def has_circle(self, name: str) -> bool:
        return any(c.name == name for c in self.circles)

    @property
    def ring_foot(self) -> Circle3D | None:
        """Where the bore's wall meets the face behind the ring (``ring_foot``): the inner
        circle moved back to the face's plane (the outline's), or None when the model does not
        say where that is. Close up the wall shows as a band of its own, and the foot, not the
        ring's inner rim, is the edge the image holds (wall against face)."""
        return self._on_face("ring_inner", "ring_foot")

    @property
    def ring_outer_foot(self) -> Circle3D | None:
        """Where the ring's outer wall meets the face (``ring_outer_foot``): the outer circle
        moved back to the face's plane, or None as for ``ring_foot``. Seen obliquely the wall
        shows outside the ring's front on one side, and the edge found there lies between
        the rim and this foot."""
        return self._on_face("ring_outer", "ring_outer_foot")

    def _on_face(self, name: str, moved_name: str) -> Circle3D | None:
        """Circle ``name`` moved along its normal back to the face's plane, named
        ``moved_name``; None without such a circle, without the face's plane, or when the
        circle lies in that plane."""
        if not self.has_circle(name) or self.outline_corners_T is None:
            return None
        circle = self.circle(name)
        depth = float((self.outline_corners_T.mean(axis=0) - circle.center_T) @ circle.normal_T)
        if depth >= -1e-4:
            return None
        return Circle3D(
            moved_name, circle.center_T + depth * circle.normal_T, circle.normal_T, circle.radius
        )

    @property
    def bore_depth_m(self) -> float:
        """How far the ring's inner rim stands in front of its foot (0 without a foot)."""
        foot = self.ring_foot
        if foot is None:
            return 0.0
        return float((self.circle("ring_inner").center_T - foot.center_T) @ foot.normal_T)

    def points_T(self, kind: str | None = None) -> np.ndarray:
        """Positions (N,3) of the point features, optionally only of one kind."""
        return np.array([f.p_T for f in self.point_features if kind is None or f.kind == kind])


# --- the camera facing the target ---------------------------------------------------------

#: The camera's optical frame when it faces the target: image x along T's x, image up along
#: T's y, looking down T's −z (R_TC = diag(1, −1, −1)).
R_TC_FACING = np.diag([1.0, -1.0, -1.0])


def facing_camera(distance_m: float) -> Pose:
    """``X_TC`` of a camera on T's z axis, ``distance_m`` in front of the ring face, facing it."""
    if distance_m <= 0:
        raise ValueError(f"distance_m must be positive; got {distance_m}")
    return Pose(R_TC_FACING, np.array([0.0, 0.0, distance_m]))
