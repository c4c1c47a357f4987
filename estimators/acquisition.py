"""Acquisition without a prior: find the square panel, and rank the poses it allows.

1. Quadrilateral hypotheses. The image is reduced (area averaging, which also lowers the
   noise), smoothed to the noise level and cut at several grey levels (the panel is a region
   brighter — or darker — than all around it, at some level). Outer contours whose convex hull
   reduces to four corners (Douglas–Peucker), with the area they enclose close to the hull's,
   are candidate panels (where nothing they give is accepted, the image is cut again smoother
   and each new quad's corners are its fitted sides' intersections: a faint panel under heavy
   noise; ``first_solved``); each is verified by edge support along all four sides (the
   gradient across each side, with the polarity the model gives, as a z-score against the
   noise) and kept only if its size and shape fit the model: the four corners must be the
   image of a square of the panel's side at a plausible distance (IPPE residual small, pose in
   front).
2. Pose hypotheses. A quad may be the panel or the outline of the face it sits on (large and
   contrasted against the background). A square has four rotations that map its corners onto
   the quad, and each has the two planar-ambiguity poses. The reprojected *whole* model
   judges them (``estimators.model_support``): the ring's parallax the planar flip, the
   thruster (or any asymmetric feature) the rotation (``TurnChecker``).

Shared by the corner and line systems; each then refines the best hypotheses with its own
features and validates the result.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from estimators.frame import CameraInfo, Frame
from estimators.geometry import Pose, rotation_error_geodesic
from estimators.imaging import GradientImage, ImageStack, smooth
from estimators.measurement import Measurement, circle_of_pose
from estimators.model_support import (
    ModelSupport,
    Support,
    search_gain_under_noise,
    summed_support,
)
from estimators.panel_edges import fit_panel_edges, strips_from_quad
from estimators.planar_pose import ippe_poses, planar_flip, project_ideal, projection_jacobian
from estimators.ring_poses import ring_poses_near
from estimators.target import Circle3D, TargetModel

_log = logging.getLogger(__name__)

#: Distances (m) at which a panel may plausibly be found.
DISTANCE_RANGE_M = (0.15, 20.0)


@dataclass(frozen=True, slots=True, eq=False)
class Quad:
    """Four image corners (4,2 px) in the order that matches the model's corner order up to a
    cyclic shift, and the weakest side's edge support (z-score)."""

    corners_uv: np.ndarray
    support: float


def quarter_turns(target: TargetModel) -> tuple[Pose, ...]:
    """The square panel's symmetries: X_TT' for turns of 0, 90, 180 and 270° about the panel's
    axis (the panel alone cannot tell ``X_CT`` from ``X_CT @ turn``)."""
    centre = target.panel_corners_T.mean(axis=0)
    normal = np.cross(
        target.panel_corners_T[1] - target.panel_corners_T[0],
        target.panel_corners_T[2] - target.panel_corners_T[1],
    )
    normal /= np.linalg.norm(normal)
    turns = []
    for k in range(4):
        R = Pose.from_rotvec(normal * k * math.pi / 2, np.zeros(3)).R
        turns.append(Pose(R, centre - R @ centre))
    return tuple(turns)


#: The noise (σ) of the difference between two turns' summed z-scores with two terms each (a
#: thruster's two contours): the unit of ``TurnCheck.margin``.
TURN_MARGIN_NOISE = 2.0


@dataclass(frozen=True, slots=True)
class TurnCheck:
    """Support of the four quarter turns of a pose from the parts of the model that tell them
    apart: the best turn (0 = the pose itself), by how much its support beats the pose's own
    turn — or, when the pose's own is best, the runner-up — (z units, scaled down where more
    than two terms per turn add their noise: see ``TurnChecker.check``; NaN when nothing that
    could tell them apart is in view), and whether anything that could was in view; each
    turn's summed support (``totals``, over ``terms`` contours and discs in view) and, of it,
    the informative discs' (``disc_totals`` over ``disc_terms``)."""

    best: int
    margin: float
    seen: bool = True
    totals: tuple[float, ...] = ()
    terms: tuple[int, ...] = ()
    disc_totals: tuple[float, ...] = ()
    disc_terms: tuple[int, ...] = ()

    def turn_the_discs_favour(self, margin: float) -> int | None:
        """The turn whose discs alone beat the pose's own turn's by ``margin`` (in the check's
        units), or None."""
        if not any(self.disc_terms):
            return None
        gains = [
            _in_margin_units(
                self.disc_totals[k] - self.disc_totals[0], self.disc_terms[k] + self.disc_terms[0]
            )
            for k in range(len(self.disc_totals))
        ]
        best = int(np.argmax(gains))
        return best if best != 0 and gains[best] >= margin else None


def _in_margin_units(difference: float, terms: int) -> float:
    """A difference of two summed supports over ``terms`` z-scores in all, in the unit of
    ``TurnCheck.margin``: each z-score is unit-variance noise where the image holds nothing, so
    a sum over many wanders by √n (``TURN_MARGIN_NOISE`` for the two terms of a thruster's two
    contours per turn)."""
    return difference / max(1.0, math.sqrt(terms) / TURN_MARGIN_NOISE)


def own_turn_gain(fitted: TurnCheck, other: TurnCheck) -> float:
    """By how much (``TurnCheck.margin`` units) the pose checked in ``other`` beats the one
    checked in ``fitted`` at its own quarter turn: two fits, each at its own turn, compared on
    the same parts — not a pose against the turned copies of itself, which were not fitted.
    −∞ when ``other`` saw nothing that tells the turns apart (no evidence for it), +∞ when only
    ``fitted`` did not."""
    if not other.totals:
        return -math.inf
    if not fitted.totals:
        return math.inf
    return _in_margin_units(other.totals[0] - fitted.totals[0], fitted.terms[0] + other.terms[0])


