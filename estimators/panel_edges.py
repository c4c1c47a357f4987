"""The panel's four edges to sub-pixel accuracy: strips along predicted edges → edge points →
robust lines → corners (intersections of neighbouring lines).

Predicted edges come from a pose (the prior; curved when the lens distorts) or from a
quadrilateral found in the image (acquisition). Edge points are measured in image pixels and
converted to ideal (undistorted pinhole) pixels, where the edges are straight, before lines are
fitted — so lens distortion never bends a fitted line.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from estimators.compiled import compiled, compiled_inline
from estimators.edge_fit import EdgePoints, Line2D, fit_edge_points, fit_line_robust, intersect
from estimators.frame import CameraInfo
from estimators.geometry import Pose
from estimators.lens_distortion import project_point
from estimators.planar_pose import EdgeObservations, ideal_pixel_jacobians, ideal_pixels
from estimators.small_linalg import rigid_transform
from estimators.target import TargetModel

#: Strips stay this far (px) from a corner, beyond the band across the neighbouring edge.
CORNER_CLEARANCE_PX = 5.0
#: ...and at least this fraction of the edge.
MIN_CORNER_FRACTION = 0.04
#: Strips on the shortest edge, shorter than ``strip_px`` where the edge is short: a line needs
#: three points, and with three strips a single one lost to noise loses the edge (a faint
#: panel 35 px across at 3 m: held-out random:111 and 112).
MIN_STRIPS = 5


def edge_span(length_px: float, strip_px: float) -> tuple[float, float]:
    """The part of an edge (fractions of its length) the strips cover: as close to the corners
    as the neighbouring edge allows — an edge's angle, which carries the panel's tilt, is
    measured best from its ends (its information grows with the cube of the span)."""
    margin = max(MIN_CORNER_FRACTION, (CORNER_CLEARANCE_PX + 0.5 * strip_px) / max(length_px, 1.0))
    margin = min(margin, 0.3)
    return margin, 1.0 - margin


def panel_edge_ends(target: TargetModel) -> np.ndarray:
    """The panel's four edges as (4,2,3) end points in T; edge i runs from corner i to i+1."""
    corners = target.panel_corners_T
    return np.stack([corners, np.roll(corners, -1, axis=0)], axis=1)


@dataclass(frozen=True, slots=True, eq=False)
class EdgeStrips:
    """Where to look for one edge: strip centres (K,2 px) on the predicted edge, unit normals
    (K,2) toward the panel's inside, the strips' half length (px), and — when predicted from
    a pose — the model points (K,3, in T) the centres are images of and the width (K, px) of
    the panel's side showing just outside the edge (0 where it faces away)."""

    centers_uv: np.ndarray
    normals: np.ndarray
    half_length_px: float
    points_T: np.ndarray | None = None
    wall_px: np.ndarray | None = None


def strip_count(length_px: float, strip_px: float) -> int:
    t0, t1 = edge_span(length_px, strip_px)
    return int(np.clip(round(length_px * (t1 - t0) / strip_px), MIN_STRIPS, 60))


def strips_from_pose(
    X_CT: Pose, camera: CameraInfo, target: TargetModel, strip_px: float
) -> list[EdgeStrips] | None:
    """Strips along the four projected panel edges (None if the panel is not in view), with
    the width of the panel's side showing beside each (``side_wall_px``)."""
    corners = target.panel_corners_T
    if not np.all(camera.in_view(X_CT.apply(corners), margin_px=1.0)):
        return None
    centre = corners.mean(axis=0)
    strips = []
    for i in range(4):
        strip = strips_along_edge(X_CT, camera, corners[i], corners[(i + 1) % 4], centre, strip_px)
        if strip is None:
            return None
        wall = side_wall_px(X_CT, camera, target, strip)
        strips.append(replace(strip, wall_px=wall))
    return strips


