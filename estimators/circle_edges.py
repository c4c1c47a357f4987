"""Edge points of a model circle in an image: sample its projection, search along the normals.

The circle is projected through the full camera model (lens distortion included), so the
search follows the curve as the camera sees it; the edge points found are then undistorted to
ideal-pinhole pixels, where circles project to conics and ``circle_fit`` applies.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimators.conics import circle_points
from estimators.edge_search import EdgeHits, search_edges
from estimators.frame import CameraInfo
from estimators.geometry import field_radius
from estimators.imaging import GradientField
from estimators.planar_pose import ideal_pixels

_MAX_SAMPLES = 2400


@dataclass(frozen=True, slots=True, eq=False)
class CurveSamples:
    """Points (N,2) on a projected circle (distorted pixels), unit outward normals (N,2), the
    circle parameter t (N,) of each, the projected centre (2,), the whole projected perimeter
    and the spacing of the samples (px)."""

    uv: np.ndarray
    normals: np.ndarray
    t: np.ndarray
    center_uv: np.ndarray
    perimeter_px: float

    spacing_px: float  # distance between neighbouring samples along the curve


def visible_pixels(
    points_C: np.ndarray, camera: CameraInfo, margin_px: float, field_radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """(mask, pixels) of points (N,3) in C that the camera images at least ``margin_px``
    inside its borders; pixels are NaN where not visible. Same test as ``geometry.in_view``,
    with the field radius (which rejects distortion fold-back) computed once by the caller."""
    mask = points_C[:, 2] > 1e-3
    xy = np.full((len(points_C), 2), np.inf)
    xy[mask] = points_C[mask, :2] / points_C[mask, 2:3]
    mask &= np.einsum("ij,ij->i", xy, xy) <= (1.02 * field_radius) ** 2
    uv = np.full((len(points_C), 2), np.nan)
    if np.any(mask):
        uv[mask] = camera.project(points_C[mask])
    with np.errstate(invalid="ignore"):
        mask &= (uv[:, 0] >= margin_px - 0.5) & (uv[:, 0] <= camera.width - 0.5 - margin_px)
        mask &= (uv[:, 1] >= margin_px - 0.5) & (uv[:, 1] <= camera.height - 0.5 - margin_px)
    return mask, uv


def camera_field_radius(camera: CameraInfo) -> float:
    """``geometry.field_radius`` of a camera (normalised radius of its image corners)."""
    return field_radius(camera.K, camera.dist, camera.width, camera.height)


def sample_projected_circle(
    center_C: np.ndarray,
    normal_C: np.ndarray,
    radius: float,
    camera: CameraInfo,
    *,
    spacing_px: float,
    margin_px: float = 0.0,
    field_radius_xy: float | None = None,
    max_samples: int = _MAX_SAMPLES,
) -> CurveSamples | None:
    """Samples every ~``spacing_px`` (or more, to stay within ``max_samples`` around the whole
    circle) along the image of a 3-D circle, keeping those at least ``margin_px`` inside the
    image; None when the circle is not (safely) in front of the camera or nothing of it is in
    view. ``field_radius_xy`` (``camera_field_radius``) saves its recomputation."""
    if field_radius_xy is None:
        field_radius_xy = camera_field_radius(camera)
    center_C = np.asarray(center_C, dtype=float)
    coarse = circle_points(center_C, normal_C, radius, 32)
    if center_C[2] <= 0 or np.any(coarse[:, 2] < 0.02):
        return None
    # Perimeter from the ideal (pinhole) projection; distortion changes it by a few percent.
    K = camera.K
    coarse_uv = coarse[:, :2] / coarse[:, 2:3] * np.array([K[0, 0], K[1, 1]])
    perimeter = float(
        np.linalg.norm(np.diff(np.vstack([coarse_uv, coarse_uv[:1]]), axis=0), axis=1).sum()
    )
    count = int(np.clip(perimeter / max(spacing_px, 0.25), 16, max_samples))
    t = np.linspace(0.0, 2.0 * np.pi, count, endpoint=False)
    dt = 1e-4
    points = circle_points(center_C, normal_C, radius, angles=np.concatenate([t, t + dt, t - dt]))
    mask, uv_all = visible_pixels(points, camera, margin_px, field_radius_xy)
    keep = mask[:count] & mask[count : 2 * count] & mask[2 * count :]
    if not np.any(keep):
        return None
    uv = uv_all[:count][keep]
    tangent = uv_all[count : 2 * count][keep] - uv_all[2 * count :][keep]
    normals = np.column_stack([tangent[:, 1], -tangent[:, 0]])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    center_uv = camera.project(center_C[None, :])[0]
    outward = np.einsum("ij,ij->i", normals, uv - center_uv) >= 0
    normals[~outward] *= -1.0
    return CurveSamples(uv, normals, t[keep], center_uv, perimeter, perimeter / count)


@dataclass(frozen=True, slots=True, eq=False)
class CircleEdges:
    """Edge points found on one projected circle: ``hits`` (distorted pixels), their
    ideal-pinhole positions ``uv_ideal`` (found ones only), the samples searched, and the
    polarity used (+1: brighter outside the circle)."""

    samples: CurveSamples
    hits: EdgeHits
    uv_ideal: np.ndarray
    polarity: int

    @property
    def support(self) -> float:
        """Fraction of the searched samples with an edge."""
        return float(self.hits.found.mean()) if len(self.hits.found) else 0.0


def find_circle_edges(
    field: GradientField,
    samples: CurveSamples,
    camera: CameraInfo,
    *,
    polarity: int | None,
    half_width_px: float,
    min_snr: float = 3.0,
    prior_sigma_px: float | None = None,
) -> CircleEdges:
    """Search the samples' normals for the circle's edge. ``polarity`` None lets the image
    decide which side is brighter: both polarities are tried on every fourth sample and the
    one with the larger total edge strength is searched on all of them."""
    if polarity is None:
        probe = slice(None, None, 4)
        strengths = {
            p: float(
                search_edges(
                    field,
                    samples.uv[probe],
                    samples.normals[probe],
                    p,
                    half_width_px,
                    min_snr=min_snr,
                    prior_sigma_px=prior_sigma_px,
                ).snr.sum()
            )
            for p in (1, -1)
        }
        polarity = max(strengths, key=strengths.get)
    hits = search_edges(
        field,
        samples.uv,
        samples.normals,
        polarity,
        half_width_px,
        min_snr=min_snr,
        prior_sigma_px=prior_sigma_px,
    )
    return CircleEdges(
        samples, hits, ideal_pixels(hits.uv[hits.found], camera.K, camera.dist), polarity
    )