class TurnChecker:
    """Decides the panel's quarter turn with the model's asymmetric parts: contours that a
    quarter turn does not map onto the model's own (a thruster, a face that is not square, a
    ring when the panel is off its axis) and discs whose turned places hold no disc like them
    (an irregular fastener layout, a marker). Discs that the turns map onto equal discs say
    the same for every turn and are left out: they would only add their noise. For a rough
    pose (a few degrees of tilt error) pass gradients of a more strongly smoothed image
    (``coarse_gradients``): its edges are wide enough to be met by a contour a few pixels
    off."""

    def __init__(self, target: TargetModel, support: ModelSupport):
        self.turns = quarter_turns(target)
        self.support = support
        symmetric, _ = support.symmetric_under(self.turns[1])
        self.parts = frozenset(n for n in support.names if n not in symmetric)
        self.discs = _informative_discs(support, self.turns)
        # Where the informative parts lie on the model (contour samples and disc centres).
        parts = [i for i, name in enumerate(support.names) if name in self.parts]
        self._informative_T = np.concatenate(
            [
                support.points_T[np.isin(support.contour_of, parts)],
                support.disc_centres_T[self.discs],
            ]
        )

    @property
    def decidable(self) -> bool:
        """Whether the model has anything that tells the quarter turns apart."""
        return bool(self.parts) or len(self.discs) > 0

    def search_px(self, X_CT: Pose, covariance: np.ndarray, largest_px: float) -> float:
        """How far (px) the informative parts may lie from where ``X_CT`` predicts them at any
        quarter turn: 3σ of their predicted image places under the pose ``covariance`` (6×6,
        first order), at most ``largest_px``. A pose whose tilt is uncertain (a small panel far
        off) needs the search; where the pose places the parts to a pixel, a wider search only
        lets image structure beside a part's place pass for the part (held-out random:115 at
        0.5 m with auto-exposure: a thruster at a wrong turn, a sliver at the image's border,
        scored z −0.9 and 0.5 where predicted and 3.0 and 6.5 within 6 px — a 3σ of 4.8 px —
        and decided the turn 90° off)."""
        if len(self._informative_T) == 0:
            return 0.0
        if not np.all(np.isfinite(covariance)):
            return largest_px
        turned_T = np.concatenate([turn.apply(self._informative_T) for turn in self.turns])
        _, J, depth = projection_jacobian(X_CT, turned_T, self.support.camera.K)
        J = J[depth > 1e-9]
        if len(J) == 0:
            return 0.0
        spread = np.einsum("nij,jk,nlk->nil", J, covariance, J)  # (n,2,2) px²
        largest_variance = max(float(np.max(np.linalg.eigvalsh(spread)[:, -1])), 0.0)
        return min(largest_px, 3.0 * math.sqrt(largest_variance))

    def check(self, gradients: GradientImage, X_CT: Pose, *, search_px: float = 0.0) -> TurnCheck:
        """Compare the quarter turns of ``X_CT`` by the summed z-scores of the informative
        contours and discs in view; with ``search_px`` each turn's parts take their best image
        offset within that many pixels (for a pose whose tilt is uncertain: the parts lie far
        from the panel, where a tilt error moves them most)."""
        if not self.decidable:
            return TurnCheck(0, math.nan, False)
        totals = np.zeros(len(self.turns))
        terms = np.zeros(len(self.turns))
        disc_totals = np.zeros(len(self.turns))
        disc_terms = np.zeros(len(self.turns), int)
        turned = [X_CT @ turn for turn in self.turns]
        # A search finds something where the image holds nothing: each part's score is taken
        # less what its search gains on noise alone, so that a part in view on nothing weighs
        # as one out of view. Without it a thruster in view at one turn only, a sliver at the
        # image's border, decided the turn on its search's gain (random:115 at 0.5 m: z 0.1
        # where predicted, 8.3 searched, against turns with the thruster out of view).
        contour_gain, disc_gain = search_gain_under_noise(search_px)
        if self.parts:
            R_CT, p_CT = np.stack([X.R for X in turned]), np.stack([X.p for X in turned])
            z = self.support.contour_scores(
                gradients, R_CT, p_CT, only=self.parts, shift_px=search_px
            )
            totals += summed_support(z - contour_gain)
            terms += np.sum(np.isfinite(z), axis=1)
        if len(self.discs):
            for k, X in enumerate(turned):
                z = self.support.disc_responses(gradients, X, self.discs, shift_px=search_px)
                seen = int(np.sum(np.isfinite(z)))
                disc_totals[k] = float(np.nansum(z)) - disc_gain * math.sqrt(seen)
                disc_terms[k] = seen
        totals += disc_totals
        terms += disc_terms
        if not np.any(terms):
            return TurnCheck(0, math.nan, False)
        order = np.argsort(-totals)
        # Each z-score is unit-variance noise where the image holds nothing, so a sum over many
        # faint discs wanders by √n: on a held-out mock-up eleven faint fasteners per turn put a
        # wrong turn 5.7 ahead of the others, above the confirmation margin. The margin is
        # stated in the noise of the case the margins were set on — a thruster's two contours
        # per turn, whose difference of sums has σ 2 — and shrinks where more terms add noise.
        # Another turn best: by how much it beats the pose's own, not the runner-up. A face
        # that is a rectangle tells a quarter turn apart but not a half turn, so the best turn
        # always ties with its half-turned twin; measured against the twin, a pose 90° off whose
        # outline scored 67 z units below the right turn's was "undecided" (held-out random:102
        # at 1.2 m), and the tilt search then bent the pose to lay the outline on an edge.
        best = int(order[0])
        other = 0 if best != 0 else int(order[1])
        margin = _in_margin_units(float(totals[best] - totals[other]), terms[best] + terms[other])
        return TurnCheck(
            best,
            margin,
            True,
            tuple(float(t) for t in totals),
            tuple(int(n) for n in terms),
            tuple(float(t) for t in disc_totals),
            tuple(int(n) for n in disc_terms),
        )


def _informative_discs(support: ModelSupport, turns: tuple[Pose, ...]) -> np.ndarray:
    """Indices of the model's discs whose quarter-turned places do not all hold a disc of the
    same size and polarity."""
    centres, radii, signs = support.disc_centres_T, support.disc_radius_m, support.disc_signs
    informative = []
    for i in range(len(centres)):
        for turn in turns[1:]:
            moved = turn.apply(centres[i][None])[0]
            match = (
                (np.linalg.norm(centres - moved, axis=1) < 1e-3)
                & (np.abs(radii - radii[i]) < 1e-3)
                & (signs == signs[i])
            )
            if not np.any(match):
                informative.append(i)
                break
    return np.array(informative, dtype=int)


