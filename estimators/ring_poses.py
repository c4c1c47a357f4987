"""The target poses the ring's own image gives, near a pose that may be tens of degrees off.

A pose of the panel from a few faint features may be wrong in tilt and range together (held-out
random:115 at 2 m: 34° off and 125 mm short, its panel centre right across the line of sight),
which no tilt about the panel's centre and no move along the line of sight reaches alone. The
ring's image decides both: its ellipse gives the ring's centre and normal, up to the circle's
two-fold ambiguity (``circle_poses_from_conic``). Its edges are searched along the normals of the
ellipse the pose predicts, in a window as wide as such an error moves them; an ellipse is fitted
to what is found (a direct fit, refitted without its outliers); and each of the circle's two
poses, read as the ring's outer and as its inner circle, becomes a target pose with the roll
nearest the given pose's (``roll_of``). They are candidates only: the whole model's support
judges them (``acquisition.judge_tilt_and_range``).
"""

from __future__ import annotations

import numpy as np

from estimators.circle_edges import find_circle_edges, sample_projected_circle
from estimators.circle_pose import circle_poses_from_conic
from estimators.conics import fit_ellipse_direct, sampson_distances
from estimators.ellipse_detection import pose_with_roll, roll_of
from estimators.frame import CameraInfo
from estimators.geometry import Pose
from estimators.imaging import ImageStack
from estimators.least_squares import median
from estimators.target import TargetModel

#: Smoothing (px) of the gradients the ring's edges are searched on: a window tens of pixels
#: wide meets the ring's edge and its neighbours; smoothed, the edge is the strongest.
RING_SEARCH_SMOOTHING_PX = 2.0
#: The search window, as a fraction of the ring's semi-major axis in the image (a tilt error of
#: 35° changes an axis by 18 %), within these bounds (px).
RING_SEARCH_FRACTION = 0.25
RING_SEARCH_PX = (6.0, 30.0)
#: Edges found on fewer of the samples than this leave the ring unmeasured.
MIN_RING_SUPPORT = 0.5


def ring_poses_near(
    image: ImageStack, X_CT: Pose, target: TargetModel, camera: CameraInfo
) -> tuple[Pose, ...]:
    """Target poses that put the ring on its image edges found around where ``X_CT`` puts its
    outer circle: none, or the two poses of the circle the edges' ellipse is the image of, read
    as the outer and (when the model has one) as the inner circle."""
    if not target.has_circle("ring_outer"):
        return ()
    ring = target.circle("ring_outer")
    center_C = X_CT.apply(ring.center_T[None])[0]
    normal_C = X_CT.R @ ring.normal_T
    if center_C[2] <= ring.radius:
        return ()
    semi_major_px = camera.K[0, 0] * ring.radius / center_C[2]
    window = float(np.clip(RING_SEARCH_FRACTION * semi_major_px, *RING_SEARCH_PX))
    samples = sample_projected_circle(
        center_C, normal_C, ring.radius, camera, spacing_px=2.0, margin_px=window + 2.0
    )
    if samples is None or len(samples.uv) < 16:
        return ()
    lo = np.floor(samples.uv.min(axis=0) - window - 4.0)
    hi = np.ceil(samples.uv.max(axis=0) + window + 4.0)
    field = image.gradient_field(RING_SEARCH_SMOOTHING_PX, (*lo, *hi))
    edges = find_circle_edges(field, samples, camera, polarity=None, half_width_px=window)
    if edges.support < MIN_RING_SUPPORT or len(edges.uv_ideal) < 16:
        return ()
    try:
        conic = _trimmed_ellipse(edges.uv_ideal)
    except ValueError:
        return ()
    # The strongest edge near the predicted outer one may be the ring's inner edge (a pose too
    # near predicts the ring too large): the ellipse is read as each of the ring's circles.
    poses = []
    for name in ("ring_outer", "ring_inner"):
        if not target.has_circle(name):
            continue
        circle = target.circle(name)
        try:
            found = circle_poses_from_conic(conic, circle.radius, camera.K)
        except ValueError:
            continue
        poses += [pose_with_roll(c, circle, roll_of(X_CT, c, circle)) for c in found]
    return tuple(poses)


def _trimmed_ellipse(uv: np.ndarray) -> np.ndarray:
    """The direct ellipse fit of edge points, refitted once without those beyond three robust
    standard deviations of its Sampson distances (edges of the ring's neighbours the wide
    window met); ValueError when too few are left."""
    conic = fit_ellipse_direct(uv)
    distance = np.abs(sampson_distances(conic, uv))
    # 1.4826 × the median absolute value: a normal distribution's σ.
    keep = distance <= 3.0 * 1.4826 * max(median(distance), 1e-3)
    if np.sum(keep) < 16:
        raise ValueError("too few edge points agree on an ellipse")
    return fit_ellipse_direct(uv[keep])
