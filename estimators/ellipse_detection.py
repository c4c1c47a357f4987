"""Detection and labeling: which extracted ellipse is which circle of the target.

* With a prior pose, each model circle is projected (through the full camera model) and every
  extracted ellipse of the right polarity is scored against it by a normalised cost over
  centre, semi-axes and orientation; the cheapest one within the gate gets the label.
* Without a prior, the ring's two concentric edges are looked for together: pairs of ellipses
  of opposite polarity, nearly concentric, whose axes stand in the ratio of the known radii;
  lone ellipses follow as weaker hypotheses. Hypotheses are verified downstream by the pose
  fit (edge support of both edges).
* An off-axis circle (the thruster) fixes the roll about the ring's axis: once the ring's
  centre and normal are known, it can only lie on one circle around that axis, so a 1-D search
  over the roll angle scores edge support of its predicted image along that locus.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimators.circle_edges import camera_field_radius, visible_pixels
from estimators.circle_pose import CirclePose
from estimators.conics import (
    Ellipse,
    circle_points,
    ellipse_from_conic,
    fit_ellipse_direct,
)
from estimators.edge_search import search_edges
from estimators.ellipse_extraction import ExtractedEllipse
from estimators.frame import CameraInfo
from estimators.geometry import Pose, any_perpendicular, cross3, rotation_between
from estimators.imaging import GradientField
from estimators.target import Circle3D

#: Gate on the normalised labeling cost (≈ χ² with 4 degrees of freedom at 99.5 %).
LABEL_GATE = 15.0


def projected_ellipse(
    center_C: np.ndarray, normal_C: np.ndarray, radius: float, camera: CameraInfo
) -> Ellipse | None:
    """The ellipse best fitting a 3-D circle's image through the full camera model (pixels),
    or None when the circle is not safely in front of the camera."""
    points_C = circle_points(center_C, normal_C, radius, 72)
    if np.any(points_C[:, 2] < 0.02):
        return None
    try:
        return ellipse_from_conic(fit_ellipse_direct(camera.project(points_C)))
    except ValueError:
        return None


def labeling_cost(extracted: Ellipse, predicted: Ellipse) -> float:
    """Normalised squared difference of two ellipses: centre, semi-axes and orientation (the
    orientation weighs by the ellipse's eccentricity, since a circle's angle is undefined).
    Scales grow with the predicted size, so the gate means the same at any range."""
    sigma_center = 0.15 * predicted.a + 3.0
    sigma_axis = 0.08 * predicted.a + 2.0
    d_angle = (extracted.angle - predicted.angle + np.pi / 2) % np.pi - np.pi / 2
    return float(
        np.hypot(extracted.cx - predicted.cx, extracted.cy - predicted.cy) ** 2 / sigma_center**2
        + (extracted.a - predicted.a) ** 2 / sigma_axis**2
        + (extracted.b - predicted.b) ** 2 / sigma_axis**2
        + (d_angle * (predicted.a - predicted.b)) ** 2 / sigma_axis**2
    )


def label_with_prior(
    extracted: list[ExtractedEllipse],
    predicted: dict[str, tuple[Ellipse, int | None]],
    *,
    gate: float = LABEL_GATE,
) -> dict[str, tuple[ExtractedEllipse, float]]:
    """Assign extracted ellipses to model circles: ``predicted`` maps a circle name to its
    predicted ellipse and expected polarity (None: either). Each ellipse labels at most one
    circle; cheapest pairs first, gated."""
    pairs = []
    for name, (ellipse, polarity) in predicted.items():
        for k, e in enumerate(extracted):
            if polarity is not None and e.polarity != polarity:
                continue
            cost = labeling_cost(e.ellipse, ellipse)
            if cost <= gate:
                pairs.append((cost, name, k))
    labels: dict[str, tuple[ExtractedEllipse, float]] = {}
    used: set[int] = set()
    for cost, name, k in sorted(pairs):
        if name in labels or k in used:
            continue
        labels[name] = (extracted[k], cost)
        used.add(k)
    return labels


@dataclass(frozen=True, slots=True, eq=False)
class RingHypothesis:
    """Ellipses taken for the ring's outer and/or inner edge, with a consistency cost."""

    outer: ExtractedEllipse | None
    inner: ExtractedEllipse | None
    cost: float
    bore_foot: ExtractedEllipse | None = None  # the inner edge's partner: the bore's foot

    @property
    def concentric(self) -> bool:
        return self.outer is not None and self.inner is not None