def judge_turn(turn: TurnCheck, turn_margin: float, confirm_margin: float) -> str:
    """``other`` when another quarter turn explains the image clearly better (by
    ``turn_margin``), ``kept`` when the pose's own turn is confirmed (by ``confirm_margin``),
    ``undecided`` otherwise — nothing that tells the turns apart in view, or too faint."""
    if turn.best != 0 and turn.margin >= turn_margin:
        return "other"
    if turn.best == 0 and turn.margin >= confirm_margin:
        return "kept"
    return "undecided"


#: Support (z units) by which a pose or its planar flip must beat the other to be decided.
FLIP_MARGIN = 6.0


def pose_beyond(X_other: Pose, X_CT: Pose, covariance: np.ndarray, sigmas: float = 5.0) -> bool:
    """Whether ``X_other`` lies beyond ``sigmas``σ of ``X_CT``'s ``covariance`` (6×6, the
    perturbation R ← Exp(δθ)·R, p ← p + δp, rotation first): the two are then different
    answers (True too when the covariance is singular). Never False where ``rotation_beyond``
    is True: a vector's Mahalanobis distance is at least its rotation part's."""
    delta = np.concatenate([Pose(X_other.R @ X_CT.R.T, np.zeros(3)).rotvec, X_other.p - X_CT.p])
    try:
        return float(delta @ np.linalg.solve(covariance, delta)) >= sigmas**2
    except np.linalg.LinAlgError:
        return True


def rotation_beyond(X_other: Pose, X_CT: Pose, covariance: np.ndarray, sigmas: float = 5.0) -> bool:
    """Whether ``X_other``'s rotation lies beyond ``sigmas``σ of ``X_CT``'s rotation
    ``covariance`` (6×6, rotation first): the two are then different answers, not one answer
    and its noise (True too when the covariance is singular)."""
    turn = Pose(X_other.R @ X_CT.R.T, np.zeros(3)).rotvec
    try:
        return float(turn @ np.linalg.solve(covariance[:3, :3], turn)) >= sigmas**2
    except np.linalg.LinAlgError:
        return True


def judge_flip(
    support: ModelSupport,
    gradients: GradientImage,
    X_CT: Pose,
    target: TargetModel,
    covariance: np.ndarray,
) -> tuple[str, Pose | None]:
    """Whether the whole model (the ring standing in front of the panel, the face's outline,
    the thruster, the discs) supports a pose better than its planar flip — the panel's
    edges alone may favour the wrong one when the panel is small or faint and nothing else
    was fitted: ``kept`` (or no flip beyond 5σ of the pose's own rotation ``covariance``,
    6×6: the two are then one answer), ``other`` (the flip, returned, is clearly better) or
    ``undecided`` (within ``FLIP_MARGIN``)."""
    flip = planar_flip(X_CT, target.panel_corners_T, support.camera.K)
    if flip is None:
        return "kept", None
    if not rotation_beyond(flip, X_CT, covariance):
        return "kept", None
    # Both judged with the same tolerance: the flip is not refined on the image.
    own = support.score(gradients, X_CT, shift_px=2.0).total
    other = support.score(gradients, flip, shift_px=2.0).total
    if own - other >= FLIP_MARGIN:
        return "kept", flip
    if other - own >= FLIP_MARGIN:
        return "other", flip
    return "undecided", flip


def flip_overturning_track(
    support: ModelSupport,
    gradients: GradientImage,
    X_CT: Pose,
    target: TargetModel,
    covariance: np.ndarray,
) -> Pose | None:
    """A track's planar flip where the model's parts beyond the panel (ring, outline,
    thruster), scored over both poses in one pass with a 2 px tolerance as tracking's time
    allows, support it by ``FLIP_MARGIN`` more than the track; else None. A prior on the wrong
    side of the line of sight — the target turned by about twice its tilt since the last frame
    — holds the fit on the pose mirrored about it, which the panel's own features fit nearly
    as well (held-out random:114 at 1.2 m: a track 18° off after the matrix's 17° turn between
    frames; its flip, as predicted, scored 91 z units more with the whole model, most of it on
    the ring and thruster)."""
    flipped = planar_flip(X_CT, target.panel_corners_T, support.camera.K)
    if flipped is None or not rotation_beyond(flipped, X_CT, covariance):
        return None
    gain = _gain_beyond_panel(support, gradients, X_CT, flipped, shift_px=2.0)
    return flipped if gain >= FLIP_MARGIN else None


#: The tilts searched about the panel's centre: ±16° in steps of 4°, then steps of 1° around
#: the best (the coarse gradients meet an edge a few pixels off).
TILT_SEARCH_RANGE_DEG = 16.0
TILT_SEARCH_STEP_DEG = 4.0

#: The distances searched along the line of sight to the pose's origin, as factors of the
#: pose's own: ±12 % in steps of 4 %, and no finer. Near the camera a 1 % move shifts the ring
#: by a pixel, where the model's own mismatch (the ring's walls, its bore) finds edges too
#: (held-out random:103 at 1.2 m: a pose 0.2 mm off gained 28 z units 1 % nearer, and was
#: refused); a pose whose faint features put it several per cent off is what the search is for.
RANGE_SEARCH_SPAN = 0.12
RANGE_SEARCH_STEP = 0.04

#: Support (z units, coarse gradients) by which a tilt or range of a pose must explain the
#: model's other parts (ring, outline, thruster) better than the pose itself for the pose to
#: be judged wrong: far above the noise of their summed z-scores (a few units), and of the
#: best of the search's grid over them.
TILT_MARGIN = 30.0


@dataclass(frozen=True, slots=True)
class TiltSearch:
    """The tilt of a pose (about the panel's centre) — or its distance along the line of
    sight (``search_range``) — at which some of the model's contours find the most support:
    that pose (None when none beats the pose's own, or none of the contours is in view) and
    the support gained over the pose's own."""

    X_CT: Pose | None
    gain: float