def side_wall_px(
    X_CT: Pose, camera: CameraInfo, target: TargetModel, strips: EdgeStrips
) -> np.ndarray | None:
    """Width (K, px) of the panel's side showing outside its edge at each strip: the image
    offset, outward across the edge, of the side's foot on the face behind (``panel_thickness``
    back along the panel's normal) from the front edge; 0 where the side faces away (its
    image then lies under the panel's front). None without model points or thickness."""
    if strips.points_T is None or target.panel_thickness <= 0:
        return None
    corners = target.panel_corners_T
    normal = np.cross(corners[1] - corners[0], corners[2] - corners[1])
    normal /= np.linalg.norm(normal)
    front = camera.project(X_CT.apply(strips.points_T))
    foot = camera.project(X_CT.apply(strips.points_T - target.panel_thickness * normal))
    outward = -np.sum((foot - front) * strips.normals, axis=1)
    return np.maximum(outward, 0.0)


#: Samples along a model edge when looking for its part in view.
_VIEW_SAMPLES = 257


def _visible_run(
    X_CT: Pose, camera: CameraInfo, a_T: np.ndarray, b_T: np.ndarray, border_px: float
) -> tuple[float, float] | None:
    """The longest stretch [t0, t1] of the edge a + t·(b − a) imaged at least ``border_px``
    inside the image (None if none is), to 1/256 of the edge."""
    ends = camera.in_view(X_CT.apply(np.array([a_T, b_T])), margin_px=border_px)
    if ends.all() and not camera.has_distortion:
        return 0.0, 1.0  # a straight image segment between two points inside the image
    t = np.linspace(0.0, 1.0, _VIEW_SAMPLES)
    seen = camera.in_view(X_CT.apply(a_T + t[:, None] * (b_T - a_T)), margin_px=border_px)
    if seen.all():
        return 0.0, 1.0
    if not seen.any():
        return None
    # Longest run of consecutive visible samples.
    padded = np.concatenate([[False], seen, [False]])
    changes = np.flatnonzero(np.diff(padded.astype(int)))
    starts, stops = changes[::2], changes[1::2] - 1
    k = int(np.argmax(stops - starts))
    return float(t[starts[k]]), float(t[stops[k]])


def strips_along_edge(
    X_CT: Pose,
    camera: CameraInfo,
    a_T: np.ndarray,
    b_T: np.ndarray,
    inside_T: np.ndarray,
    strip_px: float,
    *,
    border_px: float = 0.0,
    min_length_px: float = 0.0,
    max_strips: int | None = None,
) -> EdgeStrips | None:
    """Strips along the part of the model edge a→b (T) that ``X_CT`` images at least
    ``border_px`` inside the image, normals toward ``inside_T`` (a point on the side whose grey
    level is ``inside``). Where the edge ends in view (a model corner) the strips keep clear of
    the corner (``edge_span``); where the image border cuts it they run up to the border. None
    when less than ``min_length_px`` of it is in view. Strips are contiguous (at most 60,
    longer on a longer edge); with ``max_strips`` at most that many, ``strip_px`` long, spread
    out with gaps between them on a longer edge (fewer pixels to fit)."""
    a = np.asarray(a_T, dtype=float)
    b = np.asarray(b_T, dtype=float)
    run = _visible_run(X_CT, camera, a, b, border_px)
    if run is None:
        return None
    t0, t1 = run
    ends_uv = camera.project(X_CT.apply(np.array([a + t0 * (b - a), a + t1 * (b - a)])))
    visible_px = float(np.linalg.norm(ends_uv[1] - ends_uv[0]))
    if visible_px < max(min_length_px, 1e-6):
        return None
    if t0 == 0.0 and t1 == 1.0:
        lo, hi = edge_span(visible_px, strip_px)
    else:
        # Corner clearance in pixels, as a fraction of the visible part, at model corners only.
        clearance = (CORNER_CLEARANCE_PX + 0.5 * strip_px) / visible_px
        span = t1 - t0
        lo = t0 + (max(MIN_CORNER_FRACTION, clearance) * span if t0 == 0.0 else 0.0)
        hi = t1 - (max(MIN_CORNER_FRACTION, clearance) * span if t1 == 1.0 else 0.0)
        if hi - lo < 0.2 * span:
            return None
    # Strips evenly spaced in the image (a receding edge is foreshortened unevenly): places
    # along the edge by its image arc length.
    max_count = 60 if max_strips is None else max_strips
    # (writable copies of the small arrays: one compiled signature whatever the caller holds)
    uv, normal, points, span_px, count = _strip_places(
        np.array(X_CT.R, dtype=float),
        np.array(X_CT.p, dtype=float),
        np.array(camera.K, dtype=float),
        *camera.lens,
        np.array(a),
        np.array(b),
        np.array(inside_T, dtype=float),
        float(lo),
        float(hi),
        float(strip_px),
        MIN_STRIPS,
        max_count,
    )
    spacing = span_px / max(count - 1, 1)
    half_length = 0.5 * spacing if max_strips is None else 0.5 * min(spacing, strip_px)
    return EdgeStrips(uv, normal, half_length, points)


