"""The mock-up as a pybullet scene, built from its configuration or the user's URDF/OBJ export.

Each scene owns a private pybullet client in DIRECT mode (no shared global state) and places the
mock-up at ``X_WT`` in the world frame W; ``set_pose`` moves it (the linear track does).
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from configuration.mockup import MockupConfig
from estimators.geometry import Pose
from sim_backends import meshes
from sim_backends.bullet import connect_direct, pybullet, silenced_fds
from sim_backends.meshes import Mesh


@dataclass(frozen=True, slots=True)
class _Part:
    """One rigid visual part: a mesh, or a box of ``half_extents`` centred on ``center_T``."""

    name: str
    mesh: Mesh | None  # None for primitive boxes
    half_extents: tuple[float, float, float] | None
    center_T: tuple[float, float, float]
    color: tuple[float, float, float]


def mockup_parts(mockup: MockupConfig) -> list[_Part]:
    """The mock-up's visual parts, in T, from its configuration (pure; no pybullet)."""
    face, ring, panel = mockup.bus_face, mockup.marman_ring, mockup.centre_panel
    z_bus = mockup.z_bus
    n = ring.segments
    parts = [
        _Part(
            "bus_face",
            None,
            (face.width / 2, face.height / 2, face.depth / 2),
            (0.0, 0.0, z_bus - face.depth / 2),
            face.color,
        ),
        _Part(
            "centre_panel",
            None,
            (panel.side / 2, panel.side / 2, panel.thickness / 2),
            (*panel.center, z_bus + panel.thickness / 2),
            panel.color,
        ),
        _Part(
            "marman_ring",
            Mesh.merge(
                meshes.annulus(ring.inner_radius, ring.outer_radius, 0.0, n),
                meshes.frustum_wall(ring.outer_radius, z_bus, ring.outer_radius, 0.0, n),
                meshes.frustum_wall(
                    ring.inner_radius, z_bus, ring.inner_radius, 0.0, n, outward=False
                ),
            ),
            None,
            (0.0, 0.0, 0.0),
            ring.color,
        ),
    ]
    if mockup.thruster is not None:
        t = mockup.thruster
        r_exit, r_base = t.exit_diameter / 2, t.base_diameter / 2
        r_in = r_exit - t.lip_width
        z_exit = z_bus + t.length
        z_floor = z_bus + 0.2 * t.length
        cx, cy = t.center
        n_t = max(128, n // 2)
        shell = Mesh.merge(
            meshes.frustum_wall(r_base, z_bus, r_exit, z_exit, n_t),
            meshes.annulus(r_in, r_exit, z_exit, n_t),
        ).translated((cx, cy, 0.0))
        bore = Mesh.merge(
            meshes.frustum_wall(r_base * 0.5, z_floor, r_in, z_exit, n_t, outward=False),
            meshes.disc(r_base * 0.5, z_floor, n_t),
        ).translated((cx, cy, 0.0))
        parts.append(_Part("thruster_shell", shell, None, (0.0, 0.0, 0.0), t.color))
        parts.append(_Part("thruster_bore", bore, None, (0.0, 0.0, 0.0), t.interior_color))
    for group in mockup.fasteners:
        z_surface = mockup.surface_z(group.surface)
        r = group.diameter / 2
        seg = 48
        head = Mesh.merge(
            meshes.disc(r, z_surface + group.height, seg),
            meshes.frustum_wall(r, z_surface, r, z_surface + group.height, seg),
        )
        for i, (x, y) in enumerate(group.centers_xy()):
            parts.append(
                _Part(
                    f"{group.name}_{i}",
                    head.translated((x, y, 0.0)),
                    None,
                    (0.0, 0.0, 0.0),
                    group.color,
                )
            )
    return parts


def export_mockup_obj(mockup: MockupConfig, path: str | Path) -> Path:
    """Write the built-in geometry of ``mockup`` as an OBJ (+MTL) in T — a starting point for a
    user's own model, and the test fixture for loading one."""
    obj_parts = []
    for part in mockup_parts(mockup):
        mesh = part.mesh if part.mesh is not None else _box_mesh(part.half_extents, part.center_T)
        obj_parts.append((part.name, mesh, part.color))
    meshes.write_obj(str(path), obj_parts)
    return Path(path)


def _box_mesh(half: tuple[float, float, float] | None, center: tuple[float, float, float]) -> Mesh:
    assert half is not None
    faces = []
    for axis in range(3):
        for sign in (1.0, -1.0):
            normal = np.zeros(3)
            normal[axis] = sign
            u_axis, v_axis = [a for a in range(3) if a != axis]
            corners = []
            for du, dv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                c = np.zeros(3)
                c[axis] = sign * half[axis]
                c[u_axis] = du * half[u_axis]
                c[v_axis] = dv * half[v_axis]
                corners.append(c)
            tris = np.array([[0, 1, 2], [0, 2, 3]])
            # Wind counter-clockwise seen from outside.
            if np.dot(np.cross(corners[1] - corners[0], corners[2] - corners[0]), normal) < 0:
                tris = tris[:, ::-1]
            faces.append(Mesh(np.array(corners), np.tile(normal, (4, 1)), tris))
    return Mesh.merge(*faces).translated(center)


def _obj_parts(path: Path, scale: float) -> list[_Part]:
    """The meshes of an OBJ file, one per material, coloured by the material's main colour
    (textures are not rendered)."""
    try:
        loaded = trimesh.load(str(path), force="scene", group_material=True, process=False)
    except Exception as exc:  # trimesh raises many types for malformed files
        raise ValueError(f"mockup.model_file.path: cannot read {path}: {exc}") from exc
    parts = []
    for node in loaded.graph.nodes_geometry:
        transform, name = loaded.graph[node]
        mesh = loaded.geometry[name].copy()
        mesh.apply_transform(transform)
        material = getattr(mesh.visual, "material", None)
        rgba = material.main_color if material is not None else mesh.visual.main_color
        color = tuple(float(c) / 255.0 for c in rgba[:3])
        vertices = np.asarray(mesh.vertices, dtype=float) * scale
        normals = np.asarray(mesh.vertex_normals, dtype=float)
        parts.append(
            _Part(
                str(name),
                Mesh(vertices, normals, np.asarray(mesh.faces)),
                None,
                (0.0, 0.0, 0.0),
                color,
            )
        )
    if not parts:
        raise ValueError(f"mockup.model_file.path: {path} holds no meshes")
    return parts


_I3 = np.eye(3)


@dataclass(frozen=True, slots=True, eq=False)
class SceneMesh:
    """Every triangle of the scene in T, for a renderer of its own (``sim_backends.raster``).

    ``colors_8bit``: per triangle, the part's RGB as pybullet stores it (0–255, truncated).
    """

    vertices_T: np.ndarray  # (V, 3)
    normals_T: np.ndarray  # (V, 3)
    triangles: np.ndarray  # (T, 3) int64
    colors_8bit: np.ndarray  # (T, 3) float64


def _scene_mesh(placed: list[tuple[Mesh, Pose, tuple[float, float, float]]]) -> SceneMesh:
    vertices, normals, triangles, colors = [], [], [], []
    offset = 0
    for mesh, X_TB, color in placed:
        vertices.append(mesh.vertices @ X_TB.R.T + X_TB.p)
        normals.append(mesh.normals @ X_TB.R.T)
        triangles.append(mesh.indices + offset)
        colors.append(np.tile(np.floor(255.0 * np.asarray(color)), (len(mesh.indices), 1)))
        offset += len(mesh.vertices)
    return SceneMesh(
        np.vstack(vertices),
        np.vstack(normals),
        np.vstack(triangles).astype(np.int64),
        np.vstack(colors),
    )


class MockupScene:
    """A pybullet world holding the mock-up at pose ``X_WT``.

    Use as a context manager, or call ``close()``; the pybullet client is private to the scene.
    """

    def __init__(self, mockup: MockupConfig, X_WT: Pose | None = None):
        self.mockup = mockup
        self.client = connect_direct()
        self._bodies: list[tuple[int, Pose]] = []  # (body id, X_TB)
        self._placed_meshes: list[tuple[Mesh, Pose, tuple[float, float, float]]] | None = []
        try:
            if mockup.model_file is not None:
                self._load_model_file()
            else:
                for part in mockup_parts(mockup):
                    self._add_part(part)
        except Exception:
            self.close()
            raise
        #: The scene's triangles in T, or None when pybullet loaded them itself (a URDF).
        self.mesh: SceneMesh | None = (
            _scene_mesh(self._placed_meshes) if self._placed_meshes else None
        )
        self._X_WT = Pose.identity()
        self._placed = False
        self.set_pose(X_WT or Pose.identity())

    # --- building -----------------------------------------------------------------------
    def _add_part(self, part: _Part, X_TF: Pose | None = None) -> None:
        """Add a part given in frame F (T unless ``X_TF`` says otherwise)."""
        rgba = [*part.color, 1.0]
        if part.mesh is None:
            shape = pybullet.createVisualShape(
                pybullet.GEOM_BOX,
                halfExtents=part.half_extents,
                rgbaColor=rgba,
                physicsClientId=self.client,
            )
        else:
            shape = pybullet.createVisualShape(
                pybullet.GEOM_MESH,
                vertices=part.mesh.vertices.tolist(),
                indices=part.mesh.indices.reshape(-1).tolist(),
                normals=part.mesh.normals.tolist(),
                rgbaColor=rgba,
                physicsClientId=self.client,
            )
        if shape < 0:
            raise RuntimeError(f"pybullet refused the visual shape of part {part.name!r}")
        body = pybullet.createMultiBody(baseVisualShapeIndex=shape, physicsClientId=self.client)
        X_FB = Pose(np.eye(3), np.array(part.center_T))
        X_TB = X_FB if X_TF is None else X_TF @ X_FB
        self._bodies.append((body, X_TB))
        if self._placed_meshes is not None:
            origin = (0.0, 0.0, 0.0)
            mesh = part.mesh if part.mesh is not None else _box_mesh(part.half_extents, origin)
            self._placed_meshes.append((mesh, X_TB, part.color))

    def _load_model_file(self) -> None:
        model = self.mockup.model_file
        assert model is not None
        path = Path(model.path)
        if not path.is_file():
            raise FileNotFoundError(f"mockup.model_file.path: {path} does not exist")
        suffix = path.suffix.lower()
        if suffix == ".urdf":
            with silenced_fds():  # pybullet prints warnings about missing inertials
                body = pybullet.loadURDF(
                    str(path),
                    useFixedBase=True,
                    globalScaling=model.scale,
                    physicsClientId=self.client,
                )
        elif suffix == ".obj":
            # pybullet gives a whole OBJ one colour; split it by material to keep the contrast.
            for part in _obj_parts(path, model.scale):
                self._add_part(part, model.X_TF)
            return
        else:
            raise ValueError(f"mockup.model_file.path: expected a .urdf or .obj file; got {path}")
        if body < 0:
            raise RuntimeError(f"mockup.model_file.path: pybullet could not load {path}")
        self._bodies.append((body, model.X_TF))
        self._placed_meshes = None  # pybullet holds the URDF's meshes

    # --- pose -----------------------------------------------------------------------------
    @property
    def X_WT(self) -> Pose:
        return self._X_WT

    def set_pose(self, X_WT: Pose) -> None:
        """Place the mock-up so that its frame T is at ``X_WT`` in the world."""
        if (
            np.array_equal(X_WT.R, self._X_WT.R)
            and np.array_equal(X_WT.p, self._X_WT.p)
            and self._placed
        ):
            return  # the track stands still most of the time
        quat_WT = Rotation.from_matrix(X_WT.R).as_quat().tolist()
        for body, X_TB in self._bodies:
            X_WB = X_WT @ X_TB
            # Built-in parts are not rotated relative to T: reuse T's quaternion.
            if np.array_equal(X_TB.R, _I3):
                quat = quat_WT
            else:
                quat = Rotation.from_matrix(X_WB.R).as_quat().tolist()
            pybullet.resetBasePositionAndOrientation(
                body, X_WB.p.tolist(), quat, physicsClientId=self.client
            )
        self._X_WT = X_WT
        self._placed = True

    # --- lifecycle ------------------------------------------------------------------------
    def close(self) -> None:
        if self.client is not None and self.client >= 0:
            with contextlib.suppress(pybullet.error):
                pybullet.disconnect(self.client)
        self.client = -1

    def __enter__(self) -> MockupScene:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