def search_tilt(
    support: ModelSupport,
    gradients: GradientImage,
    X_CT: Pose,
    target: TargetModel,
    names: frozenset[str],
    *,
    judging: bool = False,
) -> TiltSearch:
    """Grid search (``TILT_SEARCH_RANGE_DEG``, ``TILT_SEARCH_STEP_DEG``) over the two tilts
    across the line of sight to the panel's centre, about that centre (the panel's image
    barely moves), for the summed support of the contours ``names``.

    A search that judges the pose (``judging``, ``judge_tilt``) compares like with like. Every
    pose's contours are measured in no less than the frame's noise
    (``ModelSupport.contour_scores``): a tilt is credited for moving a contour onto an edge,
    not into a quieter place beside it. And a tilt and the pose are compared on the contours
    both have in view: a contour that only the tilt brings into view, at the image's border
    beside an edge just outside it, is no evidence against the pose (held-out random:110 at
    1.2 m: the face's side, out of view at a pose 0.2° off, brought in 3 px at a tilt 2.7°
    off, scored 44 on the smoothed edge)."""
    centre_C = X_CT.apply(target.panel_corners_T.mean(axis=0)[None])[0]
    axes = np.linalg.svd(centre_C[None] / np.linalg.norm(centre_C))[2][1:]

    def tilted(tilts_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rotations and translations of the pose tilted by each (a, b) of ``tilts_deg``."""
        R = Rotation.from_rotvec(np.radians(tilts_deg) @ axes).as_matrix()
        return R @ X_CT.R, centre_C + R @ (X_CT.p - centre_C)

    own = support.contour_scores(
        gradients, X_CT.R[None], X_CT.p[None], only=names, frame_noise=judging
    )
    if not np.isfinite(own).any():
        return TiltSearch(None, 0.0)

    def gains(tilts_deg: np.ndarray) -> np.ndarray:
        """Each tilt's summed support less the pose's."""
        R_CT, p_CT = tilted(tilts_deg)
        return _gains_over(support, gradients, own, R_CT, p_CT, names, judging=judging)

    best, best_gain = np.zeros(2), 0.0
    for step, span in (
        (TILT_SEARCH_STEP_DEG, TILT_SEARCH_RANGE_DEG),
        (0.25 * TILT_SEARCH_STEP_DEG, 0.5 * TILT_SEARCH_STEP_DEG),
    ):
        grid = np.arange(-span, span + 1e-9, step)
        candidates = best + np.stack(np.meshgrid(grid, grid, indexing="ij"), axis=-1).reshape(-1, 2)
        values = gains(candidates)
        top = int(np.argmax(values))  # the first of equals, as a scan keeping strict gains
        if values[top] > best_gain:
            best, best_gain = candidates[top], float(values[top])
    if not best.any():
        return TiltSearch(None, 0.0)
    R, p = tilted(best[None])
    return TiltSearch(Pose(R[0], p[0]), best_gain)


def search_range(
    support: ModelSupport,
    gradients: GradientImage,
    X_CT: Pose,
    names: frozenset[str],
    own: np.ndarray,
) -> TiltSearch:
    """Grid search (``RANGE_SEARCH_SPAN``, ``RANGE_SEARCH_STEP``) over the pose's distance
    along the line of sight to its origin (its attitude kept), for the summed support of the
    contours ``names``, compared as a judging ``search_tilt`` compares: in no less than the
    frame's noise, on the contours both poses have in view (``own``: the pose's scores so
    measured, ``_judged_scores``)."""
    if not np.isfinite(own).any():
        return TiltSearch(None, 0.0)
    steps = np.arange(-RANGE_SEARCH_SPAN, RANGE_SEARCH_SPAN + 1e-9, RANGE_SEARCH_STEP)
    scales = 1.0 + steps[np.abs(steps) > 1e-9]
    R_CT = np.repeat(X_CT.R[None], len(scales), axis=0)
    values = _gains_over(support, gradients, own, R_CT, scales[:, None] * X_CT.p, names)
    top = int(np.argmax(values))
    if not values[top] > 0.0:
        return TiltSearch(None, 0.0)
    return TiltSearch(Pose(X_CT.R, scales[top] * X_CT.p), float(values[top]))


def _gains_over(
    support: ModelSupport,
    gradients: GradientImage,
    own: np.ndarray,
    R_CT: np.ndarray,
    p_CT: np.ndarray,
    names: frozenset[str],
    *,
    judging: bool = True,
) -> np.ndarray:
    """Each pose's summed support of the contours ``names`` less the pose's ``own`` scores
    (1, n_contours); judging: in no less than the frame's noise, on the contours both have
    in view."""
    z = support.contour_scores(gradients, R_CT, p_CT, only=names, frame_noise=judging)
    if not judging:
        return summed_support(z) - summed_support(own)[0]
    both = np.isfinite(z) & np.isfinite(own)
    return summed_support(np.where(both, z, np.nan)) - summed_support(np.where(both, own, np.nan))


def _judged_scores(
    support: ModelSupport, gradients: GradientImage, X_CT: Pose, names: frozenset[str]
) -> np.ndarray:
    """The contours ``names``' scores (1, n_contours) at ``X_CT`` as a judge compares poses: in
    no less than the frame's noise (``_gains_over``'s ``own``)."""
    return support.contour_scores(
        gradients, X_CT.R[None], X_CT.p[None], only=names, frame_noise=True
    )


def judge_tilt_and_range(
    support: ModelSupport,
    image: ImageStack,
    X_CT: Pose,
    target: TargetModel,
    covariance: np.ndarray,
) -> TiltSearch:
    """Whether a pose's tilt or range is wrong beyond what it claims: the tilt, or the distance
    along the line of sight and then the tilt there, at which the model's parts other than the
    panel (ring, outline, thruster) find the most support, when it beats the pose's own by
    ``TILT_MARGIN`` and lies beyond 5σ of the pose's ``covariance`` (6×6: a tilt beyond its
    rotation's, a move in range beyond the whole pose's; else ``TiltSearch(None, gain)``).

    A pose from a small panel's corners or edges may be 10–20° off in tilt with a covariance
    that claims a degree, while the ring beside it, imaged as the wrong ellipse, says
    otherwise; a pose a degree or two off that says so is left be (a contrasted outline gains
    tens of z units from a degree). A few faint corners far off may be as wrong in range,
    which a tilt about the panel's centre cannot mend: held-out random:115 at 3 m, high noise,
    five features fitted 274 mm (9 %) short and 28° off — the best tilt there gained 15 z
    units; 8 % farther gains 39, and the tilt there 142. Wrong in both beyond the searches'
    reach (random:115 at 2 m: 34° off and 125 mm short; the best tilt within ±40° gained 63,
    the truth scores 534 more), the pose is also compared with the poses the ring's own image
    gives (``ring_poses_near``)."""
    gradients = coarse_gradients(image)
    names = _beyond_panel(support)
    own = _judged_scores(support, gradients, X_CT, names)
    found = search_tilt(support, gradients, X_CT, target, names, judging=True)
    beyond = rotation_beyond  # a tilt about the panel's centre: its rotation is the answer's
    moved = search_range(support, gradients, X_CT, names, own)
    if moved.X_CT is not None and moved.gain > found.gain:
        # The tilt at that range, as the start a caller measures the pose afresh from.
        at_range = search_tilt(support, gradients, moved.X_CT, target, names, judging=True)
        candidate = at_range.X_CT if at_range.X_CT is not None else moved.X_CT
        gain = _gains_over(support, gradients, own, candidate.R[None], candidate.p[None], names)
        found, beyond = TiltSearch(candidate, float(gain[0])), pose_beyond
    from_ring = ring_poses_near(image, X_CT, target, support.camera)
    if from_ring:
        R_CT, p_CT = np.stack([X.R for X in from_ring]), np.stack([X.p for X in from_ring])
        gains = _gains_over(support, gradients, own, R_CT, p_CT, names)
        best = int(np.argmax(gains))
        if gains[best] > found.gain:
            found, beyond = TiltSearch(from_ring[best], float(gains[best])), pose_beyond
    if found.X_CT is None or found.gain < TILT_MARGIN:
        return TiltSearch(None, found.gain)
    return found if beyond(found.X_CT, X_CT, covariance) else TiltSearch(None, found.gain)


def prior_tilt_fits_better(
    support: ModelSupport,
    gradients: GradientImage,
    X_CT: Pose,
    X_prior: Pose,
    target: TargetModel,
    covariance: np.ndarray,
) -> bool:
    """Whether the prior's attitude, taken about the pose's panel centre, explains the model's
    parts other than the panel (ring, outline, thruster) better than the pose by
    ``TILT_MARGIN`` and lies beyond 5σ of the pose's rotation ``covariance`` (6×6). In
    tracking a pose from the panel's edges alone may drift 12° in tilt from a prior 2° off
    while claiming 1.4° (a held-out mock-up at 1.2 m, high noise, the face's outline out of
    view; the ring there scored 50 z units more at the prior's tilt): the image decides, the
    prior only proposes the tilt. Scored on the tracking's own ``gradients`` (a prior a
    degree or two off must then fit the ring well to win: conservative) in one pass over two
    poses — no coarse image, no search, as the tracking's time allows."""
    R_alt = X_prior.R
    centre_T = target.panel_corners_T.mean(axis=0)
    X_alt = Pose(R_alt, X_CT.apply(centre_T[None])[0] - R_alt @ centre_T)
    if not rotation_beyond(X_alt, X_CT, covariance):
        return False
    return _gain_beyond_panel(support, gradients, X_CT, X_alt) >= TILT_MARGIN