def ring_hypotheses(
    extracted: list[ExtractedEllipse],
    outer: Circle3D,
    inner: Circle3D | None,
    *,
    max_count: int = 8,
    bore_depth_m: float = 0.0,
    focal_px: float | None = None,
) -> list[RingHypothesis]:
    """Ring hypotheses without a prior: concentric pairs (opposite polarity, axis ratios ≈
    r_inner / r_outer, centres together), then lone ellipses; largest ring first within each
    kind, since smaller look-alikes (a bright annular lip) are the likelier confusion.

    A deep bore (``bore_depth_m`` behind the ring's front, the camera's ``focal_px``) shows a
    second concentric pair: its rim and, farther away and so smaller, its foot. Where their
    ratio — which depends on the distance — fits the pair better than r_inner / r_outer does,
    the pair is also taken for the bore (the inner edge with ``bore_foot``): a ring larger by
    r_outer / r_inner, tried first. Taken for the ring's two edges, such a pair put the ring
    15 % too far, at 0.5 m and 1.2 m, with its normal right (random mock-ups, issue 13).

    A lone ellipse is taken for the outer edge and for the inner edge; with a deep bore the two
    with the most points are also taken, last, for the bore's foot alone: a wall as dark as
    the ring's front shows no rim, and close up, the outer edge out of view, the foot may be
    all of the ring the image holds — and two fits of it may be extracted, the one with more
    points the worse (held-out random:109 at 0.5 m, high noise: 383 points 14° off, 372 points
    3° off)."""
    hypotheses: list[RingHypothesis] = []
    if inner is not None:
        ratio = inner.radius / outer.radius
        for eo in extracted:
            for ei in extracted:
                if eo is ei or eo.brighter_inside == ei.brighter_inside:
                    continue
                o, i = eo.ellipse, ei.ellipse
                distance = np.hypot(o.cx - i.cx, o.cy - i.cy)
                if distance > 0.1 * o.a + 2.0:
                    continue
                ra, rb = i.a / o.a, i.b / o.b
                standard = _pair_cost(ra, rb, ratio, distance, o.a)
                if standard is not None:
                    hypotheses.append(RingHypothesis(eo, ei, standard))
                if bore_depth_m > 0.0 and focal_px is not None:
                    z = focal_px * inner.radius / o.a  # the rim's distance, were ``eo`` the rim
                    bore = _pair_cost(ra, rb, z / (z + bore_depth_m), distance, o.a)
                    if bore is not None and (standard is None or bore < standard):
                        hypotheses.append(RingHypothesis(None, eo, bore, bore_foot=ei))
    scale = outer.radius / inner.radius if inner is not None else 1.0
    hypotheses.sort(
        key=lambda h: -(h.outer.ellipse.a if h.outer is not None else scale * h.inner.ellipse.a)
    )
    singles = sorted(extracted, key=lambda e: -len(e.points))
    for e in singles:
        hypotheses.append(RingHypothesis(e, None, np.inf))
        if inner is not None:
            hypotheses.append(RingHypothesis(None, e, np.inf))
    hypotheses = hypotheses[:max_count]
    if inner is not None and bore_depth_m > 0.0 and singles:
        # Last and beyond the count: the likelier readings keep their places.
        for e in singles[:2]:
            hypotheses.append(RingHypothesis(None, None, np.inf, bore_foot=e))
    return hypotheses


def _pair_cost(ra: float, rb: float, ratio: float, distance_px: float, a_px: float) -> float | None:
    """How well two concentric ellipses' axis ratios (``ra``, ``rb``) and centre distance fit
    circles of radius ``ratio`` to each other; None beyond the gate."""
    if abs(ra - ratio) > 0.08 or abs(rb - ratio) > 0.08:
        return None
    return float(
        ((ra - ratio) / 0.03) ** 2
        + ((rb - ratio) / 0.03) ** 2
        + (distance_px / (0.03 * a_px + 1.0)) ** 2
    )