@compiled
def _strip_places(
    R, p, K, d, M, tilted, distorted, a, b, inside_T, lo, hi, strip_px, min_count, max_count
):
    """Strip centres (K,2 px), unit normals toward ``inside_T`` (K,2) and model points (K,3)
    along the edge a→b between its fractions ``lo`` and ``hi``, evenly spaced by image arc
    length (65 places along the edge measure it), about ``strip_px`` apart within
    [``min_count``, ``max_count``] strips; and the arc's length (px) and the strip count.
    Compiled: as NumPy, some forty calls an edge, and the line system places a dozen edges a
    frame."""
    e = b - a
    dense = np.linspace(lo, hi, 65)
    arc = np.zeros(65)
    u0 = v0 = 0.0
    for j in range(65):
        u, v = _image_of(R, p, K, d, M, tilted, distorted, a + dense[j] * e)
        if j > 0:
            arc[j] = arc[j - 1] + math.sqrt((u - u0) * (u - u0) + (v - v0) * (v - v0))
        u0, v0 = u, v
    span_px = arc[64]
    count = min(max(round(span_px / strip_px), min_count), max_count)  # (half to even)
    t = np.interp(np.linspace(0.0, span_px, count), arc, dense)
    uv, normal, points = np.empty((count, 2)), np.empty((count, 2)), np.empty((count, 3))
    depth = np.empty(count)
    for i in range(count):
        points[i] = a + t[i] * e
        depth[i] = rigid_transform(R, p, points[i, 0], points[i, 1], points[i, 2])[2]
        uv[i, 0], uv[i, 1] = _image_of(R, p, K, d, M, tilted, distorted, points[i])
        au, av = _image_of(R, p, K, d, M, tilted, distorted, a + (t[i] + 1e-3) * e)
        tu, tv = au - uv[i, 0], av - uv[i, 1]
        norm = math.sqrt(tu * tu + tv * tv)
        normal[i, 0], normal[i, 1] = -tv / norm, tu / norm
    step_m = 1e-3 * np.median(depth)
    facing = 0.0
    for i in range(count):
        toward = inside_T - points[i]
        toward = toward / max(math.sqrt(np.sum(toward * toward)), 1e-12)
        iu, iv = _image_of(R, p, K, d, M, tilted, distorted, points[i] + step_m * toward)
        facing += (iu - uv[i, 0]) * normal[i, 0] + (iv - uv[i, 1]) * normal[i, 1]
    if facing < 0:
        normal = -normal
    return uv, normal, points, span_px, count


@compiled_inline
def _image_of(R, p, K, d, M, tilted, distorted, point_T):
    """The pixel of a model point (3,) in T seen from (R, p)."""
    X, Y, Z = rigid_transform(R, p, point_T[0], point_T[1], point_T[2])
    return project_point(X, Y, Z, K, d, M, tilted, distorted)


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


