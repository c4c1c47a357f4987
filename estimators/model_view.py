"""The target model as a camera at a given pose sees it: local affine maps of its planes and
image pixels mapped back onto them. Used to shape fitting windows and to mask other features.
"""

from __future__ import annotations

import math

import numpy as np

from estimators.compiled import compiled
from estimators.frame import CameraInfo
from estimators.geometry import Pose, as_points


def local_affine(X_CT: Pose, points_T: np.ndarray, camera: CameraInfo, *, step_m: float = 1e-4):
    """∂(pixel)/∂(x_T, y_T) (N,2,2, px per metre) at points (N,3) of planes parallel to T's
    xy plane — how a small disc or patch there is imaged (lens distortion included)."""
    points = as_points(points_T, 3, "points_T")
    A = np.empty((len(points), 2, 2))
    for axis in range(2):
        step = np.zeros(3)
        step[axis] = step_m
        plus = camera.project(X_CT.apply(points + step))
        minus = camera.project(X_CT.apply(points - step))
        A[:, :, axis] = (plus - minus) / (2.0 * step_m)
    return A


def plane_coordinates(uv: np.ndarray, X_CT: Pose, camera: CameraInfo, z_T: float) -> np.ndarray:
    """T-frame (x, y) (N,2) where the viewing rays of pixels (N,2) meet the plane z = z_T of T
    (NaN where a ray misses it in front of the camera)."""
    xy = camera.undistort(uv)
    rays_C = np.column_stack([xy, np.ones(len(xy))])
    # In T: origin o = camera centre, direction d; solve (o + s·d)_z = z_T.
    R_TC = X_CT.R.T
    o = -R_TC @ X_CT.p
    d = rays_C @ R_TC.T
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (z_T - o[2]) / d[:, 2]
    s = np.where(s > 0, s, np.nan)
    return o[:2] + s[:, None] * d[:, :2]


def outside_circles(
    points: np.ndarray, centres: np.ndarray, radii: np.ndarray, *, within: float = math.inf
) -> np.ndarray:
    """Which points (N,2) lie farther than ``radii`` (M,) from every centre (M,2), and closer
    than ``within`` to the origin (False for a non-finite point) — the pixels an edge or corner
    fit may use: clear of the fasteners, inside the ring. Compiled: it runs on every pixel of
    every band (N × M distances as NumPy temporaries cost the line system a millisecond a
    frame)."""
    return _outside_circles(
        np.ascontiguousarray(points, dtype=float),
        np.ascontiguousarray(centres, dtype=float).reshape(-1, 2),
        np.ascontiguousarray(radii, dtype=float).reshape(-1),
        float(within),
    )


@compiled
def _outside_circles(points, centres, radii, within):
    keep = np.empty(len(points), np.bool_)
    for i in range(len(points)):
        x, y = points[i, 0], points[i, 1]
        ok = math.isfinite(x) and math.hypot(x, y) < within
        j = 0
        while ok and j < len(centres):
            ok = math.hypot(x - centres[j, 0], y - centres[j, 1]) > radii[j]
            j += 1
        keep[i] = ok
    return keep


def head_extrusion(
    X_CT: Pose, points_T: np.ndarray, height_m: np.ndarray, camera: CameraInfo
) -> np.ndarray:
    """Image vectors (N,2 px) from the top centre of each head (N,3, in T) to its base, the
    head standing ``height_m`` (N,) proud of a surface parallel to T's xy plane — how far its
    wall shows beside its top (0 for a flat disc)."""
    points = as_points(points_T, 3, "points_T")
    height = np.broadcast_to(np.asarray(height_m, dtype=float), (len(points),))
    out = np.zeros((len(points), 2))
    raised = height > 0
    if np.any(raised):
        base = points[raised] - np.outer(height[raised], [0.0, 0.0, 1.0])
        out[raised] = camera.project(X_CT.apply(base)) - camera.project(X_CT.apply(points[raised]))
    return out
