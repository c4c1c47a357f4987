"""Sub-pixel refinement of point features by fitting an intensity model to the raw pixels.

Under additive Gaussian noise the maximum-likelihood position of a feature whose appearance is
known up to two grey levels is the least-squares fit of that appearance to the pixels (the
estimator that attains the Cramér–Rao bound, cf. ../shared/LIMITS.md). Two models:

* a disc (bolt head or hole) of known metric radius, seen through the local affine map A
  (px per metre) of its plane: I(x) = b + (a − b)·Φ(ρ(x)/s), ρ the signed distance (px) from
  the disc's rim, positive inside. A head standing proud of its surface is a short cylinder:
  off the optical axis its wall shows between the top disc and the base disc, whose image is
  the top's shifted by ``extrusion`` (px). The model is then the top disc over the stadium
  (the top swept to the base) with the wall's own grey level c:
  I = a·Φ(ρ_top/s) + c·[Φ(ρ_stadium/s) − Φ(ρ_top/s)] + b·[1 − Φ(ρ_stadium/s)], and the fitted
  position is the top's centre whatever the wall's shading;
* a corner (wedge) of two straight edges through c: I(x) = b + (a − b)·Φ(d₁/s)·Φ(d₂/s), d_k the
  signed distance from edge k, positive on the inner side.

Φ is the normal CDF with s = 0.45 px, standing in for pixel area sampling (an aliased renderer
averages to the same ramp). The smooth model is fitted to the *unsmoothed* pixels: smoothing
first would correlate the noise and bias the covariance. Gauss–Newton on all parameters
(position, shape, the grey levels) for all features at once; the covariance is σ²·(JᵀJ)⁻¹
with σ² from each feature's residuals. Given the image noise σ (``noise_sigma``), the fits
maximise the likelihood of noise clipped at black and white instead (Fisher scoring with the
terms of ``estimators.imaging.clipped_likelihood_terms``): a dark panel or hole loses a third
of its noise to the clip at low noise, and a least-squares wedge then neither fits nor
converges.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from scipy.special import ndtr

from estimators.imaging import clipped_likelihood_terms, clipped_moments

EDGE_WIDTH_PX = 0.45
_SQRT_2PI = math.sqrt(2.0 * math.pi)


@dataclass(frozen=True, slots=True, eq=False)
class PointFits:
    """Fitted positions (N,2 px) and covariances (N,2,2), grey levels inside/outside and the
    contrast's standard deviation, residual noise, pixels used, and whether each fit is usable
    (converged, finite, enough pixels)."""

    uv: np.ndarray
    covariance: np.ndarray
    inside: np.ndarray
    outside: np.ndarray
    contrast_sigma: np.ndarray
    noise_sigma: np.ndarray
    pixels_used: np.ndarray
    ok: np.ndarray

    @property
    def contrast(self) -> np.ndarray:
        return self.inside - self.outside

    @property
    def contrast_snr(self) -> np.ndarray:
        """(inside − outside) / its standard deviation."""
        return self.contrast / np.maximum(self.contrast_sigma, 1e-12)


def fit_discs(
    pixels: np.ndarray,
    centers_uv: np.ndarray,
    A_px_per_m: np.ndarray,
    radius_m: np.ndarray,
    window_m: np.ndarray,
    *,
    extrusion_px: np.ndarray | None = None,
    iterations: int = 4,
    noise_sigma: float = 0.0,
) -> PointFits:
    """Refine disc centres (N,2 px) by fitting a disc of metric radius ``radius_m`` (N,) seen
    through the local affine maps ``A_px_per_m`` (N,2,2) of its plane, using the pixels within
    ``window_m`` (N,) of the centre (metres in the disc's plane; keep it clear of other
    structure). ``extrusion_px`` (N,2): for heads standing proud of their surface, the image
    vector from the top's centre to the base's (the wall's grey level is then fitted too, see
    the module docstring); None for flat discs. ``noise_sigma``: the image noise, for the
    clipped likelihood (0: least squares). Starts may be off by about a pixel: the first
    iterations use a wider edge (coarse to fine). All discs are fitted together on one flat
    array of their pixels."""
    centers = np.asarray(centers_uv, dtype=float).reshape(-1, 2)
    n = len(centers)
    fits = _empty_fits(n)
    if n == 0:
        return fits
    A = np.asarray(A_px_per_m, dtype=float).reshape(n, 2, 2)
    radius = np.asarray(radius_m, dtype=float).reshape(n)
    window = np.asarray(window_m, dtype=float).reshape(n)
    A_inv = np.linalg.inv(A)
    scale = np.sqrt(np.abs(np.linalg.det(A)))  # px per metre, geometric mean
    extrusion = np.zeros((n, 2)) if extrusion_px is None else np.asarray(extrusion_px, float)
    extrusion = np.nan_to_num(extrusion.reshape(n, 2))
    e_m = np.einsum("nij,nj->ni", A_inv, extrusion)  # metres in the disc plane
    e_m2 = np.maximum(np.sum(e_m * e_m, axis=1), 1e-30)
    h, w = pixels.shape
    # Flat pixel list: every pixel within the window (plus the start's uncertainty) of a start.
    reach = window * np.linalg.norm(A, ord=2, axis=(1, 2)) + 1.5
    reach += np.linalg.norm(extrusion, axis=1)
    owner, u_int, v_int = _pixels_within(centers, reach, h, w)
    u = u_int.astype(float)
    v = v_int.astype(float)
    values = pixels[v_int, u_int].astype(float)
    a11, a12, a21, a22 = (A_inv[owner, i, j] for i, j in ((0, 0), (0, 1), (1, 0), (1, 1)))
    ex, ey, ee = e_m[owner, 0], e_m[owner, 1], e_m2[owner]
    sc = scale[owner]
    rad_px = radius[owner] * sc
    win = window[owner]

    def model(c: np.ndarray, s: float):
        """Top-disc and stadium coverages, their slopes and ∂ρ/∂c, and the window mask."""
        du = u - c[owner, 0]
        dv = v - c[owner, 1]
        wx = a11 * du + a12 * dv  # metres in the disc plane
        wy = a21 * du + a22 * dv
        d = np.sqrt(wx * wx + wy * wy)
        z = (rad_px - d * sc) / s
        inv_d = sc / np.maximum(d, 1e-12)
        # ∂ρ/∂c = scale · A⁻ᵀ ŵ
        gx = (a11 * wx + a21 * wy) * inv_d
        gy = (a12 * wx + a22 * wy) * inv_d
        # The stadium: distance to the segment from the top's centre to the base's.
        t = np.clip((wx * ex + wy * ey) / ee, 0.0, 1.0)
        qx, qy = wx - t * ex, wy - t * ey
        dq = np.sqrt(qx * qx + qy * qy)
        zq = (rad_px - dq * sc) / s
        inv_q = sc / np.maximum(dq, 1e-12)
        hx = (a11 * qx + a21 * qy) * inv_q
        hy = (a12 * qx + a22 * qy) * inv_q
        top, stadium = ndtr(z), ndtr(zq)
        slope_top = np.exp(-0.5 * z * z) / (_SQRT_2PI * s)
        slope_stadium = np.exp(-0.5 * zq * zq) / (_SQRT_2PI * s)
        return top, stadium, slope_top, slope_stadium, (gx, gy), (hx, hy), d < win

    def sums(x: np.ndarray, mask: np.ndarray) -> np.ndarray:
        return np.bincount(owner, x * mask, minlength=n)

    def levels(top, stadium, mask, current=None):
        """Grey levels (top a, surroundings b, wall c) by linear least squares — or, from
        ``current`` with a noise σ, a scoring step on the clipped likelihood. The wall's level
        is tied to the top's (the same material): weakly without σ (decisive only where the
        wall does not show); with σ by a prior of sd |a − b|/2 — a wall a fraction of a pixel
        wide barely shows its own grey, and a free one trades with the centre at high noise."""
        basis = (top, 1.0 - stadium, stadium - top)
        if current is None or noise_sigma <= 0:
            score, info = values, np.ones_like(values)
            start = np.zeros((n, 3))
        else:
            start = np.column_stack(current)
            model_values = sum(start[owner, i] * basis[i] for i in range(3))
            score, info = clipped_likelihood_terms(values, model_values, noise_sigma)
        G = np.zeros((n, 3, 3))
        t = np.zeros((n, 3))
        for i in range(3):
            t[:, i] = sums(basis[i] * score, mask)
            for j in range(i, 3):
                G[:, i, j] = G[:, j, i] = sums(info * basis[i] * basis[j], mask)
        tie = 1e-3 * np.maximum(sums(info, mask), 1e-9)
        if current is not None and noise_sigma > 0:
            tie = 1.0 / np.maximum((start[:, 0] - start[:, 1]) / 2.0, 1e-3) ** 2
        t[:, 0] -= tie * (start[:, 0] - start[:, 2])
        t[:, 2] += tie * (start[:, 0] - start[:, 2])
        G[:, 0, 0] += tie
        G[:, 2, 2] += tie
        G[:, 0, 2] -= tie
        G[:, 2, 0] -= tie
        G += 1e-12 * np.eye(3)
        x = start + np.linalg.solve(G, t[..., None])[..., 0]
        return x[:, 0], x[:, 1], x[:, 2]

    c = centers.copy()
    a = np.zeros(n)
    b = np.zeros(n)
    wall = np.zeros(n)
    current = None
    schedule = [(1.2, 2), (0.7, 1), (EDGE_WIDTH_PX, iterations)]
    last_step = np.full(n, np.inf)
    for s, count in schedule:
        for _ in range(count):
            top, stadium, slope_t, slope_s, (gx, gy), (hx, hy), mask = model(c, s)
            mask = mask.astype(float)
            a, b, wall = levels(top, stadium, mask, current)
            current = (a, b, wall)
            predicted = a[owner] * top + b[owner] * (1.0 - stadium) + wall[owner] * (stadium - top)
            score, info = clipped_likelihood_terms(values, predicted, noise_sigma)
            k_top = (a - wall)[owner] * slope_t
            k_stadium = (wall - b)[owner] * slope_s
            jx, jy = k_top * gx + k_stadium * hx, k_top * gy + k_stadium * hy
            hxx, hxy, hyy = (
                sums(info * jx * jx, mask),
                sums(info * jx * jy, mask),
                sums(info * jy * jy, mask),
            )
            gxr, gyr = sums(jx * score, mask), sums(jy * score, mask)
            det2 = hxx * hyy - hxy * hxy
            det2 = np.where(np.abs(det2) < 1e-18 * np.maximum(hxx * hyy, 1e-30), np.nan, det2)
            step = np.column_stack([(hyy * gxr - hxy * gyr) / det2, (hxx * gyr - hxy * gxr) / det2])
            step = np.nan_to_num(step)
            norm = np.linalg.norm(step, axis=1, keepdims=True)
            step = np.where(norm > 1.0, step / np.maximum(norm, 1e-12), step)
            c = c + step
            last_step = norm[:, 0]
    # Statistics at the solution: covariance of centre and grey levels (and the wall's level
    # where it shows).
    top, stadium, slope_t, slope_s, (gx, gy), (hx, hy), mask = model(c, EDGE_WIDTH_PX)
    mask = mask.astype(float)
    r = values - a[owner] * top - b[owner] * (1.0 - stadium) - wall[owner] * (stadium - top)
    k_top = (a - wall)[owner] * slope_t
    k_stadium = (wall - b)[owner] * slope_s
    walled = np.linalg.norm(extrusion, axis=1) >= 0.05
    columns = [k_top * gx + k_stadium * hx, k_top * gy + k_stadium * hy, top, 1.0 - stadium]
    if np.any(walled):
        columns.append(np.where(walled[owner], stadium - top, 0.0))
    J = np.stack(columns, axis=1)
    weights, sigma2 = _clipped_statistics(
        values, values - r, noise_sigma, owner, mask, n, J.shape[1]
    )
    used = np.bincount(owner, mask, minlength=n)
    ok = (used >= 12) & np.all(np.isfinite(c), axis=1) & np.isfinite(a) & np.isfinite(b)
    fits = _point_fits(
        J, r, owner, weights, used, c, a, b, ok, contrast_columns=(2, 3), sigma2=sigma2
    )
    return _converged(fits, last_step)


def _converged(fits: PointFits, last_step: np.ndarray) -> PointFits:
    """``fits`` with ``ok`` also requiring convergence: the last step under 0.1 px or under
    half the position's own standard deviation (with little contrast the fit settles only to
    within its noise)."""
    sigma = np.sqrt(np.maximum(np.trace(np.nan_to_num(fits.covariance), axis1=1, axis2=2), 0.0))
    settled = (last_step < 0.1) | (last_step < 0.5 * sigma)
    return replace(fits, ok=fits.ok & settled)


def _clipped_statistics(
    values: np.ndarray,
    predicted: np.ndarray,
    noise_sigma: float,
    owner: np.ndarray,
    mask: np.ndarray | float,
    n: int,
    k: int,
) -> tuple[np.ndarray | float, np.ndarray | None]:
    """Covariance weights and per-feature σ² of fits to pixels with clipped noise (None and
    the mask without a noise σ: least squares). Each pixel weighs its clipped likelihood's
    information relative to an unclipped pixel's; σ² is the noise's, raised by how much the
    residuals exceed what clipped noise of that σ leaves (the misfit of the model) — never
    the residuals' own spread, which clipping shrinks."""
    if noise_sigma <= 0:
        return mask, None
    _, info = clipped_likelihood_terms(values, predicted, noise_sigma)
    mean, variance, _ = clipped_moments(predicted, noise_sigma)
    weights = mask * np.ones_like(values)
    seen = np.bincount(owner, (values - mean) ** 2 * weights, minlength=n)
    expected = np.bincount(owner, variance * weights, minlength=n)
    count = np.bincount(owner, weights, minlength=n)
    ratio = seen / np.maximum(expected, 1e-12) * count / np.maximum(count - k, 1)
    return weights * info * noise_sigma**2, noise_sigma**2 * np.maximum(ratio, 1.0)