def last_side_quads(
    edges: PanelEdges, side: int, guess_ideal: np.ndarray, step_px: float, reach: float
) -> list[np.ndarray]:
    """Where a quad's one missing ``side`` may lie once the other three edges are found:
    quads (4,2 ideal px, model corner order) whose two corners on the opposite edge are where
    the found lines meet, and whose missing side's ends slide along the two neighbouring lines
    together, ``step_px`` apart, from ``1 − reach`` to ``1 + reach`` times their distance in
    ``guess_ideal`` (a hypothesis's corners, 4,2). Empty when the lines do not meet."""
    before, after, opposite = (
        edges.edges[side - 1],
        edges.edges[(side + 1) % 4],
        edges.edges[(side + 2) % 4],
    )
    far_before = intersect(opposite.line, before.line)  # type: ignore[arg-type]
    far_after = intersect(opposite.line, after.line)  # type: ignore[arg-type]
    if far_before is None or far_after is None:
        return []
    guess = np.asarray(guess_ideal, dtype=float)
    # Corner ``side`` ends the edge before it, corner ``side + 1`` starts the one after it.
    ends = []
    for line, far, near_guess in (
        (before.line, far_before, guess[side]),
        (after.line, far_after, guess[(side + 1) % 4]),
    ):
        direction = line.direction  # type: ignore[union-attr]
        length = float((near_guess - far) @ direction)
        ends.append((far, direction * length))
    span = max(float(np.linalg.norm(d)) for _, d in ends)
    if span < 1.0:
        return []
    quads = []
    for scale in np.arange(1.0 - reach, 1.0 + reach + 1e-9, step_px / span):
        quad = np.zeros((4, 2))
        quad[side] = ends[0][0] + scale * ends[0][1]
        quad[(side + 1) % 4] = ends[1][0] + scale * ends[1][1]
        quad[(side + 2) % 4] = far_after
        quad[(side + 3) % 4] = far_before
        quads.append(quad)
    return quads


def shift_strips_onto(strips: EdgeStrips, point: np.ndarray, direction: np.ndarray) -> EdgeStrips:
    """Strips moved along their normals onto the image line through ``point`` along
    ``direction`` (e.g. a labeled Hough segment), keeping their spacing and shape."""
    normal_line = np.array([-direction[1], direction[0]]) / np.linalg.norm(direction)
    # Solve (c + s·n)·n_line = point·n_line for s per strip.
    denominator = strips.normals @ normal_line
    safe = np.where(np.abs(denominator) < 0.2, np.nan, denominator)
    shift = ((point - strips.centers_uv) @ normal_line) / safe
    shift = np.where(np.isfinite(shift), shift, 0.0)
    return shift_strips(strips, shift)