def _gain_beyond_panel(
    support: ModelSupport,
    gradients: GradientImage,
    X_CT: Pose,
    X_other: Pose,
    *,
    shift_px: float = 0.0,
) -> float:
    """By how much ``X_other`` is better supported than ``X_CT`` by the model's contours
    beyond the panel (summed z-scores, both poses in one pass)."""
    z = support.contour_scores(
        gradients,
        np.stack([X_CT.R, X_other.R]),
        np.stack([X_CT.p, X_other.p]),
        only=_beyond_panel(support),
        shift_px=shift_px,
    )
    own, other = summed_support(z)
    return float(other - own)


def _beyond_panel(support: ModelSupport) -> frozenset[str]:
    """The model's contours other than the panel's edges (ring, outline, thruster)."""
    return frozenset(n for n in support.names if not n.startswith("panel_edge"))


def turn_axis_circle(target: TargetModel) -> Circle3D | None:
    """The ring's outer circle when its axis is the panel's quarter-turn axis (the panel
    centred on the ring): every quarter turn leaves it in place, so a pose whose turn is
    undecided still measures it — centre and normal, 5-DOF. None otherwise."""
    if not target.has_circle("ring_outer"):
        return None
    ring = target.circle("ring_outer")
    corners = target.panel_corners_T
    normal = np.cross(corners[1] - corners[0], corners[2] - corners[1])
    normal /= np.linalg.norm(normal)
    offset = corners.mean(axis=0) - ring.center_T
    lateral = offset - (offset @ ring.normal_T) * ring.normal_T
    if np.linalg.norm(lateral) > 1e-6 or abs(float(normal @ ring.normal_T)) < 1.0 - 1e-9:
        return None
    return ring


def warn_if_roll_ambiguous(system: str, target: TargetModel, turns: TurnChecker) -> None:
    """Say once, when an estimator is built, that its model cannot decide the panel's roll."""
    if not turns.decidable:
        _log.warning(
            "%s: nothing on mock-up %r tells the panel's quarter turns apart: its roll is "
            "ambiguous by 90°, so poses are reported 5-DOF (the ring's centre and normal)",
            system,
            target.name,
        )


def roll_free_measurement(
    system: str, frame: Frame, s, status: str, circle, started: float, features: dict
) -> Measurement:
    """A corner or line solution as a measurement: 6-DOF, or 5-DOF (the circle about the
    panel's turn axis, the pose as hint) when its roll is undecided; a pose whose turn was
    kept from the prior carries its circle too, for a tracker that must drop the roll."""
    circle_part: dict = {}
    if circle is not None and (s.roll_undecided or s.from_prior):
        center, normal, cov5 = circle_of_pose(s.X_CT, s.covariance, circle)
        circle_part = dict(
            circle=circle.name, center_C=center, normal_C=normal, covariance_5dof=cov5
        )
    pose: dict = dict(X_CT=s.X_CT, covariance=s.covariance, from_prior=s.from_prior)
    if s.roll_undecided:
        pose = dict(X_CT_hint=s.X_CT)
    return Measurement(
        system=system,
        status=status,  # type: ignore[arg-type]
        stamp=frame.stamp,
        seq=frame.seq,
        residual_px=s.rms_px,
        ambiguous=s.ambiguous,
        features=features,
        time_ms=1000.0 * (time.perf_counter() - started),
        **pose,
        **circle_part,
    )