def _point_fits(
    J: np.ndarray,
    r: np.ndarray,
    owner: np.ndarray,
    weights: np.ndarray | float,
    used: np.ndarray,
    uv: np.ndarray,
    inside: np.ndarray,
    outside: np.ndarray,
    ok: np.ndarray,
    *,
    contrast_columns: tuple[int, int],
    sigma2: np.ndarray | None = None,
) -> PointFits:
    """Statistics of N per-feature least-squares fits at their solution: the Gauss–Newton
    covariance s²·(JᵀJ)⁻¹ of each feature's parameters from its pixels' Jacobian rows ``J``
    (M,k) and residuals ``r`` (M,) (pixel m belongs to feature ``owner[m]``, weighted by
    ``weights``), with s² the residual variance over ``used − k`` degrees of freedom. The
    first two parameters are the image position; ``contrast_columns`` are the inside and
    outside grey levels. ``ok`` is and-ed with a positive position variance. ``sigma2`` (N,),
    when given, replaces s² (fits with clipped noise, ``_clipped_statistics``)."""
    n, k = len(uv), J.shape[1]

    def sums(x: np.ndarray) -> np.ndarray:
        return np.bincount(owner, x * weights, minlength=n)

    H = np.zeros((n, k, k))
    for i in range(k):
        for j in range(i, k):
            H[:, i, j] = H[:, j, i] = sums(J[:, i] * J[:, j])
    if sigma2 is None:
        sigma2 = sums(r * r) / np.maximum(used - k, 1)
    H += 1e-12 * np.eye(k)
    try:
        cov = np.linalg.inv(H) * sigma2[:, None, None]
    except np.linalg.LinAlgError:
        cov = np.linalg.pinv(H) * sigma2[:, None, None]
    i, j = contrast_columns
    contrast_var = cov[:, i, i] + cov[:, j, j] - 2.0 * cov[:, i, j]
    return PointFits(
        uv=uv,
        covariance=0.5 * (cov[:, :2, :2] + cov[:, :2, :2].transpose(0, 2, 1)),
        inside=inside,
        outside=outside,
        contrast_sigma=np.sqrt(np.maximum(contrast_var, 0.0)),
        noise_sigma=np.sqrt(sigma2),
        pixels_used=used,
        ok=ok & (cov[:, 0, 0] > 0) & (cov[:, 1, 1] > 0),
    )


