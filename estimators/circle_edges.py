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
from estimators.lens_distortion import pixel_in_view, project_point
from estimators.lens_distortion import visible_pixels as _lens_visible_pixels
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
    """(mask, pixels) of points (N,3) in C more than 1 mm in front of the camera that it images
    at least ``margin_px`` inside its borders; pixels are NaN where not in front or beyond the
    field. ``geometry.in_view``'s test, with the field radius (which rejects distortion
    fold-back) computed once by the caller."""
    return _lens_visible_pixels(
        np.ascontiguousarray(points_C, dtype=float).reshape(-1, 3),
        np.array(camera.K, dtype=float),
        *camera.lens,
        *_view_bounds(camera, margin_px, field_radius),
    )


def _view_bounds(
    camera: CameraInfo, margin_px: float, field_radius: float
) -> tuple[float, float, float, float, float, float]:
    """``lens_distortion.pixel_in_view``'s bounds for a circle's samples: more than 1 mm in
    front, within 1.02 × the field radius, ``margin_px`` inside the pixels' outer edges."""
    return (
        1e-3,
        1.02 * float(field_radius),
        float(margin_px) - 0.5,
        camera.width - 0.5 - float(margin_px),
        float(margin_px) - 0.5,
        camera.height - 0.5 - float(margin_px),
    )


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
        _view_bounds(camera, margin_px, field_radius_xy),
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
    bounds,
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
        x, y, z = _circle_point(center, u, v, radius, i * (2.0 * np.pi / 32))
        if z < 0.02 or center[2] <= 0:
            return False, empty, empty, np.zeros(0), np.zeros(2), 0.0, 0
        pu, pv = x / z * K[0, 0], y / z * K[1, 1]
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
    for i in range(count):
        t = i * step
        seen, pu, pv = _circle_pixel(center, u, v, radius, t, K, d, M, tilted, distorted, bounds)
        if not seen:
            continue
        ahead, au, av = _circle_pixel(
            center, u, v, radius, t + 1e-4, K, d, M, tilted, distorted, bounds
        )
        if not ahead:
            continue
        behind, bu, bv = _circle_pixel(
            center, u, v, radius, t - 1e-4, K, d, M, tilted, distorted, bounds
        )
        if not behind:
            continue
        tu, tv = au - bu, av - bv
        nu, nv = tv, -tu
        norm = max(math.sqrt(nu * nu + nv * nv), 1e-12)
        nu, nv = nu / norm, nv / norm
        if nu * (pu - cu) + nv * (pv - cv) < 0:
            nu, nv = -nu, -nv
        uv[kept, 0], uv[kept, 1] = pu, pv
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
    """The circle's point (x, y, z) at ``angle`` in its plane's basis (u, v)
    (``conics.circle_points``); three scalars, not an array: this runs thrice per sample."""
    c, s = math.cos(angle), math.sin(angle)
    return (
        center[0] + radius * (c * u[0]) + radius * (s * v[0]),
        center[1] + radius * (c * u[1]) + radius * (s * v[1]),
        center[2] + radius * (c * u[2]) + radius * (s * v[2]),
    )


@compiled_inline
def _circle_pixel(center, u, v, radius, angle, K, d, M, tilted, distorted, bounds):
    """Whether the circle's point at ``angle`` is seen within ``bounds`` (``_view_bounds``),
    and its pixel."""
    x, y, z = _circle_point(center, u, v, radius, angle)
    min_depth, field_limit, u_min, u_max, v_min, v_max = bounds
    return pixel_in_view(
        x, y, z, K, d, M, tilted, distorted, min_depth, field_limit, u_min, u_max, v_min, v_max
    )


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
