"""The panel's four edges to sub-pixel accuracy: strips along predicted edges → edge points →
robust lines → corners (intersections of neighbouring lines).

Predicted edges come from a pose (the prior; curved when the lens distorts) or from a
quadrilateral found in the image (acquisition). Edge points are measured in image pixels and
converted to ideal (undistorted pinhole) pixels, where the edges are straight, before lines are
fitted — so lens distortion never bends a fitted line.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from drivers.base import CameraInfo
from estimators.edge_fit import EdgePoints, Line2D, fit_edge_points, fit_line_robust, intersect
from estimators.geometry import Pose
from estimators.planar_pose import EdgeObservations, ideal_pixel_jacobians, ideal_pixels
from estimators.target import TargetModel

#: Strips stay this far (px) from a corner, beyond the band across the neighbouring edge.
CORNER_CLEARANCE_PX = 5.0
#: ...and at least this fraction of the edge.
MIN_CORNER_FRACTION = 0.04


def edge_span(length_px: float, strip_px: float) -> tuple[float, float]:
    """The part of an edge (fractions of its length) the strips cover: as close to the corners
    as the neighbouring edge allows — an edge's angle, which carries the panel's tilt, is
    measured best from its ends (its information grows with the cube of the span)."""
    margin = max(MIN_CORNER_FRACTION, (CORNER_CLEARANCE_PX + 0.5 * strip_px) / max(length_px, 1.0))
    margin = min(margin, 0.3)
    return margin, 1.0 - margin


@dataclass(frozen=True, slots=True, eq=False)
class EdgeStrips:
    """Where to look for one edge: strip centres (K,2 px) on the predicted edge, unit normals
    (K,2) toward the panel's inside, and the strips' half length (px)."""

    centers_uv: np.ndarray
    normals: np.ndarray
    half_length_px: float


def strip_count(length_px: float, strip_px: float) -> int:
    t0, t1 = edge_span(length_px, strip_px)
    return int(np.clip(round(length_px * (t1 - t0) / strip_px), 3, 60))


def strips_from_pose(
    X_CT: Pose, camera: CameraInfo, target: TargetModel, strip_px: float
) -> list[EdgeStrips] | None:
    """Strips along the four projected panel edges (None if the panel is not in view)."""
    corners = target.panel_corners_T
    corners_C = X_CT.apply(corners)
    if not np.all(camera.in_view(corners_C, margin_px=1.0)):
        return None
    centre_uv = camera.project(X_CT.apply(corners.mean(axis=0)[None]))[0]
    corners_uv = camera.project(corners_C)
    strips = []
    for i in range(4):
        a, b = corners[i], corners[(i + 1) % 4]
        length = float(np.linalg.norm(corners_uv[(i + 1) % 4] - corners_uv[i]))
        count = strip_count(length, strip_px)
        t0, t1 = edge_span(length, strip_px)
        t = np.linspace(t0, t1, count)[:, None]
        uv = camera.project(X_CT.apply(a + t * (b - a)))
        ahead = camera.project(X_CT.apply(a + (t + 1e-3) * (b - a)))
        tangent = ahead - uv
        tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
        normal = np.column_stack([-tangent[:, 1], tangent[:, 0]])
        if np.mean(np.sum((centre_uv - uv) * normal, axis=1)) < 0:
            normal = -normal
        spacing = length * (t1 - t0) / max(count - 1, 1)
        strips.append(EdgeStrips(uv, normal, 0.5 * spacing))
    return strips


def strips_from_quad(corners_uv: np.ndarray, strip_px: float) -> list[EdgeStrips]:
    """Strips along the straight sides of an image quadrilateral (4,2 px)."""
    quad = np.asarray(corners_uv, dtype=float).reshape(4, 2)
    centre = quad.mean(axis=0)
    strips = []
    for i in range(4):
        a, b = quad[i], quad[(i + 1) % 4]
        length = float(np.linalg.norm(b - a))
        count = strip_count(length, strip_px)
        t0, t1 = edge_span(length, strip_px)
        t = np.linspace(t0, t1, count)[:, None]
        uv = a + t * (b - a)
        tangent = (b - a) / max(length, 1e-9)
        normal = np.array([-tangent[1], tangent[0]])
        if normal @ (centre - 0.5 * (a + b)) < 0:
            normal = -normal
        spacing = length * (t1 - t0) / max(count - 1, 1)
        strips.append(EdgeStrips(uv, np.broadcast_to(normal, uv.shape).copy(), 0.5 * spacing))
    return strips


def shift_strips_onto(strips: EdgeStrips, point: np.ndarray, direction: np.ndarray) -> EdgeStrips:
    """Strips moved along their normals onto the image line through ``point`` along
    ``direction`` (e.g. a labeled Hough segment), keeping their spacing and shape."""
    normal_line = np.array([-direction[1], direction[0]]) / np.linalg.norm(direction)
    # Solve (c + s·n)·n_line = point·n_line for s per strip.
    denominator = strips.normals @ normal_line
    safe = np.where(np.abs(denominator) < 0.2, np.nan, denominator)
    shift = ((point - strips.centers_uv) @ normal_line) / safe
    shift = np.where(np.isfinite(shift), shift, 0.0)
    return EdgeStrips(
        strips.centers_uv + shift[:, None] * strips.normals, strips.normals, strips.half_length_px
    )


@dataclass(frozen=True, slots=True, eq=False)
class FittedEdge:
    """One fitted edge: its points (image px and ideal px) with σ across the edge (ideal px),
    the inliers of the robust line (in ideal px), and the grey-level contrast test."""

    points: EdgePoints
    uv_ideal: np.ndarray
    sigma_ideal: np.ndarray
    line: Line2D | None
    used: np.ndarray  # indices into points of the inliers used for the line

    @property
    def found(self) -> bool:
        return self.line is not None and len(self.used) >= 3


@dataclass(frozen=True, slots=True, eq=False)
class PanelEdges:
    """The four fitted edges (in model order) and the corners where neighbours meet (ideal
    px; corner i is between edge i−1 and edge i, matching the model's corner i)."""

    edges: tuple[FittedEdge, ...]
    corners_ideal: np.ndarray | None

    @property
    def all_found(self) -> bool:
        return all(e.found for e in self.edges) and self.corners_ideal is not None

    def observations(self, target: TargetModel) -> EdgeObservations:
        """Edge points as pose observations (point-to-projected-edge distances)."""
        corners = target.panel_corners_T
        ends = np.stack([corners, np.roll(corners, -1, axis=0)], axis=1)
        uv, edge, sigma = [], [], []
        for i, e in enumerate(self.edges):
            if not e.found:
                continue
            uv.append(e.uv_ideal[e.used])
            sigma.append(e.sigma_ideal[e.used])
            edge.append(np.full(len(e.used), i))
        return EdgeObservations(
            ends, np.concatenate(edge), np.concatenate(uv), np.concatenate(sigma)
        )

    def image_points(self) -> np.ndarray:
        """All inlier edge points in image pixels (for overlays)."""
        parts = [e.points.uv[e.used] for e in self.edges if e.found]
        return np.concatenate(parts) if parts else np.zeros((0, 2))


def _fit_one_edge(
    pixels, strip, camera, half_width_px, search_px, min_contrast_snr, polarity, keep
):
    points = fit_edge_points(
        pixels,
        strip.centers_uv,
        strip.normals,
        strip.half_length_px,
        half_width_px,
        search_px=search_px,
        keep=keep,
    )
    ok = np.flatnonzero(points.ok)
    empty = FittedEdge(points, np.zeros((0, 2)), np.zeros(0), None, np.zeros(0, int))
    if len(ok) < 3 or polarity * points.contrast_snr < min_contrast_snr:
        return empty
    uv_ideal = ideal_pixels(points.uv[ok], camera.K, camera.dist)
    sigma = points.sigma_px[ok]
    if camera.has_distortion:
        J = ideal_pixel_jacobians(points.uv[ok], camera.K, camera.dist)
        across = np.einsum("nij,nj->ni", J, strip.normals[ok])
        sigma = sigma * np.linalg.norm(across, axis=1)
    line = fit_line_robust(uv_ideal, sigma)
    if line is None:
        return empty
    full_uv = np.full((len(points.uv), 2), np.nan)
    full_sigma = np.full(len(points.uv), np.inf)
    full_uv[ok] = uv_ideal
    full_sigma[ok] = sigma
    return FittedEdge(points, full_uv, full_sigma, line, ok[line.inliers])


def fit_panel_edges(
    pixels: np.ndarray,
    strips: list[EdgeStrips],
    camera: CameraInfo,
    *,
    half_width_px: float = 3.0,
    search_px: float | list[float] = 2.0,
    min_contrast_snr: float = 3.5,
    polarity: float = 1.0,
    keep: Callable[[np.ndarray], np.ndarray] | None = None,
    fallback: list[EdgeStrips] | None = None,
    fallback_search_px: float = 4.0,
) -> PanelEdges:
    """Fit the four edges from their strips (``search_px`` per edge or for all). An edge
    counts as found when its grey levels differ with the model's polarity (+1: the panel is
    brighter) by ``min_contrast_snr`` standard deviations and a robust line fits at least three
    points; an edge not found from ``strips`` is tried again from ``fallback`` (e.g. the
    prior's prediction when a labeled image line misled)."""
    searches = list(search_px) if isinstance(search_px, list | tuple) else [search_px] * len(strips)
    fitted = []
    for i, strip in enumerate(strips):
        edge = _fit_one_edge(
            pixels, strip, camera, half_width_px, searches[i], min_contrast_snr, polarity, keep
        )
        if not edge.found and fallback is not None:
            edge = _fit_one_edge(
                pixels,
                fallback[i],
                camera,
                half_width_px,
                fallback_search_px,
                min_contrast_snr,
                polarity,
                keep,
            )
        fitted.append(edge)
    corners = None
    if all(e.found for e in fitted):
        found = []
        for i in range(4):
            point = intersect(fitted[i - 1].line, fitted[i].line)  # type: ignore[arg-type]
            if point is None:
                break
            found.append(point)
        if len(found) == 4 and np.all(np.isfinite(found)):
            corners = np.array(found)
    return PanelEdges(tuple(fitted), corners)


def corner_sigma_px(edges: PanelEdges) -> float:
    """A typical corner uncertainty (px) from the edge points' scatter, for closed-form use."""
    sigmas = [float(np.median(e.sigma_ideal[e.used])) for e in edges.edges if e.found]
    counts = [len(e.used) for e in edges.edges if e.found]
    if not sigmas:
        return math.nan
    return float(np.median(sigmas) * math.sqrt(4.0 / max(min(counts), 1)))