def pose_with_roll(ring: CirclePose, reference: Circle3D, roll: float) -> Pose:
    """``X_CT`` placing ``reference`` at the ring pose, turned by ``roll`` (rad) about its axis
    from a fixed zero (the roll at which T's x axis is as close as possible to C's x axis)."""
    n = ring.normal_C
    x = any_perpendicular(n)
    R_CA = np.column_stack([x, cross3(n, x), n])  # axis frame A: z along the normal
    c, s = np.cos(roll), np.sin(roll)
    R_AA = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    # Frame T: its reference normal maps to A's z.
    R_TA = rotation_between(np.array([0.0, 0.0, 1.0]), reference.normal_T)
    R_CT = R_CA @ R_AA @ R_TA.T
    return Pose(R_CT, ring.center_C - R_CT @ reference.center_T)


def roll_of(X_CT: Pose, ring: CirclePose, reference: Circle3D) -> float:
    """The roll (rad, as in ``pose_with_roll``) that comes closest to the orientation of
    ``X_CT`` for the given ring pose."""
    zero = pose_with_roll(ring, reference, 0.0)
    # Rotation about the normal taking zero's T-x axis onto X_CT's (projected on the plane).
    n = ring.normal_C
    a = zero.R @ any_perpendicular(reference.normal_T)
    b = X_CT.R @ any_perpendicular(reference.normal_T)
    b = b - (b @ n) * n
    return float(np.arctan2(cross3(a, b) @ n, a @ b))


@dataclass(frozen=True, slots=True)
class RollSearch:
    """Best roll (rad) of the off-axis circle, its score (mean edge SNR per sample, each
    clipped at 8), the median score over all rolls tried, and the polarity that scored."""

    roll: float
    score: float
    median_score: float
    polarity: int


def _score_rolls(
    field: GradientField,
    ring: CirclePose,
    reference: Circle3D,
    circle: Circle3D,
    camera: CameraInfo,
    polarity: int,
    rolls: np.ndarray,
    samples_per_circle: int,
    half_width_px: float,
    field_radius_xy: float,
) -> np.ndarray:
    """Score (mean clipped edge SNR per sample; NaN where out of view) of the off-axis circle
    at each roll, for one polarity."""
    zero = pose_with_roll(ring, reference, 0.0)
    rolls = np.asarray(rolls, dtype=float)
    # The circle at roll 0 (points at t and t ± dt for the tangent), then turned about the
    # ring's axis for every roll at once (Rodrigues' formula).
    t = np.linspace(0.0, 2.0 * np.pi, samples_per_circle, endpoint=False)
    dt = 1e-3
    base = (
        np.vstack(
            [
                circle_points(
                    zero.apply(circle.center_T),
                    zero.R @ circle.normal_T,
                    circle.radius,
                    angles=t + e,
                )
                for e in (0.0, dt, -dt)
            ]
        )
        - ring.center_C
    )
    n = ring.normal_C
    cos, sin = np.cos(rolls)[:, None, None], np.sin(rolls)[:, None, None]
    turned = (
        base[None] * cos
        + np.cross(n, base)[None] * sin
        + (base @ n)[None, :, None] * n[None, None, :] * (1.0 - cos)
    ) + ring.center_C  # (M, 3K, 3)
    m, k = len(rolls), samples_per_circle
    flat = turned.reshape(-1, 3)
    visible, uv_flat = visible_pixels(flat, camera, half_width_px + 2.0, field_radius_xy)
    visible = visible.reshape(m, 3 * k)
    visible = visible[:, :k] & visible[:, k : 2 * k] & visible[:, 2 * k :]
    usable = visible.sum(axis=1) >= 0.75 * k
    if not np.any(usable):
        return np.full(m, np.nan)
    uv = uv_flat.reshape(m, 3 * k, 2)
    point_uv = uv[:, :k]
    tangent = uv[:, k : 2 * k] - uv[:, 2 * k :]
    normal_uv = np.stack([tangent[..., 1], -tangent[..., 0]], axis=-1)
    normal_uv /= np.maximum(np.linalg.norm(normal_uv, axis=-1, keepdims=True), 1e-12)
    centres = np.zeros((m, 2))
    centres[usable] = np.nanmean(point_uv[usable], axis=1)
    outward = np.einsum("mkj,mkj->mk", normal_uv, point_uv - centres[:, None, :])
    normal_uv[outward < 0] *= -1.0
    keep = visible & usable[:, None]
    owner = np.nonzero(keep)[0]
    hits = search_edges(field, point_uv[keep], normal_uv[keep], polarity, half_width_px)
    # Clip each sample's SNR so a few very strong edges (clutter) cannot outvote support all
    # around the circle.
    score = np.bincount(owner, weights=np.minimum(hits.snr, 8.0), minlength=m) / np.maximum(
        np.bincount(owner, minlength=m), 1
    )
    score[~usable] = np.nan
    return score