def _pixels_within(centers: np.ndarray, reach: np.ndarray, height: int, width: int):
    """(owner, u, v) of every in-image pixel within ``reach`` (N,) px of each centre (N,2),
    as flat integer arrays — one vectorised pass over a common square."""
    r = math.ceil(float(np.max(reach)))
    dv, du = np.mgrid[-r : r + 1, -r : r + 1]
    base = np.round(centers).astype(int)
    u = base[:, 0:1] + du.reshape(1, -1)
    v = base[:, 1:2] + dv.reshape(1, -1)
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    inside &= (u - centers[:, 0:1]) ** 2 + (v - centers[:, 1:2]) ** 2 <= reach[:, None] ** 2
    owner = np.broadcast_to(np.arange(len(centers))[:, None], u.shape)
    return owner[inside], u[inside], v[inside]


def _empty_fits(n: int) -> PointFits:
    return PointFits(
        uv=np.full((n, 2), np.nan),
        covariance=np.full((n, 2, 2), np.nan),
        inside=np.full(n, np.nan),
        outside=np.full(n, np.nan),
        contrast_sigma=np.full(n, np.nan),
        noise_sigma=np.full(n, np.nan),
        pixels_used=np.zeros(n),
        ok=np.zeros(n, dtype=bool),
    )