def shift_strips(strips: EdgeStrips, shift_px: np.ndarray) -> EdgeStrips:
    """Strips moved along their normals by ``shift_px`` (K,) (the model points they image are
    no longer exact: dropped)."""
    return EdgeStrips(
        strips.centers_uv + np.asarray(shift_px, dtype=float)[:, None] * strips.normals,
        strips.normals,
        strips.half_length_px,
        wall_px=strips.wall_px,  # a shift of a few pixels leaves the side's width as it was
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

    @property
    def information(self) -> float:
        """Σ 1/σ² over the inliers (px⁻²; 0 when not found): more points on the edge, and
        sharper ones, measure it better — points found on noise beside it are few and blurred."""
        if not self.found:
            return 0.0
        return float(np.sum(1.0 / np.square(self.sigma_ideal[self.used])))


@dataclass(frozen=True, slots=True, eq=False)
class PanelEdges:
    """The four fitted edges (in model order) and the corners where neighbours meet (ideal
    px; corner i is between edge i−1 and edge i, matching the model's corner i)."""

    edges: tuple[FittedEdge, ...]
    corners_ideal: np.ndarray | None

    @staticmethod
    def of(edges: Sequence[FittedEdge]) -> PanelEdges:
        """The edges with their corners, when all four are found and neighbours meet."""
        corners = None
        if all(e.found for e in edges):
            found = []
            for i in range(4):
                point = intersect(edges[i - 1].line, edges[i].line)  # type: ignore[arg-type]
                if point is None:
                    break
                found.append(point)
            if len(found) == 4 and np.all(np.isfinite(found)):
                corners = np.array(found)
        return PanelEdges(tuple(edges), corners)

    @property
    def all_found(self) -> bool:
        return all(e.found for e in self.edges) and self.corners_ideal is not None

    def observations(self, target: TargetModel) -> EdgeObservations:
        """Edge points as pose observations (point-to-projected-edge distances)."""
        return edge_observations(panel_edge_ends(target), self.edges)

    def turned(self, quarter_turns: int) -> PanelEdges:
        """The same image edges labeled for the pose turned by ``quarter_turns`` about the
        panel's axis (``X_CT @ quarter_turns(target)[k]``): that turn carries the model's edge
        j onto its edge j + k (the corners run counter-clockwise about the panel's normal), so
        the turned pose sees edge j where this one sees edge j + k."""
        k = quarter_turns % 4
        edges = self.edges[k:] + self.edges[:k]
        corners = None if self.corners_ideal is None else np.roll(self.corners_ideal, -k, axis=0)
        return PanelEdges(edges, corners)

    def image_points(self) -> np.ndarray:
        """All inlier edge points in image pixels (for overlays)."""
        parts = [e.points.uv[e.used] for e in self.edges if e.found]
        return np.concatenate(parts) if parts else np.zeros((0, 2))


def fit_edge(
    pixels: np.ndarray,
    strip: EdgeStrips,
    camera: CameraInfo,
    *,
    half_width_px: float = 3.0,
    search_px: float = 2.0,
    min_contrast_snr: float = 3.5,
    polarity: float = 1.0,
    keep: Callable[[np.ndarray], np.ndarray] | None = None,
    noise_sigma: float = 0.0,
    tilt_px: float = 0.0,
) -> FittedEdge:
    """One straight edge from its strips: step-edge points (``estimators.edge_fit``) converted
    to ideal pixels, and a robust line through them. Found when the grey levels differ with
    ``polarity`` (+1: brighter on the normals' side, −1: darker, 0: either) by
    ``min_contrast_snr`` standard deviations and the line has at least three inliers.
    ``noise_sigma``: the image noise, for the model of clipped pixels; ``tilt_px``: how much
    more one end of the strips may be off the edge than the other (``fit_edge_points``)."""
    points = fit_edge_points(
        pixels,
        strip.centers_uv,
        strip.normals,
        strip.half_length_px,
        half_width_px,
        search_px=search_px,
        keep=keep,
        noise_sigma=noise_sigma,
        wall_px=strip.wall_px,
        tilt_px=tilt_px,
    )
    ok = np.flatnonzero(points.ok)
    empty = FittedEdge(points, np.zeros((0, 2)), np.zeros(0), None, np.zeros(0, int))
    sign = polarity if polarity != 0 else math.copysign(1.0, points.contrast_snr)
    if len(ok) < 3 or sign * points.contrast_snr < min_contrast_snr:
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


def side_contrast_z(
    pixels: np.ndarray,
    ends_uv: np.ndarray,
    inside_uv: np.ndarray,
    polarity: float,
    noise_sigma: float,
    keep: Callable[[np.ndarray], np.ndarray] | None = None,
    *,
    strip_px: float = 6.0,
    gap_px: float = 1.0,
    band_px: float = 4.0,
    min_pixels: int = 8,
) -> np.ndarray:
    """The contrast across straight image edges at given places (``ends_uv``, S,2,2 px; the
    panel toward ``inside_uv``), each as a z-score: the mean grey level of the pixels
    ``gap_px`` to ``gap_px + band_px`` on the panel's side of the edge, less that of the
    pixels as far on the other side, times ``polarity`` (+1: the panel brighter), over its
    standard error for white noise ``noise_sigma`` — along the part of the edge strips would
    cover (``edge_span``). Each pixel (kept by ``keep``) counts once, by its centre, and no
    position is searched: where there is no edge each score is a standard normal, unlike
    ``fit_edge``'s contrast, taken at each strip's best position
    (tests/estimators/test_panel_edges.py). (S,) scores, NaN with fewer than ``min_pixels``
    on a side."""
    ends = np.asarray(ends_uv, dtype=float).reshape(-1, 2, 2)
    h, w = pixels.shape[:2]
    margin = gap_px + band_px + 1.0
    lo = np.floor(np.maximum(ends.reshape(-1, 2).min(axis=0) - margin, 0.0)).astype(int)
    hi = np.ceil(np.minimum(ends.reshape(-1, 2).max(axis=0) + margin, [w - 1, h - 1])).astype(int)
    scores = np.full(len(ends), math.nan)
    if np.any(hi < lo):
        return scores
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1))
    uv = np.column_stack([gx.ravel(), gy.ravel()]).astype(float)
    if keep is not None:
        uv = uv[keep(uv)]
    values = pixels[uv[:, 1].astype(int), uv[:, 0].astype(int)].astype(float)
    a, b = ends[:, 0], ends[:, 1]
    length = np.linalg.norm(b - a, axis=1)
    tangent = (b - a) / np.maximum(length, 1e-9)[:, None]
    normal = np.column_stack([-tangent[:, 1], tangent[:, 0]])
    toward = np.einsum("sj,sj->s", normal, np.asarray(inside_uv, dtype=float) - a)
    normal *= np.where(toward < 0, -1.0, 1.0)[:, None]
    relative = uv[None, :, :] - a[:, None, :]
    along = np.einsum("spj,sj->sp", relative, tangent)
    across = np.einsum("spj,sj->sp", relative, normal)
    span = np.array([edge_span(float(n), strip_px) for n in length]) * length[:, None]
    on_edge = (along >= span[:, :1]) & (along <= span[:, 1:])
    inner = on_edge & (across >= gap_px) & (across <= gap_px + band_px)
    outer = on_edge & (-across >= gap_px) & (-across <= gap_px + band_px)
    n_in, n_out = inner.sum(axis=1), outer.sum(axis=1)
    enough = (n_in >= min_pixels) & (n_out >= min_pixels)
    mean_in = (inner @ values) / np.maximum(n_in, 1)
    mean_out = (outer @ values) / np.maximum(n_out, 1)
    error = max(noise_sigma, 1e-6) * np.sqrt(1.0 / np.maximum(n_in, 1) + 1.0 / np.maximum(n_out, 1))
    scores[enough] = (polarity * (mean_in - mean_out) / error)[enough]
    return scores