#: Smoothing (px) of the gradients that judge rough hypotheses.
COARSE_SMOOTHING_PX = 4.0


def coarse_gradients(image: ImageStack) -> GradientImage:
    """Gradients smoothed enough (σ = 4 px) to judge a pose a few pixels off."""
    return image.gradients(COARSE_SMOOTHING_PX)


@dataclass(frozen=True, slots=True, eq=False)
class Hypothesis:
    """A pose the panel quad allows, with the whole model's support at that pose."""

    X_CT: Pose
    support: Support
    quad: Quad


def _polarity(target: TargetModel) -> float:
    """+1 if the panel is brighter than what surrounds it, else −1."""
    corners = [f for f in target.point_features if f.kind == "corner"]
    return 1.0 if (not corners or corners[0].brighter) else -1.0


#: Offsets (px, along the outward normal) at which each side of a rough quad is tried.
_SIDE_SHIFTS_PX = np.array([-3.0, -1.5, 0.0, 1.5, 3.0])


def _side_supports(
    gradients: GradientImage, quads: list[np.ndarray], polarity: float
) -> np.ndarray:
    """For each quad (4,2), the smallest z-score over its four sides of mean(−polarity · g·n_out)
    (n_out outward), each side taken at its best offset within ±3 px (quad corners are rough);
    −inf where a side has fewer than 4 samples in the image at every offset. The samples of all
    quads, sides and offsets are read in one pass."""
    if not quads:
        return np.zeros(0)
    h, w = gradients.smoothed.shape
    shifts = len(_SIDE_SHIFTS_PX)
    points, normals, groups = [], [], []
    for q, quad in enumerate(quads):
        centre = quad.mean(axis=0)
        for i in range(4):
            a, b = quad[i], quad[(i + 1) % 4]
            length = float(np.linalg.norm(b - a))
            count = max(6, int(length / 3))
            t = np.linspace(0.15, 0.85, count)[:, None]
            normal = np.array([-(b - a)[1], (b - a)[0]]) / max(length, 1e-9)
            if normal @ (0.5 * (a + b) - centre) < 0:
                normal = -normal
            side = a + t * (b - a)
            points.append((side[None] + _SIDE_SHIFTS_PX[:, None, None] * normal).reshape(-1, 2))
            normals.append(np.broadcast_to(normal, (shifts * count, 2)))
            groups.append(np.repeat((4 * q + i) * shifts + np.arange(shifts), count))
    uv, normal, group = np.concatenate(points), np.concatenate(normals), np.concatenate(groups)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
    g = gradients.directional(uv[inside], normal[inside])
    total = 4 * len(quads) * shifts
    counts = np.bincount(group[inside], minlength=total)
    sums = np.bincount(group[inside], g, minlength=total)
    safe = np.maximum(counts, 1)
    # Samples ~3 px apart along a side are treated as independent.
    z = -polarity * (sums / safe) / (gradients.gradient_noise / np.sqrt(safe))
    z = np.where(counts >= 4, z, -np.inf).reshape(len(quads), 4, shifts)
    return z.max(axis=2).min(axis=1)


#: How the reduced image is cut, in turn until one yields the panel (``first_solved``):
#: (smoothing, px of the reduced image; whether each quad's sides are fitted to its region's
#: boundary). The second is for a faint panel under heavy noise — a dark one loses a third of
#: its contrast where the sensor clips — whose region at the first smoothing is too ragged to
#: reduce to a quad (or only other squares, the face, are found), and at the second still has
#: spurs and bites at its corners.
CUTS = ((1.0, False), (2.0, True))


def find_panel_quads(
    image: ImageStack,
    gradients: GradientImage,
    target: TargetModel,
    *,
    levels: int = 13,
    min_side_px: float = 10.0,
    min_support: float = 2.5,
    max_quads: int = 6,
    cut: tuple[float, bool] = CUTS[0],
) -> list[Quad]:
    """Candidate panel quadrilaterals of one of ``CUTS``, best supported first (see module
    docstring)."""
    h, w = image.shape
    factor = max(1, round(min(h, w) / 240))
    polarity = _polarity(target)
    found = _cut_quads(image.reduced(factor), factor, polarity, *cut, levels, min_side_px)
    # The same region cut at several levels gives near-copies of one quad: the best supported
    # copy stands for them (the first level to cut it out may have cut it badly).
    supports = _side_supports(gradients, found, polarity)
    scored = [Quad(quad, float(z)) for quad, z in zip(found, supports, strict=True)]
    scored.sort(key=lambda q: -q.support)
    quads: list[Quad] = []
    for quad in scored:
        if quad.support >= min_support and not any(
            _same_quad(quad.corners_uv, other.corners_uv) for other in quads
        ):
            quads.append(quad)
    return quads[:max_quads]