def fit_corners(
    pixels: np.ndarray,
    corners_uv: np.ndarray,
    edge_directions: np.ndarray,
    window_px: np.ndarray,
    keep: Callable[[np.ndarray], np.ndarray] | None = None,
    *,
    iterations: int = 4,
    noise_sigma: float = 0.0,
) -> PointFits:
    """Refine wedge corners (N,2 px) whose two edges leave the corner along the unit image
    directions ``edge_directions`` (N,2,2); both edge angles are fitted too. Pixels within
    ``window_px`` (N,) of the start are used, less those ``keep(coords (P,2)) -> bool (P,)``
    rejects (other features inside the window). ``noise_sigma``: the image noise, for the
    clipped likelihood (0: least squares)."""
    corners = np.asarray(corners_uv, dtype=float).reshape(-1, 2)
    n = len(corners)
    if n == 0:
        return _empty_fits(0)
    dirs = np.asarray(edge_directions, dtype=float).reshape(n, 2, 2)
    window = np.asarray(window_px, dtype=float).reshape(n)
    h, w = pixels.shape
    owner, u_int, v_int = _pixels_within(corners, window, h, w)
    coords = np.column_stack([u_int, v_int]).astype(float)
    if keep is not None and len(coords):
        kept = keep(coords)
        owner, u_int, v_int, coords = owner[kept], u_int[kept], v_int[kept], coords[kept]
    values = pixels[v_int, u_int].astype(float)
    # Orientation: the interior lies on the side of edge 1 toward edge 2 and vice versa.
    cross = dirs[:, 0, 0] * dirs[:, 1, 1] - dirs[:, 0, 1] * dirs[:, 1, 0]
    side = np.where(cross >= 0, 1.0, -1.0)[owner]
    params = np.column_stack([corners, np.arctan2(dirs[:, :, 1], dirs[:, :, 0])])

    def sums(x: np.ndarray) -> np.ndarray:
        return np.bincount(owner, x, minlength=n)

    def terms(p: np.ndarray, s: float):
        x = coords[:, 0] - p[owner, 0]
        y = coords[:, 1] - p[owner, 1]
        c1, s1 = np.cos(p[owner, 2]), np.sin(p[owner, 2])
        c2, s2 = np.cos(p[owner, 3]), np.sin(p[owner, 3])
        # Normals: edge 1 turned +90° and edge 2 turned −90°, times side, point inside.
        n1x, n1y = -s1 * side, c1 * side
        n2x, n2y = s2 * side, -c2 * side
        d1 = (x * n1x + y * n1y) / s
        d2 = (x * n2x + y * n2y) / s
        f1, f2 = ndtr(d1), ndtr(d2)
        p1 = np.exp(-0.5 * d1 * d1) / (_SQRT_2PI * s)
        p2 = np.exp(-0.5 * d2 * d2) / (_SQRT_2PI * s)
        inside = f1 * f2
        # ∂inside/∂(u, v, α1, α2): ∂d_k/∂c = −n_k; ∂d1/∂α1 = −side·x·e1; ∂d2/∂α2 = side·x·e2
        g_u = -(p1 * f2 * n1x + f1 * p2 * n2x)
        g_v = -(p1 * f2 * n1y + f1 * p2 * n2y)
        g_a1 = p1 * f2 * (-side) * (x * c1 + y * s1)
        g_a2 = f1 * p2 * side * (x * c2 + y * s2)
        return inside, np.stack([g_u, g_v, g_a1, g_a2], axis=1)

    def levels(inside: np.ndarray, current=None):
        """Grey levels by linear least squares, or a scoring step on the clipped likelihood
        from ``current`` when the noise σ is given."""
        other = 1.0 - inside
        if current is None or noise_sigma <= 0:
            score, info, a0, b0 = values, np.ones_like(values), np.zeros(n), np.zeros(n)
        else:
            a0, b0 = current
            score, info = clipped_likelihood_terms(
                values, b0[owner] + (a0 - b0)[owner] * inside, noise_sigma
            )
        s11, s12 = sums(info * inside * inside), sums(info * inside * other)
        s22 = sums(info * other * other)
        t1, t2 = sums(inside * score), sums(other * score)
        det = s11 * s22 - s12 * s12
        det = np.where(np.abs(det) < 1e-12 * np.maximum(s11 * s22, 1e-30), np.nan, det)
        return a0 + (s22 * t1 - s12 * t2) / det, b0 + (s11 * t2 - s12 * t1) / det

    max_step = np.array([1.0, 1.0, 0.05, 0.05])
    last_step = np.full(n, np.inf)
    current = None
    for s, count in ((1.2, 1), (0.7, 1), (EDGE_WIDTH_PX, iterations)):
        for _ in range(count):
            inside, g = terms(params, s)
            a, b = levels(inside, current)
            current = (a, b)
            score, info = clipped_likelihood_terms(
                values, b[owner] + (a - b)[owner] * inside, noise_sigma
            )
            J = (a - b)[owner][:, None] * g
            H = np.zeros((n, 4, 4))
            for i in range(4):
                for j in range(i, 4):
                    H[:, i, j] = H[:, j, i] = sums(info * J[:, i] * J[:, j])
            grad = np.stack([sums(J[:, i] * score) for i in range(4)], axis=1)
            H += 1e-9 * np.eye(4)
            try:
                step = np.linalg.solve(H, grad[..., None])[..., 0]
            except np.linalg.LinAlgError:
                step = (np.linalg.pinv(H) @ grad[..., None])[..., 0]
            step = np.nan_to_num(step)
            ratio = np.max(np.abs(step) / max_step, axis=1, keepdims=True)
            step = np.where(ratio > 1.0, step / np.maximum(ratio, 1e-12), step)
            params = params + step
            last_step = np.linalg.norm(step[:, :2], axis=1)
    # Statistics: covariance of all six parameters (corner, angles, grey levels).
    inside, g = terms(params, EDGE_WIDTH_PX)
    a, b = levels(inside, current)
    r = values - b[owner] - (a - b)[owner] * inside
    J = np.column_stack([(a - b)[owner][:, None] * g, inside, 1.0 - inside])
    used = np.bincount(owner, minlength=n).astype(float)
    ok = (used >= 24) & np.all(np.isfinite(params), axis=1) & np.isfinite(a) & np.isfinite(b)
    weights, sigma2 = _clipped_statistics(
        values, values - r, noise_sigma, owner, np.ones_like(values), n, J.shape[1]
    )
    fits = _point_fits(
        J,
        r,
        owner,
        weights,
        used,
        params[:, :2].copy(),
        a,
        b,
        ok,
        contrast_columns=(4, 5),
        sigma2=sigma2,
    )
    return _converged(fits, last_step)
