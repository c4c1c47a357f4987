"""Edge points of a model circle in an image: sample its projection, search along the normals.

The circle is projected through the full camera model (lens distortion included), so the
search follows the curve as the camera sees it; the edge points found are then undistorted to
ideal-pinhole pixels, where circles project to conics and ``circle_fit`` applies.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimators.compiled import compiled, compiled_inline
from estimators.conics import circle_plane_basis
from estimators.edge_search import EdgeHits, search_edges
from estimators.frame import CameraInfo
from estimators.geometry import field_radius
from estimators.imaging import GradientField
from estimators.lens_distortion import project_point
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
    inside its borders; pixels are NaN where not in front or beyond the field. Same test as
    ``geometry.in_view``, with the field radius (which rejects distortion fold-back) computed
    once by the caller."""
    return _visible_pixels(
        np.ascontiguousarray(points_C, dtype=float).reshape(-1, 3),
        np.array(camera.K, dtype=float),
        *camera.lens,
        float(margin_px),
        (1.02 * float(field_radius)) ** 2,
        camera.width,
        camera.height,
    )


@compiled_inline
def _pixel_in_view(X, Y, Z, K, d, M, tilted, distorted, margin_px, limit, width, height):
    """(in view, u, v) of one point in C: in front (z > 1 mm), within the field (normalised
    radius² ≤ ``limit``) and imaged ``margin_px`` inside the borders; u, v NaN unless in front
    and within the field."""
    if not Z > 1e-3:
        return False, np.nan, np.nan
    x, y = X / Z, Y / Z
    if not x * x + y * y <= limit:
        return False, np.nan, np.nan
    u, v = project_point(X, Y, Z, K, d, M, tilted, distorted)
    inside = margin_px - 0.5 <= u <= width - 0.5 - margin_px
    return inside and margin_px - 0.5 <= v <= height - 0.5 - margin_px, u, v


@compiled
def _visible_pixels(points_C, K, d, M, tilted, distorted, margin_px, limit, width, height):
    mask = np.zeros(len(points_C), np.bool_)
    uv = np.empty((len(points_C), 2))
    for i in range(len(points_C)):
        mask[i], uv[i, 0], uv[i, 1] = _pixel_in_view(
            points_C[i, 0],
            points_C[i, 1],
            points_C[i, 2],
            K,
            d,
            M,
            tilted,
            distorted,
            margin_px,
            limit,
            width,
            height,
        )
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
    center_C = np.array(center_C, dtype=float)
    u, v = circle_plane_basis(normal_C)
    # (writable copies of the small arrays: one compiled signature whatever the caller holds)
    found, uv, normals, t, center_uv, perimeter, count = _sample_circle(
        center_C,
        u,
        v,
        float(radius),
        np.array(camera.K, dtype=float),
        *camera.lens,
        float(spacing_px),
        float(margin_px),
        float(field_radius_xy),
        camera.width,
        camera.height,
        int(max_samples),
    )
    if not found:
        return None
    return CurveSamples(uv, normals, t, center_uv, perimeter, perimeter / count)


@compiled
def _sample_circle(
    center,
    u,
    v,
    radius,
    K,
    d,
    M,
    tilted,
    distorted,
    spacing_px,
    margin_px,
    field_radius,
    width,
    height,
    max_samples,
):
    """``sample_projected_circle``'s work, compiled (the ellipse system samples a dozen circles
    a frame, and as NumPy each took thirty calls): whether any sample is in view; the samples'
    pixels, unit outward normals and circle parameters; the projected centre; the perimeter
    (px) and the number of samples around the whole circle. A sample is kept when it and its
    two neighbours 10⁻⁴ rad either side (which give its tangent) are in view
    (``visible_pixels``' test)."""
    empty = np.zeros((0, 2))
    # Perimeter from the ideal (pinhole) projection; distortion changes it by a few percent.
    perimeter = 0.0
    first_u = first_v = last_u = last_v = 0.0
    for i in range(32):
        P = _circle_point(center, u, v, radius, i * (2.0 * np.pi / 32))
        if P[2] < 0.02 or center[2] <= 0:
            return False, empty, empty, np.zeros(0), np.zeros(2), 0.0, 0
        pu, pv = P[0] / P[2] * K[0, 0], P[1] / P[2] * K[1, 1]
        if i == 0:
            first_u, first_v = pu, pv
        else:
            perimeter += math.sqrt((pu - last_u) ** 2 + (pv - last_v) ** 2)
        last_u, last_v = pu, pv
    perimeter += math.sqrt((first_u - last_u) ** 2 + (first_v - last_v) ** 2)
    count = int(min(max(perimeter / max(spacing_px, 0.25), 16.0), float(max_samples)))
    cu, cv = project_point(center[0], center[1], center[2], K, d, M, tilted, distorted)
    step = 2.0 * np.pi / count
    uv, normals, t_kept = np.empty((count, 2)), np.empty((count, 2)), np.empty(count)
    kept = 0
    limit = (1.02 * field_radius) ** 2
    seen = np.empty(3, np.bool_)
    pixel = np.empty((3, 2))
    for i in range(count):
        t = i * step
        for k, angle in enumerate((t, t + 1e-4, t - 1e-4)):
            P = _circle_point(center, u, v, radius, angle)
            seen[k], pixel[k, 0], pixel[k, 1] = _pixel_in_view(
                P[0], P[1], P[2], K, d, M, tilted, distorted, margin_px, limit, width, height
            )
        if not (seen[0] and seen[1] and seen[2]):
            continue
        tu, tv = pixel[1, 0] - pixel[2, 0], pixel[1, 1] - pixel[2, 1]
        nu, nv = tv, -tu
        norm = max(math.sqrt(nu * nu + nv * nv), 1e-12)
        nu, nv = nu / norm, nv / norm
        if nu * (pixel[0, 0] - cu) + nv * (pixel[0, 1] - cv) < 0:
            nu, nv = -nu, -nv
        uv[kept, 0], uv[kept, 1] = pixel[0, 0], pixel[0, 1]
        normals[kept, 0], normals[kept, 1] = nu, nv
        t_kept[kept] = t
        kept += 1
    if kept == 0:
        return False, empty, empty, np.zeros(0), np.zeros(2), 0.0, 0
    center_uv = np.array([cu, cv])
    return (
        True,
        uv[:kept].copy(),
        normals[:kept].copy(),
        t_kept[:kept].copy(),
        center_uv,
        perimeter,
        count,
    )


@compiled_inline
def _circle_point(center, u, v, radius, angle):
    """The circle's point at ``angle`` in its plane's basis (u, v) (``conics.circle_points``)."""
    return center + radius * (math.cos(angle) * u) + radius * (math.sin(angle) * v)


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