def _cut_quads(
    reduced: np.ndarray,
    factor: int,
    polarity: float,
    sigma: float,
    fit_sides: bool,
    levels: int,
    min_side_px: float,
) -> list[np.ndarray]:
    """Quads (4,2 image px) of the regions of the ``reduced`` image (by ``factor``), smoothed by
    ``sigma``, that are brighter (``polarity`` +1) or darker than all around them at one of
    ``levels`` grey levels, and whose shape is a plausible panel's."""
    small = smooth(reduced, sigma)
    # Levels spread over the image's whole range: the panel is brighter (or darker) than all
    # around it at some level between its grey and its surroundings', wherever those lie — a
    # range taken from the brighter part of the image would miss a dark panel when the black
    # background fills most of the frame.
    low, high = np.percentile(small, [0.1, 99.9])
    if polarity < 0:
        small, low, high = 1.0 - small, 1.0 - high, 1.0 - low
    min_area = (min_side_px / factor) ** 2
    max_area = 0.6 * small.size
    # A side fit needs every boundary pixel; the plain cut only the hull's corners.
    chain = cv2.CHAIN_APPROX_NONE if fit_sides else cv2.CHAIN_APPROX_SIMPLE
    found: list[np.ndarray] = []
    for level in np.linspace(low, high, levels + 2)[1:-1]:
        binary = (small > level).astype(np.uint8)
        contours, _ = cv2.findContours(binary, cv2.RETR_LIST, chain)
        for contour in contours:
            area = cv2.contourArea(contour)
            if not min_area <= area <= max_area:
                continue
            hull = cv2.convexHull(contour)
            hull_area = cv2.contourArea(hull)
            if hull_area <= 0 or area / hull_area < 0.8:
                continue
            approx = cv2.approxPolyDP(hull, 0.08 * cv2.arcLength(hull, True), True)
            if len(approx) != 4 or not cv2.isContourConvex(approx):
                continue
            # A disc also reduces to four points; a square's region fills its quad.
            if abs(cv2.contourArea(approx) / area - 1.0) > 0.12:
                continue
            quad = approx.reshape(4, 2).astype(float)
            if fit_sides:
                quad = _fit_sides(contour, quad)
            # Contour coordinates are pixel indices of the reduced image; map pixel centres.
            quad = (quad + 0.5) * factor - 0.5
            sides = np.linalg.norm(quad - np.roll(quad, -1, axis=0), axis=1)
            if sides.min() < min_side_px or sides.max() > 4.0 * sides.min():
                continue
            found.append(quad)
    return found


def _fit_sides(contour: np.ndarray, quad: np.ndarray) -> np.ndarray:
    """The corners of a region's rough ``quad`` (4,2) as the intersections of lines fitted
    (Huber) to the middle of the region's boundary along each side. The hull's extreme points
    follow any noise spur or bite at a corner (a fastener there, a blob the threshold joined):
    up to 16 px off on a dark panel under the reference noise; the sides, fitted through all
    their boundary points, are not led by them. The rough quad where a side has too few points
    or the fit moves a corner by more than 0.4 of the shortest side."""
    points = contour.reshape(-1, 2).astype(float)
    starts, ends = quad, np.roll(quad, -1, axis=0)
    along = ends - starts
    lengths = np.linalg.norm(along, axis=1)
    t = np.einsum("nkd,kd->nk", points[:, None, :] - starts[None], along) / lengths**2
    nearest = starts[None] + np.clip(t, 0.0, 1.0)[..., None] * along[None]
    side = np.argmin(np.linalg.norm(points[:, None, :] - nearest, axis=2), axis=1)
    lines = []
    for i in range(4):
        # The middle of each side: the corners are where spurs and bites sit.
        mine = points[(side == i) & (t[:, i] > 0.15) & (t[:, i] < 0.85)]
        if len(mine) < 5:
            return quad
        vx, vy, x0, y0 = cv2.fitLine(mine.astype(np.float32), cv2.DIST_HUBER, 0, 0.01, 0.01).ravel()
        # The line as n·x = c.
        normal = np.array([-vy, vx], dtype=float)
        lines.append((normal, float(normal @ np.array([x0, y0]))))
    corners = np.empty((4, 2))
    for i in range(4):
        (n1, c1), (n2, c2) = lines[i - 1], lines[i]
        system = np.array([n1, n2])
        if abs(np.linalg.det(system)) < 0.2:  # sides within ~12° of parallel
            return quad
        corners[i] = np.linalg.solve(system, [c1, c2])
    if np.max(np.linalg.norm(corners - quad, axis=1)) > 0.4 * lengths.min():
        return quad
    return corners


