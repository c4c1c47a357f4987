"""Arc-based ellipse extraction: edges → arcs → grouped arcs → sub-pixel ellipses.

In the spirit of Fornaciari, Prati & Cucchiara, "A fast and effective ellipse detector for
embedded vision applications" (Pattern Recognition 47(11), 2014), with a sub-pixel back end:

1. **Edges.** The image (optionally a region, at a pyramid level that averages the noise down)
   is smoothed with a Gaussian matched to the noise and run through Canny with hysteresis
   thresholds set in units of the gradient noise, so the same settings work at any noise level.
2. **Arcs.** Edge pixels are split by the direction of their gradient into four 90° sectors;
   the 8-connected components of each sector are curve pieces whose normal turns by at most
   90° — on an ellipse, exactly the pieces between its axis-aligned extreme points. A
   parabola fitted in the sector's own frame gives each piece's curvature: straight pieces
   (significance test) and thick blobs are dropped; the curvature's sign against the gradient
   gives the polarity (brighter inside or outside) — the convexity test — and the side of the
   ellipse the arc lies on.
3. **Grouping.** Pairs of arcs of equal polarity on different sides are kept when their
   positions agree with their sides (an arc facing right lies right of one facing left) and
   their circles of curvature overlap; a direct least-squares ellipse through the pair must fit
   both arcs and agree with their gradient directions (the tangent test). The ellipse then
   collects every other arc that lies on it, and is refitted.
4. **Sub-pixel fit and validation.** At full resolution the candidate is sampled along its
   whole curve; edges of its polarity are searched along the normals (``edge_search``); a
   direct fit (Fitzgibbon, Pilu & Fisher 1999) and a geometric refinement (Kanatani) on the
   sub-pixel points are repeated with a narrower window; the ellipse is kept when enough of its
   in-image curve has edge support.

There is no size cap: arcs are local, and validation counts only the part of the curve inside
the image, so ellipses larger than the image (partial arcs at close range) are found as well.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from estimators.conics import (
    Ellipse,
    conic_from_ellipse,
    covered_angle,
    ellipse_angles,
    ellipse_from_conic,
    fit_ellipse_direct,
    fit_ellipse_leaving_out_an_arc,
    major_axis_log_sd,
    refine_ellipse,
    sampson_distances,
)
from estimators.edge_search import search_edges
from estimators.imaging import GradientField, gradient_noise_gain, smoothed_gradient

# Outward unit directions of the four gradient sectors: +x, +y, −x, −y (image axes, y down).
_SECTOR_DIRECTIONS = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])
_CANNY_UNITS = 100.0  # int16 gradient units per gradient-noise std


@dataclass(frozen=True, slots=True)
class ExtractorSettings:
    """Tuning of the extractor (pixels at full resolution unless said otherwise)."""

    level: int = 1  # pyramid level of the arc stage (each level halves the image)
    sigma_px: float = 1.2  # smoothing at that level
    canny_low_snr: float = 2.5
    canny_high_snr: float = 5.0
    min_arc_px: int = 8  # edge pixels per arc, at the arc level
    min_minor_axis_px: float = 6.0
    max_candidates: int = 16
    max_pairs: int = 600
    fine_sigma_px: float = 1.2
    sample_spacing_px: float = 2.0
    search_half_width_px: float = 4.0
    min_support: float = 0.5
    min_arc_angle_rad: float = np.pi / 2
    max_residual_px: float = 1.2
    #: An ellipse whose points fix its major axis no better than this (1σ of log a: 10 %) is
    #: not measured: two short arcs on opposite sides of a thin ellipse — two nearly straight
    #: edges — fit one 1968 px long across a 640 px image (held-out random:117 at 3 m: 28 %,
    #: against ≤ 4 % for every real ellipse of those frames), and a ring read from it lay
    #: 0.28 m away instead of 3 m. (``min_arc_angle_rad`` passes it: 2π less the largest gap
    #: counts two opposite arcs as 199°.)
    max_major_axis_log_sd: float = 0.1


@dataclass(frozen=True, slots=True, eq=False)
class Arc:
    """A piece of edge curve whose normal turns by at most 90°, in full-resolution pixels.

    ``side`` is the sector (0 right, 1 bottom, 2 left, 3 top) of its outward normal on the
    ellipse it belongs to; ``brighter_inside`` its polarity; ``center``/``radius`` its circle
    of curvature; ``gradient`` the unit gradient direction at each point.
    """

    points: np.ndarray
    gradient: np.ndarray
    side: int
    brighter_inside: bool
    midpoint: np.ndarray
    center: np.ndarray
    radius: float


@dataclass(frozen=True, slots=True, eq=False)
class ExtractedEllipse:
    """An ellipse found in the image (pixels; distortion not removed).

    ``points``: the sub-pixel edge points supporting it; ``brighter_inside``: its polarity;
    ``arc_angle``: the parametric angle its support covers (rad, ≤ 2π); ``residual_px``: the
    robust RMS distance of the support to the curve; ``support``: the fraction of the curve
    samples inside the image that found an edge.
    """

    ellipse: Ellipse
    conic: np.ndarray
    points: np.ndarray
    brighter_inside: bool
    arc_angle: float
    residual_px: float
    support: float

    @property
    def polarity(self) -> int:
        """+1 when the intensity rises going outward (darker inside), −1 otherwise."""
        return -1 if self.brighter_inside else 1


# --- arcs -----------------------------------------------------------------------------------


def _edges(gray: np.ndarray, noise_sigma: float, settings: ExtractorSettings):
    smoothed = cv2.GaussianBlur(gray, (0, 0), settings.sigma_px)
    gx = cv2.Sobel(smoothed, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(smoothed, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    noise = max(noise_sigma, 1e-4) * gradient_noise_gain(settings.sigma_px)
    scale = _CANNY_UNITS / noise
    dx = np.clip(gx * scale, -32767, 32767).astype(np.int16)
    dy = np.clip(gy * scale, -32767, 32767).astype(np.int16)
    edges = cv2.Canny(
        dx,
        dy,
        settings.canny_low_snr * _CANNY_UNITS,
        settings.canny_high_snr * _CANNY_UNITS,
        L2gradient=True,
    )
    return edges, gx, gy


def find_arcs(
    gray: np.ndarray,
    noise_sigma: float,
    settings: ExtractorSettings,
    *,
    scale: float = 1.0,
    offset: tuple[float, float] = (0.0, 0.0),
) -> list[Arc]:
    """Arcs of ``gray`` (an image at some pyramid level); coordinates are mapped to the full
    image by ``full = scale·level + (scale − 1)/2 + offset``."""
    edges, gx, gy = _edges(gray, noise_sigma, settings)
    ys, xs = np.nonzero(edges)
    if len(xs) == 0:
        return []
    g = np.column_stack([gx[ys, xs], gy[ys, xs]]).astype(float)
    g /= np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-12)
    angle = np.arctan2(g[:, 1], g[:, 0])
    sector = (np.floor((angle + np.pi / 4) / (np.pi / 2)).astype(int)) % 4
    ids = np.full(len(xs), -1)
    next_id = 0
    mask = np.zeros(edges.shape, np.uint8)
    for k in range(4):
        mask[:] = 0
        in_k = sector == k
        mask[ys[in_k], xs[in_k]] = 1
        count, labels = cv2.connectedComponents(mask, connectivity=8)
        ids[in_k] = labels[ys[in_k], xs[in_k]] - 1 + next_id
        next_id += count - 1
    sizes = np.bincount(ids, minlength=next_id)
    keep = sizes[ids] >= settings.min_arc_px
    if not np.any(keep):
        return []
    xs, ys, g, sector = xs[keep], ys[keep], g[keep], sector[keep]
    _, ids = np.unique(ids[keep], return_inverse=True)
    fits = _fit_arc_parabolas(xs.astype(float), ys.astype(float), ids, sector, settings)
    shift = (scale - 1.0) / 2.0
    to_full = np.array([offset[0] + shift, offset[1] + shift])
    order = np.argsort(ids, kind="stable")
    starts = np.searchsorted(ids[order], np.arange(ids.max() + 1))
    ends = np.append(starts[1:], len(ids))
    points = np.column_stack([xs, ys]).astype(float)[order] * scale + to_full
    gradient = g[order]
    return [
        Arc(
            points[starts[k] : ends[k]],
            gradient[starts[k] : ends[k]],
            int(fits["side"][k]),
            bool(fits["brighter_inside"][k]),
            fits["midpoint"][k] * scale + to_full,
            fits["center"][k] * scale + to_full,
            float(fits["radius"][k] * scale),
        )
        for k in np.flatnonzero(fits["valid"])
    ]


def _fit_arc_parabolas(
    xs: np.ndarray, ys: np.ndarray, ids: np.ndarray, sector: np.ndarray, settings: ExtractorSettings
) -> dict[str, np.ndarray]:
    """For every piece at once: a parabola d = a0 + a1·t + a2·t² in its sector's frame (d along
    the sector's gradient direction, t across it), from per-piece sums. A piece is valid when
    it is long enough, thin (RMS ≤ 1.5 px) and significantly curved (|a2| > 3 standard errors
    and a sagitta ≥ 0.4 px) — the straight-segment rejection."""
    m = int(ids.max()) + 1
    sec = np.zeros(m, int)
    sec[ids] = sector
    d_dir = _SECTOR_DIRECTIONS[sec]
    t_dir = np.column_stack([-d_dir[:, 1], d_dir[:, 0]])
    t = xs * t_dir[ids, 0] + ys * t_dir[ids, 1]
    d = xs * d_dir[ids, 0] + ys * d_dir[ids, 1]
    n = np.bincount(ids, minlength=m).astype(float)
    t_mean = np.bincount(ids, weights=t, minlength=m) / n
    tc = t - t_mean[ids]

    def total(values: np.ndarray) -> np.ndarray:
        return np.bincount(ids, weights=values, minlength=m)

    s1, s2, s3, s4 = total(tc), total(tc**2), total(tc**3), total(tc**4)
    normal = np.stack(
        [np.stack([n, s1, s2], -1), np.stack([s1, s2, s3], -1), np.stack([s2, s3, s4], -1)], 1
    )
    rhs = np.stack([total(d), total(d * tc), total(d * tc**2)], -1)
    valid = n >= settings.min_arc_px
    det = np.linalg.det(normal)
    valid &= np.abs(det) > 1e-9
    normal[~valid] = np.eye(3)
    rhs[~valid] = 0.0
    coefficients = np.linalg.solve(normal, rhs[..., None])[..., 0]
    inverse = np.linalg.inv(normal)
    a0, a1, a2 = coefficients.T
    residual = d - (a0[ids] + a1[ids] * tc + a2[ids] * tc**2)
    rms = np.sqrt(total(residual**2) / n)
    t_min = np.full(m, np.inf)
    t_max = np.full(m, -np.inf)
    np.minimum.at(t_min, ids, tc)
    np.maximum.at(t_max, ids, tc)
    span = t_max - t_min
    se_a2 = np.maximum(rms, 0.3) * np.sqrt(np.abs(inverse[:, 2, 2]))
    sagitta = np.abs(a2) * (span / 2.0) ** 2
    valid &= span >= 0.6 * settings.min_arc_px
    valid &= rms <= 1.5  # thicker pieces are blobs or branches, not curves
    valid &= (np.abs(a2) >= 3.0 * se_a2) & (sagitta >= 0.4)
    a2 = np.where(valid, a2, 1.0)
    radius = (1.0 + a1**2) ** 1.5 / (2.0 * np.abs(a2))
    normal_td = np.column_stack([-a1, np.ones(m)]) / np.hypot(a1, 1.0)[:, None]
    midpoint = t_mean[:, None] * t_dir + a0[:, None] * d_dir
    to_centre = normal_td[:, :1] * t_dir + normal_td[:, 1:] * d_dir
    center = midpoint + (np.sign(a2) * radius)[:, None] * to_centre
    # The gradient points along +d; with the centre on the +d side (a2 > 0) the intensity
    # rises toward the centre: brighter inside. The arc's side is its outward normal's sector.
    brighter_inside = a2 > 0
    side = np.where(brighter_inside, (sec + 2) % 4, sec)
    return {
        "valid": valid,
        "side": side,
        "brighter_inside": brighter_inside,
        "midpoint": midpoint,
        "center": center,
        "radius": radius,
    }


# --- grouping -------------------------------------------------------------------------------


def _outward_normals(Q: np.ndarray, points: np.ndarray) -> np.ndarray:
    h = np.column_stack([points, np.ones(len(points))])
    n = (h @ Q)[:, :2]
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def group_arcs(
    arcs: list[Arc], settings: ExtractorSettings, *, tolerance_px: float
) -> list[tuple[np.ndarray, tuple[int, ...]]]:
    """Candidate ellipses (conic, arc indices) from pairs of arcs grown by every arc on them,
    longest support first."""
    n = len(arcs)
    if n < 2:
        return []
    side = np.array([a.side for a in arcs])
    bright = np.array([a.brighter_inside for a in arcs])
    mid = np.array([a.midpoint for a in arcs])
    centre = np.array([a.center for a in arcs])
    radius = np.array([a.radius for a in arcs])
    length = np.array([len(a.points) for a in arcs])
    outward = _SECTOR_DIRECTIONS[side]
    i, j = np.triu_indices(n, k=1)
    ok = (bright[i] == bright[j]) & (side[i] != side[j])
    ok &= np.einsum("ij,ij->i", mid[i] - mid[j], outward[i] - outward[j]) > 0
    overlap = np.linalg.norm(centre[i] - centre[j], axis=1) / (radius[i] + radius[j])
    ok &= overlap <= 1.0
    i, j, overlap = i[ok], j[ok], overlap[ok]
    order = np.argsort(overlap)[: settings.max_pairs]
    # A few points of every arc (with their outward gradient directions) test agreement with a
    # hypothesis for all arcs at once.
    sub = [np.linspace(0, len(a.points) - 1, min(len(a.points), 24)).astype(int) for a in arcs]
    points = np.vstack([a.points[k] for a, k in zip(arcs, sub, strict=True)])
    directions = np.vstack(
        [
            a.gradient[k] * (-1.0 if a.brighter_inside else 1.0)
            for a, k in zip(arcs, sub, strict=True)
        ]
    )
    owner = np.concatenate([np.full(len(k), m) for m, k in enumerate(sub)])
    counts = np.bincount(owner, minlength=n).astype(float)

    def agreement(Q: np.ndarray) -> np.ndarray:
        """Per arc: True when ≥ 70 % of its points lie on Q and its gradients agree with Q's
        normals (mean cosine ≥ 0.7) — the tangent test."""
        close = np.abs(sampson_distances(Q, points)) <= tolerance_px
        cosine = np.einsum("ij,ij->i", _outward_normals(Q, points), directions)
        fraction = np.bincount(owner, weights=close.astype(float), minlength=n) / counts
        mean_cosine = np.bincount(owner, weights=cosine, minlength=n) / counts
        return (fraction >= 0.7) & (mean_cosine >= 0.7)

    candidates: dict[tuple[int, ...], np.ndarray] = {}
    explained: list[set[int]] = []
    for a, b in zip(i[order], j[order], strict=True):
        if any(a in group and b in group for group in explained):
            continue
        try:
            Q = fit_ellipse_direct(points[(owner == a) | (owner == b)])
            e = ellipse_from_conic(Q)
        except ValueError:
            continue
        if e.b < settings.min_minor_axis_px / 2:
            continue
        on_curve = agreement(Q) & (bright == bright[a])
        if not (on_curve[a] and on_curve[b]):
            continue
        members = tuple(int(k) for k in np.flatnonzero(on_curve))
        explained.append(set(members))
        if len(members) > 2:
            try:
                Q = fit_ellipse_direct(np.vstack([arcs[k].points for k in members]))
                ellipse_from_conic(Q)
            except ValueError:
                continue
        candidates[members] = Q
    # Drop candidates whose arcs are a subset of another's; longest support first.
    keys = sorted(candidates, key=lambda k: -int(length[list(k)].sum()))
    kept: list[tuple[int, ...]] = []
    for k in keys:
        if not any(set(k) <= set(other) for other in kept):
            kept.append(k)
    return [(candidates[k], k) for k in kept]


# --- sub-pixel fit and validation -----------------------------------------------------------


def ellipse_samples(
    e: Ellipse, spacing_px: float, max_count: int = 3000
) -> tuple[np.ndarray, np.ndarray]:
    """Points (N,2) every ~``spacing_px`` along an ellipse and their outward unit normals."""
    perimeter = np.pi * (3 * (e.a + e.b) - np.sqrt((3 * e.a + e.b) * (e.a + 3 * e.b)))
    count = int(np.clip(perimeter / spacing_px, 12, max_count))
    t = np.linspace(0.0, 2.0 * np.pi, count, endpoint=False)
    c, s = np.cos(e.angle), np.sin(e.angle)
    x, y = e.a * np.cos(t), e.b * np.sin(t)
    points = np.column_stack([e.cx + c * x - s * y, e.cy + s * x + c * y])
    nx, ny = np.cos(t) / e.a, np.sin(t) / e.b  # gradient of x²/a² + y²/b² (halved)
    normals = np.column_stack([c * nx - s * ny, s * nx + c * ny])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return points, normals


def fit_ellipse_subpixel(
    field: GradientField,
    initial: Ellipse,
    polarity: int,
    settings: ExtractorSettings,
    *,
    half_width_px: float | None = None,
    rounds: int = 2,
) -> ExtractedEllipse | None:
    """Sub-pixel ellipse near ``initial``: search edges of ``polarity`` along its normals, fit
    (direct, then geometric), repeat with a narrower window; None if it lacks support."""
    e = initial
    width = settings.search_half_width_px if half_width_px is None else half_width_px
    h, w = field.shape
    margin = 2.0
    for round_index in range(rounds):
        points, normals = ellipse_samples(e, settings.sample_spacing_px)
        reach = width + margin
        inside = (
            (points[:, 0] >= field.x0 + reach)
            & (points[:, 0] <= field.x0 + w - 1 - reach)
            & (points[:, 1] >= field.y0 + reach)
            & (points[:, 1] <= field.y0 + h - 1 - reach)
        )
        if inside.sum() < 12:
            return None
        hits = search_edges(field, points[inside], normals[inside], polarity, width)
        # Cheap early exit: a candidate without support is not worth fitting.
        if hits.count < 8 or hits.count < 0.7 * settings.min_support * inside.sum():
            return None
        found = hits.uv[hits.found]
        try:
            e = ellipse_from_conic(fit_ellipse_leaving_out_an_arc(found))
            if round_index == rounds - 1:  # geometric refinement once, on the final points
                e, residuals, sigma = refine_ellipse(found, e, iterations=3)
        except ValueError:
            return None
        if e.b < settings.min_minor_axis_px / 2:
            return None
        width = max(2.0, width / 2.0)
    support = hits.count / int(inside.sum())
    inliers = np.abs(residuals) <= 3.0 * sigma
    arc_angle = covered_angle(ellipse_angles(e, found[inliers]))
    residual = float(np.sqrt(np.mean(residuals[inliers] ** 2))) if inliers.any() else np.inf
    if (
        support < settings.min_support
        or arc_angle < settings.min_arc_angle_rad
        or residual > settings.max_residual_px
        or major_axis_log_sd(found[inliers], e, sigma) > settings.max_major_axis_log_sd
    ):
        return None
    return ExtractedEllipse(
        ellipse=e,
        conic=conic_from_ellipse(e),
        points=found[inliers],
        brighter_inside=polarity < 0,
        arc_angle=arc_angle,
        residual_px=residual,
        support=support,
    )


def _same_ellipse(a: Ellipse, b: Ellipse) -> bool:
    size = max(a.a, b.a)
    return (
        np.hypot(a.cx - b.cx, a.cy - b.cy) < 0.05 * size + 1.0
        and abs(a.a - b.a) < 0.05 * size + 1.0
        and abs(a.b - b.b) < 0.05 * size + 1.0
    )


def extract_ellipses(
    gray: np.ndarray,
    noise_sigma: float,
    *,
    roi: tuple[int, int, int, int] | None = None,
    settings: ExtractorSettings | None = None,
    field: GradientField | None = None,
    reduced: np.ndarray | None = None,
) -> list[ExtractedEllipse]:
    """Ellipses in ``gray`` (float32 mono in [0, 1]) or in its ``roi`` = (x0, y0, x1, y1).

    ``noise_sigma`` is the image noise std as the pixels show it (``ImageStack.noise_sigma``); ``field``
    an already computed full-resolution gradient (at ``settings.fine_sigma_px``) to reuse,
    ``reduced`` the whole image already reduced to the arc stage's level (``roi`` None).
    Returns validated ellipses, best supported first.
    """
    settings = settings or ExtractorSettings()
    height, width = gray.shape
    x0, y0, x1, y1 = (0, 0, width, height) if roi is None else roi
    x0, y0 = max(0, int(x0)), max(0, int(y0))
    x1, y1 = min(width, int(x1)), min(height, int(y1))
    if x1 - x0 < 16 or y1 - y0 < 16:
        return []
    region = gray[y0:y1, x0:x1]
    scale = 2**settings.level
    level_image = region
    level_noise = noise_sigma / scale  # block averages of independent pixels
    if reduced is not None and roi is None:
        level_image = reduced
    else:
        for _ in range(settings.level):
            level_image = cv2.resize(
                level_image,
                (level_image.shape[1] // 2, level_image.shape[0] // 2),
                interpolation=cv2.INTER_AREA,
            )
    arcs = find_arcs(level_image, level_noise, settings, scale=scale, offset=(x0, y0))
    groups = group_arcs(arcs, settings, tolerance_px=1.5 * scale)
    if field is None:
        field = smoothed_gradient(gray, settings.fine_sigma_px, noise_sigma, (x0, y0, x1, y1))
    found: list[ExtractedEllipse] = []
    for Q, members in groups[: settings.max_candidates]:
        polarity = -1 if arcs[members[0]].brighter_inside else 1
        try:
            initial = ellipse_from_conic(Q)
        except ValueError:
            continue
        result = fit_ellipse_subpixel(
            field, initial, polarity, settings, half_width_px=settings.search_half_width_px + scale
        )
        if result is None:
            continue
        duplicate = next(
            (
                k
                for k, other in enumerate(found)
                if other.brighter_inside == result.brighter_inside
                and _same_ellipse(other.ellipse, result.ellipse)
            ),
            None,
        )
        if duplicate is None:
            found.append(result)
        elif len(result.points) > len(found[duplicate].points):
            found[duplicate] = result
    found.sort(key=lambda x: -len(x.points))
    return found