def search_roll(
    field: GradientField,
    ring: CirclePose,
    reference: Circle3D,
    circle: Circle3D,
    camera: CameraInfo,
    *,
    polarity: int | None,
    rolls: np.ndarray | None = None,
    samples_per_circle: int = 16,
    half_width_px: float = 2.5,
    field_radius_xy: float | None = None,
) -> RollSearch | None:
    """Score the off-axis ``circle`` at rolls about the ring's axis and return the best; None
    when it is not in view at any roll.

    Without ``rolls`` the whole turn is searched coarse to fine: steps of half the circle's
    image radius along its locus, then the three best neighbourhoods at a tenth of it. The
    window ``half_width_px`` should cover the error of the ring's pose at the circle.
    """
    if field_radius_xy is None:
        field_radius_xy = camera_field_radius(camera)
    center_zero = pose_with_roll(ring, reference, 0.0).apply(circle.center_T)
    lever_px = (
        camera.K[0, 0] * np.linalg.norm(center_zero - ring.center_C) / max(center_zero[2], 1e-3)
    )
    radius_px = camera.K[0, 0] * circle.radius / max(center_zero[2], 1e-3)
    step = max(0.5 * radius_px / max(lever_px, 1e-6), np.radians(0.5))
    coarse = rolls is None
    tried = np.arange(-np.pi, np.pi, step) if coarse else np.asarray(rolls, dtype=float)
    # Only rolls that put the circle's centre in view (or nearly) are worth scoring.
    offset = center_zero - ring.center_C
    n = ring.normal_C
    cos, sin = np.cos(tried)[:, None], np.sin(tried)[:, None]
    centers = (
        ring.center_C + offset * cos + np.cross(n, offset) * sin + (offset @ n) * n * (1.0 - cos)
    )
    in_view, _ = visible_pixels(centers, camera, -radius_px, field_radius_xy)
    tried = tried[in_view]
    if len(tried) == 0:
        return None
    best: RollSearch | None = None
    for p in (1, -1) if polarity is None else (polarity,):
        score = _score_rolls(
            field,
            ring,
            reference,
            circle,
            camera,
            p,
            tried,
            samples_per_circle,
            max(half_width_px, 0.5 * step * lever_px if coarse else 0.0),
            field_radius_xy,
        )
        if not np.any(np.isfinite(score)):
            continue
        median = float(np.nanmedian(score))
        candidates_rolls, candidates_scores = tried, score
        if coarse:
            top = np.argsort(np.nan_to_num(score, nan=-1.0))[::-1][:3]
            fine = np.concatenate([tried[k] + np.linspace(-step, step, 11) for k in top])
            candidates_rolls = fine
            candidates_scores = _score_rolls(
                field,
                ring,
                reference,
                circle,
                camera,
                p,
                fine,
                samples_per_circle,
                half_width_px,
                field_radius_xy,
            )
        if not np.any(np.isfinite(candidates_scores)):
            continue
        k = int(np.nanargmax(candidates_scores))
        result = RollSearch(float(candidates_rolls[k]), float(candidates_scores[k]), median, p)
        if best is None or result.score > best.score:
            best = result
    return best