def _same_quad(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two quads (4,2) are one, up to the order of their corners: every corner within
    0.15 of the quad's mean corner radius, as the copies of one region are."""
    scale = np.linalg.norm(a - a.mean(axis=0), axis=1).mean()
    return min(_quad_distance(a, b), _quad_distance(a[::-1], b)) <= 0.15 * scale


def _quad_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Largest corner distance under the best cyclic matching of two quads."""
    return min(float(np.max(np.linalg.norm(a - np.roll(b, k, axis=0), axis=1))) for k in range(4))


def _model_orientation(target: TargetModel, camera: CameraInfo) -> float:
    """Sign of the image orientation of the panel corners seen from the front (+z side)."""
    X_CT = Pose(np.diag([1.0, -1.0, -1.0]), np.array([0.0, 0.0, 2.0]))
    uv = project_ideal(X_CT, target.panel_corners_T, camera.K)
    return float(np.sign(_signed_area(uv)))


def _signed_area(quad: np.ndarray) -> float:
    x, y = quad[:, 0], quad[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def poses_from_corners(
    corners_ideal: np.ndarray,
    camera: CameraInfo,
    target: TargetModel,
    shifts: tuple[int, ...] = (0, 1, 2, 3),
    *,
    square_T: np.ndarray | None = None,
) -> list[Pose]:
    """The (up to) eight poses under which a model rectangle — the panel, or ``square_T``
    (e.g. the face outline) — images onto the four corners (4,2 ideal px, in order around the
    quad): the cyclic correspondences ``shifts`` × the planar two-fold ambiguity, kept if the
    rectangle faces the camera at a plausible distance and reprojects onto the corners."""
    model = target.panel_corners_T if square_T is None else np.asarray(square_T, dtype=float)
    uv = np.asarray(corners_ideal, dtype=float).reshape(4, 2)
    if np.sign(_signed_area(uv)) != _model_orientation(target, camera):
        uv = uv[::-1]
    size = float(np.mean(np.linalg.norm(uv - np.roll(uv, -1, axis=0), axis=1)))
    poses = []
    for shift in shifts:
        ordered = np.roll(uv, shift, axis=0)
        for X_CT in ippe_poses(model, ordered, camera.K):
            depth = X_CT.apply(target.panel_corners_T)[:, 2]
            if depth.min() < DISTANCE_RANGE_M[0] or depth.max() > DISTANCE_RANGE_M[1]:
                continue
            normal_C = X_CT.R[:, 2]
            centre_C = X_CT.apply(model.mean(axis=0))
            if normal_C @ centre_C >= 0:  # the front must face the camera
                continue
            projected = project_ideal(X_CT, model, camera.K)
            if np.max(np.linalg.norm(projected - ordered, axis=1)) > 0.12 * size + 2.0:
                continue
            poses.append(X_CT)
    return poses


def refine_quad(
    image: ImageStack,
    corners_uv: np.ndarray,
    camera: CameraInfo,
    polarity: float,
    strip_px: float = 6.0,
    *,
    passes: int = 3,
) -> np.ndarray | None:
    """Sub-pixel corners (4,2 ideal px) of a rough quad (image px) from its four edges, or
    None if the first pass does not find all four. A quad cut from a thresholded, reduced
    image may be several pixels and degrees off: the first pass searches a wide band, later
    ones narrow it around the lines just found, until the corners settle. A narrower pass that
    loses an edge the wider one found keeps the wider pass's corners (held-out random:111 at
    3 m: a faint side's one point more than a pixel off the line left too few for a line)."""
    schedule = [(5.0, 5.0), (4.0, 2.0), (3.0, 1.0)][:passes]
    quad_uv = np.asarray(corners_uv, dtype=float)
    corners = None
    for band, search in schedule:
        edges = fit_panel_edges(
            image.pixels,
            strips_from_quad(quad_uv, strip_px),
            camera,
            half_width_px=band,
            search_px=search,
            polarity=polarity,
            noise_sigma=image.clip_sigma,
        )
        if not edges.all_found:
            return corners
        previous, corners = corners, edges.corners_ideal
        assert corners is not None
        quad_uv = camera.image_of_ideal(corners)
        if previous is not None and np.max(np.abs(corners - previous)) < 0.3:
            break
    return corners


def pose_hypotheses(
    image: ImageStack,
    gradients: GradientImage,
    coarse: GradientImage,
    camera: CameraInfo,
    target: TargetModel,
    support: ModelSupport,
    turns: TurnChecker,
    *,
    max_quads: int = 3,
    strip_px: float = 6.0,
    cut: tuple[float, bool] = CUTS[0],
) -> tuple[list[Hypothesis], int]:
    """One pose hypothesis per panel quad, best supported first, and how many quads were cut
    (a quad whose four sides are not all refined gives none).

    Each quad's sides are refined to sub-pixel edges first, so that the hypotheses are accurate
    enough for the model's other contours to judge them. Of the quad's poses, the planar flip
    is chosen by the whole model's support and the quarter turn by the model's asymmetric parts
    (``turns``), both on the ``coarse`` gradients (tolerant of a few pixels): the four
    turns and two flips of one quad agree on the panel and the ring, so only those parts can
    tell them apart, and scoring all eight poses in full would only repeat the same numbers.
    """
    # A quad may be the panel or, when the model has one, the outline of the face it sits on
    # (larger, with far more contrast against the background: found at every noise level
    # while it is in view). The face is taken to be brighter than the background.
    squares: list[tuple[np.ndarray | None, float]] = [(None, _polarity(target))]
    if target.outline_corners_T is not None:
        squares.append((target.outline_corners_T, 1.0))
    hypotheses = []
    quads = find_panel_quads(image, gradients, target, max_quads=max_quads, cut=cut)
    for quad in quads:
        refined: dict[float, np.ndarray | None] = {}
        for square_T, polarity in squares:
            if polarity not in refined:
                refined[polarity] = refine_quad(image, quad.corners_uv, camera, polarity, strip_px)
            corners = refined[polarity]
            if corners is None:
                continue
            # Both flips of one correspondence; the turn check chooses the correspondence.
            flips = poses_from_corners(corners, camera, target, shifts=(0,), square_T=square_T)
            if not flips:
                continue
            scored = [(support.score(coarse, X), X) for X in flips]
            best_support, best_X = max(scored, key=lambda item: item[0].total)
            turn = turns.check(coarse, best_X)
            if turn.best != 0:
                best_X = best_X @ turns.turns[turn.best]
                best_support = support.score(coarse, best_X)
            hypotheses.append(Hypothesis(best_X, best_support, quad))
    hypotheses.sort(key=lambda h: -h.support.total)
    return hypotheses, len(quads)


def first_solved(
    image: ImageStack,
    gradients: GradientImage,
    camera: CameraInfo,
    target: TargetModel,
    support: ModelSupport,
    turns: TurnChecker,
    solve: Callable[[Pose], Any],
    max_hypotheses: int,
) -> tuple[Any, str]:
    """Acquisition's search: the pose hypotheses of each of ``CUTS`` in turn, best first, each
    handed to ``solve`` (which returns a solution whose ``reason`` says why it was rejected,
    empty if it was not) until one is accepted; at most ``max_hypotheses`` per cut, and none
    within 0.05 rad of one already tried. The next cut is looked at only when the previous one
    gave nothing that was accepted, so what the first finds is solved as it always was; and
    only for the quads the previous cuts did not find. A quad found again, a pixel apart, is
    the same evidence: solved a second time, a panel whose features were too faint once may
    pass by chance at a wrong tilt (held-out random:113 at 2 m, high noise: 6 cm and 16° off).
    Returns (the accepted solution, "") or (None, why none was)."""
    coarse = coarse_gradients(image)
    failures: list[str] = []
    tried: list[Pose] = []
    seen: list[np.ndarray] = []
    any_quad = False
    for cut in CUTS:
        hypotheses, quads = pose_hypotheses(
            image, gradients, coarse, camera, target, support, turns, cut=cut
        )
        any_quad = any_quad or quads > 0
        new = [h for h in hypotheses if not any(_same_quad(h.quad.corners_uv, q) for q in seen)]
        seen += [h.quad.corners_uv for h in hypotheses]
        count = 0
        for hypothesis in new:
            if count >= max_hypotheses:
                break
            if any(rotation_error_geodesic(hypothesis.X_CT, X) < 0.05 for X in tried):
                continue
            tried.append(hypothesis.X_CT)
            count += 1
            solution = solve(hypothesis.X_CT)
            if not solution.reason:
                return solution, ""
            failures.append(solution.reason)
    if not tried and any_quad:
        # A faint panel's quad is cut from the smoothed image, and an edge of it is then not
        # found at full resolution (held-out random:111 at 3 m): not the same as no quad.
        return None, "panel-like quadrilateral(s) found, none with all four sides refined"
    if not tried:
        return None, "no panel-like quadrilateral in the image"
    return None, f"{len(tried)} hypotheses rejected: {failures[0]}"
