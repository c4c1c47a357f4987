"""Triangle meshes of the mock-up's round parts (pure functions, no pybullet).

Circles are polygons with ``segments`` vertices, placed so that the polygon's area equals the
circle's: the radius is scaled by sqrt((2π/n) / sin(2π/n)). A polygon inscribed in the circle
would shrink its image (by 0.05 px for a 270 px radius at n = 360); the equal-area polygon's edge
deviates from the true circle by ±r·(1 − cos(π/n))/2 and its centroid and apparent size match.
Triangles wind counter-clockwise seen from the side their normal points to.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, slots=True, eq=False)
class Mesh:
    vertices: np.ndarray  # (V,3) float
    normals: np.ndarray  # (V,3) unit vertex normals
    indices: np.ndarray  # (T,3) int triangle vertex indices

    def __post_init__(self) -> None:
        if self.vertices.shape != self.normals.shape or self.vertices.shape[1] != 3:
            raise ValueError("Mesh vertices and normals must both be (V,3)")
        if self.indices.ndim != 2 or self.indices.shape[1] != 3:
            raise ValueError("Mesh indices must be (T,3)")

    @staticmethod
    def merge(*meshes: Mesh) -> Mesh:
        offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
        return Mesh(
            np.vstack([m.vertices for m in meshes]),
            np.vstack([m.normals for m in meshes]),
            np.vstack([m.indices + off for m, off in zip(meshes, offsets, strict=True)]),
        )

    def translated(self, offset: np.ndarray) -> Mesh:
        return Mesh(self.vertices + np.asarray(offset, dtype=float), self.normals, self.indices)


def equal_area_radius(radius: float, segments: int) -> float:
    """Circumradius of the regular ``segments``-gon whose area equals that of the circle."""
    step = 2.0 * np.pi / segments
    return radius * np.sqrt(step / np.sin(step))


def _ring_xy(radius: float, segments: int) -> tuple[np.ndarray, np.ndarray]:
    t = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    r = equal_area_radius(radius, segments)
    return r * np.cos(t), r * np.sin(t)


def annulus(r_inner: float, r_outer: float, z: float, segments: int) -> Mesh:
    """A flat ring in the plane at height ``z``, facing +z."""
    if not 0.0 < r_inner < r_outer:
        raise ValueError(f"annulus needs 0 < r_inner < r_outer; got {r_inner}, {r_outer}")
    xo, yo = _ring_xy(r_outer, segments)
    xi, yi = _ring_xy(r_inner, segments)
    n = segments
    vertices = np.vstack(
        [np.column_stack([xo, yo, np.full(n, z)]), np.column_stack([xi, yi, np.full(n, z)])]
    )
    i = np.arange(n)
    j = (i + 1) % n
    tris = np.vstack([np.column_stack([i, j, n + i]), np.column_stack([j, n + j, n + i])])
    return Mesh(vertices, np.tile([0.0, 0.0, 1.0], (2 * n, 1)), tris)


def disc(radius: float, z: float, segments: int, *, facing: float = 1.0) -> Mesh:
    """A flat disc at height ``z`` facing +z (``facing`` = 1) or −z (−1)."""
    x, y = _ring_xy(radius, segments)
    vertices = np.vstack([[0.0, 0.0, z], np.column_stack([x, y, np.full(segments, z)])])
    i = np.arange(segments)
    rim_i = 1 + i
    rim_j = 1 + (i + 1) % segments
    center = np.zeros(segments, dtype=int)
    tris = (
        np.column_stack([center, rim_i, rim_j])
        if facing > 0
        else np.column_stack([center, rim_j, rim_i])
    )
    normals = np.tile([0.0, 0.0, float(np.sign(facing))], (segments + 1, 1))
    return Mesh(vertices, normals, tris)


def frustum_wall(
    r0: float, z0: float, r1: float, z1: float, segments: int, *, outward: bool = True
) -> Mesh:
    """The side of a cone frustum (or cylinder when r0 == r1) from height z0 to z1.

    ``outward`` normals face away from the axis (the outside of a boss); inward ones face the
    axis (the inside of a bore or nozzle).
    """
    x0, y0 = _ring_xy(r0, segments)
    x1, y1 = _ring_xy(r1, segments)
    n = segments
    vertices = np.vstack(
        [np.column_stack([x0, y0, np.full(n, z0)]), np.column_stack([x1, y1, np.full(n, z1)])]
    )
    # Surface normal of a frustum: radial component ∝ (z1 − z0), axial ∝ −(r1 − r0).
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    radial = np.column_stack([np.cos(t), np.sin(t), np.zeros(n)]) * (z1 - z0)
    axial = np.tile([0.0, 0.0, -(r1 - r0)], (n, 1))
    normal = radial + axial
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    if not outward:
        normal = -normal
    normals = np.vstack([normal, normal])
    i = np.arange(n)
    j = (i + 1) % n
    # Counter-clockwise seen from outside when z1 > z0.
    tris = np.vstack([np.column_stack([i, j, n + j]), np.column_stack([i, n + j, n + i])])
    if (z1 < z0) == outward:
        tris = tris[:, ::-1]
    return Mesh(vertices, normals, tris)


def write_obj(path: str, parts: list[tuple[str, Mesh, tuple[float, float, float]]]) -> None:
    """Write named meshes with flat colours to an OBJ file and its MTL beside it."""
    import os

    mtl_path = os.path.splitext(path)[0] + ".mtl"
    with open(mtl_path, "w", encoding="utf-8") as mtl:
        for name, _, color in parts:
            mtl.write(f"newmtl {name}\nKd {color[0]:.4f} {color[1]:.4f} {color[2]:.4f}\n")
            mtl.write("Ka 0 0 0\nKs 0 0 0\nd 1\nillum 1\n\n")
    with open(path, "w", encoding="utf-8") as obj:
        obj.write(f"mtllib {os.path.basename(mtl_path)}\n")
        offset = 1
        for name, mesh, _ in parts:
            obj.write(f"o {name}\nusemtl {name}\n")
            np.savetxt(obj, mesh.vertices, fmt="v %.7f %.7f %.7f")
            np.savetxt(obj, mesh.normals, fmt="vn %.6f %.6f %.6f")
            faces = mesh.indices + offset
            np.savetxt(obj, np.repeat(faces, 2, axis=1), fmt="f %d//%d %d//%d %d//%d")
            offset += len(mesh.vertices)