#: The contrast (a z-score, the best of the scan's places) a panel's one missing side must show
#: where its other three bound it (``find_last_side``): with the side absent, the best of 60
#: places reaches 4 σ in 1 noise draw of 300 (tests/estimators/test_panel_edges.py).
LAST_SIDE_Z = 4.0
#: How far the missing side is scanned, as a fraction of its distance from the opposite side.
LAST_SIDE_REACH = 0.3


def find_last_side(
    pixels: np.ndarray,
    edges: PanelEdges,
    side: int,
    guess_ideal: np.ndarray,
    camera: CameraInfo,
    polarity: float,
    noise_sigma: float,
    *,
    clip_sigma: float = 0.0,
    keep: Callable[[np.ndarray], np.ndarray] | None = None,
    strip_px: float = 6.0,
    half_width_px: float = 3.0,
    min_z: float = LAST_SIDE_Z,
    reach: float = LAST_SIDE_REACH,
) -> PanelEdges | None:
    """The panel's edges with its one missing ``side`` found where the other three bound it,
    or None. A faint side falls under ``fit_edge``'s contrast test in one frame of a few (a
    small panel at 3 m: five strips a side, 5 σ each), and that test cannot be lowered: taken
    at each strip's best position, it passes noise where there is no edge 1 time in 20 at
    3.5 σ, 1 in 4 at 2.5 σ. The three sides found fix the fourth's direction and the lines its
    ends slide on; how far along them depends on the tilt, which a small panel's hypothesis
    (its corners ``guess_ideal``) may have 25° wrong. So the side is scanned along them
    (``last_side_quads``, half-pixel steps within ``reach``), its contrast at each place a
    z-score with nothing searched (``side_contrast_z``), and the best place must reach
    ``min_z``, which allows for the scan's many looks. There the side is measured (±1.5 px)
    as any edge is (``clip_sigma``: the noise for the model of clipped pixels)."""
    quads = last_side_quads(edges, side, guess_ideal, 0.5, reach)
    if not quads:
        return None
    quads_uv = camera.image_of_ideal(np.concatenate(quads)).reshape(-1, 4, 2)
    ends = quads_uv[:, [side, (side + 1) % 4]]
    z = side_contrast_z(
        pixels, ends, quads_uv[0].mean(axis=0), polarity, noise_sigma, keep, strip_px=strip_px
    )
    if not np.any(np.isfinite(z)):
        return None
    best = int(np.nanargmax(z))
    if not z[best] >= min_z:
        return None
    edge = fit_edge(
        pixels,
        strips_from_quad(quads_uv[best], strip_px)[side],
        camera,
        half_width_px=half_width_px,
        search_px=1.5,
        min_contrast_snr=0.0,  # (the z-score above is the test)
        polarity=polarity,
        keep=keep,
        noise_sigma=clip_sigma,
    )
    if not edge.found:
        return None
    completed = PanelEdges.of(edges.edges[:side] + (edge,) + edges.edges[side + 1 :])
    return completed if completed.all_found else None


