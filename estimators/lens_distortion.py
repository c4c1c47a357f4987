"""OpenCV's lens distortion of normalized image coordinates, and its inverse's refinement,
compiled (numba); the model and its public entry points are ``estimators.geometry``'s
``distort_normalized`` and ``undistort_pixels``. A point where a rational model's denominator
vanishes, far outside the calibrated field, comes out non-finite (``estimators.compiled``)."""

from __future__ import annotations

import math

import numpy as np

from estimators.compiled import compiled, compiled_inline


@compiled_inline
def _distort_point(x, y, d, M, tilted):
    """One point through the radial, tangential and thin-prism terms (coefficients ``d`` in
    OpenCV's order, padded to 14) and, when ``tilted``, the tilted sensor's projection M."""
    k1, k2, p1, p2, k3, k4, k5, k6 = d[0], d[1], d[2], d[3], d[4], d[5], d[6], d[7]
    s1, s2, s3, s4 = d[8], d[9], d[10], d[11]
    r2 = x * x + y * y
    r4 = r2 * r2
    r6 = r4 * r2
    radial = (1 + k1 * r2 + k2 * r4 + k3 * r6) / (1 + k4 * r2 + k5 * r4 + k6 * r6)
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r4
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + s3 * r2 + s4 * r4
    if tilted:
        w = M[2, 0] * xd + M[2, 1] * yd + M[2, 2]
        xd, yd = (
            (M[0, 0] * xd + M[0, 1] * yd + M[0, 2]) / w,
            (M[1, 0] * xd + M[1, 1] * yd + M[1, 2]) / w,
        )
    return xd, yd


@compiled
def distort(xy, d, M, tilted):
    """``geometry.distort_normalized`` point by point: at 1280×800 the line system distorts a
    hundred thousand points a frame, and as NumPy expressions their temporaries took 14 ms of
    it."""
    out = np.empty((len(xy), 2))
    for i in range(len(xy)):
        out[i, 0], out[i, 1] = _distort_point(xy[i, 0], xy[i, 1], d, M, tilted)
    return out


@compiled_inline
def project_point(X, Y, Z, K, d, M, tilted, distorted):
    """The pixel (u, v) of one point in C (``geometry.project``), through the lens when
    ``distorted``, for compiled callers."""
    x, y = X / Z, Y / Z
    if distorted:
        x, y = _distort_point(x, y, d, M, tilted)
    return K[0, 0] * x + K[0, 1] * y + K[0, 2], K[1, 1] * y + K[1, 2]


@compiled
def project_distorted(points_C, K, d, M, tilted):
    """``geometry.project`` through a lens, point by point: every system projects model points
    some fifty times a frame, and as NumPy calls each projection cost more than its
    arithmetic."""
    out = np.empty((len(points_C), 2))
    for i in range(len(points_C)):
        out[i, 0], out[i, 1] = project_point(
            points_C[i, 0], points_C[i, 1], points_C[i, 2], K, d, M, tilted, True
        )
    return out


@compiled
def refine_undistorted(xy, xy_d, d, M, tilted, steps):
    """Newton steps on distort(xy) = ``xy_d`` from ``xy`` (N,2), each point on its own, the
    Jacobian by central differences of 1e-7: OpenCV's fixed-point inversion can stall short of
    its tolerance for strong distortion, and two steps make it exact to ~1e-12. Compiled: as
    NumPy calls, five distortions a step cost the systems milliseconds a frame at 1280×800."""
    out = np.empty((len(xy), 2))
    h = 1e-7
    for i in range(len(xy)):
        x, y = xy[i, 0], xy[i, 1]
        for _ in range(steps):
            fx, fy = _distort_point(x, y, d, M, tilted)
            fx, fy = fx - xy_d[i, 0], fy - xy_d[i, 1]
            # (± 0.0 on the other coordinate: the NumPy version's arithmetic, to the bit)
            px0, px1 = _distort_point(x + h, y + 0.0, d, M, tilted)
            mx0, mx1 = _distort_point(x - h, y - 0.0, d, M, tilted)
            py0, py1 = _distort_point(x + 0.0, y + h, d, M, tilted)
            my0, my1 = _distort_point(x - 0.0, y - h, d, M, tilted)
            jx0, jx1 = (px0 - mx0) / 2e-7, (px1 - mx1) / 2e-7
            jy0, jy1 = (py0 - my0) / 2e-7, (py1 - my1) / 2e-7
            det = jx0 * jy1 - jy0 * jx1
            dx = (jy1 * fx - jy0 * fy) / det
            dy = (-jx1 * fx + jx0 * fy) / det
            x, y = x - dx, y - dy
        out[i, 0], out[i, 1] = x, y
    return out


@compiled_inline
def pixel_in_view(
    X, Y, Z, K, d, M, tilted, distorted, min_depth, field_limit, u_min, u_max, v_min, v_max
):
    """(seen, u, v) of one point in C: seen when it is in front (z > ``min_depth``), within
    the field (normalised radius ≤ ``field_limit``, which rejects a lens's fold-back beyond its
    calibrated field) and imaged within [``u_min``, ``u_max``] × [``v_min``, ``v_max``]; u, v
    its pixel, NaN unless in front and within the field."""
    if not min_depth < Z:
        return False, np.nan, np.nan
    x, y = X / Z, Y / Z
    if not math.sqrt(x * x + y * y) <= field_limit:
        return False, np.nan, np.nan
    u, v = project_point(X, Y, Z, K, d, M, tilted, distorted)
    return u_min <= u <= u_max and v_min <= v <= v_max, u, v


@compiled
def visible_pixels(
    points_C, K, d, M, tilted, distorted, min_depth, field_limit, u_min, u_max, v_min, v_max
):
    """``pixel_in_view`` over points (N,3): whether each is seen (N,) and its pixel (N,2, NaN
    where not in front or beyond the field) — the one visibility test of every system (``geometry.in_view``, the
    circle samples', the model support's), each with its own depth and border conventions."""
    seen = np.zeros(len(points_C), np.bool_)
    uv = np.empty((len(points_C), 2))
    for i in range(len(points_C)):
        seen[i], uv[i, 0], uv[i, 1] = pixel_in_view(
            points_C[i, 0], points_C[i, 1], points_C[i, 2], K, d, M, tilted, distorted,
            min_depth, field_limit, u_min, u_max, v_min, v_max,
        )  # fmt: skip
    return seen, uv