def edge_observations(ends_T: np.ndarray, edges: Sequence[FittedEdge | None]) -> EdgeObservations:
    """The inlier points of fitted edges as pose observations of the model edges ``ends_T``
    (E,2,3; edge i measured by ``edges[i]``, None or not found when it was not)."""
    uv, edge, sigma = [np.zeros((0, 2))], [np.zeros(0, int)], [np.zeros(0)]
    for i, e in enumerate(edges):
        if e is None or not e.found:
            continue
        uv.append(e.uv_ideal[e.used])
        sigma.append(e.sigma_ideal[e.used])
        edge.append(np.full(len(e.used), i))
    return EdgeObservations(ends_T, np.concatenate(edge), np.concatenate(uv), np.concatenate(sigma))


#: An edge fitted on fewer of its strips than this is fitted again from the fallback strips.
COVERED_FRACTION = 0.75
#: Strips of a rough hypothesis searched up to this wide (px) keep their direction.
TILT_FREE_SEARCH_PX = 2.0
#: The largest tilt (px, end to end) of a rough hypothesis's strips against their edge.
MAX_TILT_PX = 4.0


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
    noise_sigma: float = 0.0,
    rough: bool = False,
) -> PanelEdges:
    """Fit the four edges from their strips (``search_px`` per edge or for all). An edge
    counts as found when its grey levels differ with the model's polarity (+1: the panel is
    brighter) by ``min_contrast_snr`` standard deviations and a robust line fits at least three
    points. An edge not found from ``strips``, or found on fewer than ``COVERED_FRACTION`` of
    them — every edge when ``rough``, unless its strips are the fallback's — is fitted again
    from ``fallback`` (e.g. the prior's prediction, when a labeled image line misled), and the
    fit that measures the edge better (``FittedEdge.information``) is kept. ``rough``: the
    strips come from a rough hypothesis, not a tracked pose — a strip set searched wider than
    ``TILT_FREE_SEARCH_PX`` may then also be tilted against its edge by up to the rest of its
    search (at most ``MAX_TILT_PX``)."""
    searches = list(search_px) if isinstance(search_px, list | tuple) else [search_px] * len(strips)

    def tilt(search: float) -> float:
        # A hypothesis several pixels off is off in direction too: one from a quad cut at a
        # grey level had a side 3.9 px off at one end and 0.6 px at the other, and a common
        # offset for its strips found noise beside the edge (a pose 17° off).
        return min(max(search - TILT_FREE_SEARCH_PX, 0.0), MAX_TILT_PX) if rough else 0.0

    fitted = []
    for i, strip in enumerate(strips):
        settings = dict(
            half_width_px=half_width_px,
            min_contrast_snr=min_contrast_snr,
            polarity=polarity,
            keep=keep,
            noise_sigma=noise_sigma,
        )
        edge = fit_edge(
            pixels, strip, camera, search_px=searches[i], tilt_px=tilt(searches[i]), **settings
        )
        covered = len(edge.used) >= COVERED_FRACTION * len(strip.centers_uv)
        compare = rough and fallback is not None and fallback[i] is not strip
        if fallback is not None and (compare or not covered):
            # A labeled image line a little askew crosses the edge: a narrow search along it
            # meets the edge only near the crossing, elsewhere it finds noise, and the line
            # through those points keeps the image line's tilt. The prior's own strips,
            # searched wider, then measure the edge better.
            other = fit_edge(
                pixels,
                fallback[i],
                camera,
                search_px=fallback_search_px,
                tilt_px=tilt(fallback_search_px),
                **settings,
            )
            if other.information > edge.information:
                edge = other
        fitted.append(edge)
    return PanelEdges.of(fitted)


def corner_sigma_px(edges: PanelEdges) -> float:
    """A typical corner uncertainty (px) from the edge points' scatter, for closed-form use."""
    sigmas = [float(np.median(e.sigma_ideal[e.used])) for e in edges.edges if e.found]
    counts = [len(e.used) for e in edges.edges if e.found]
    if not sigmas:
        return math.nan
    return float(np.median(sigmas) * math.sqrt(4.0 / max(min(counts), 1)))
