"""The line system: the panel's four edges → pose (FEDALPE: extract → detect/label → pose).

Extract: Canny edges on an image smoothed to its noise level (thresholds from the noise of its
gradient) and probabilistic Hough segments (OpenCV ``HoughLinesP``; J. Matas, C. Galambos and
J. Kittler, "Robust detection of lines using the progressive probabilistic Hough transform",
CVIU 78(1), 2000). With a prior only the neighbourhood of the predicted panel is searched.

Detect/label: the panel's four edges are projected with the prior; a segment is a candidate
for an edge when its direction is within the angle gate, its midpoint within the distance gate
(metres at the panel, converted to pixels) and within the edge's extent, and the image is
brighter on the panel's side of it (or darker, as the model says). The longest candidate and
those collinear with it define the edge's search line.

Refine: strips along the search line are fitted with a step edge on the raw pixels (sub-pixel
edge points with their variances), robust total least squares gives each edge's line, and
neighbouring lines intersect at the corners (``estimators.panel_edges``).

Pose: nonlinear least squares on the edge points' distances from the projected model edges
(or Lu–Hager–Mjolsness on the corners), from the prior and both IPPE poses of the corners; the
planar two-fold ambiguity is resolved by the residuals when they decide, else by the prior,
else by the reprojected model's support (``estimators.planar_pose``, ``model_support``).
Without a prior the panel is acquired from quadrilateral hypotheses (``estimators.acquisition``).

Only the panel's edges measure the pose, so its tilt is weakly determined (a 0.30 m square at
several metres); see docs/corners_lines.md for the bound this sets.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import cv2
import numpy as np

from estimators.acquisition import (
    FLIP_MARGIN,
    TurnCheck,
    TurnChecker,
    coarse_gradients,
    first_solved,
    flip_overturning_track,
    judge_flip,
    judge_turn,
    prior_tilt_fits_better,
    roll_free_measurement,
    rotation_beyond,
    search_tilt,
    turn_axis_circle,
    warn_if_roll_ambiguous,
)
from estimators.deadline import NO_TIME_FOR_SEARCH, search_allowed
from estimators.frame import CameraInfo, Frame
from estimators.geometry import Pose, rotation_error_geodesic
from estimators.imaging import (
    GradientImage,
    ImageStack,
    image_stack,
    smooth,
    smoothing_sigma_px,
)
from estimators.least_squares import median
from estimators.measurement import Measurement
from estimators.model_support import ModelSupport, Support
from estimators.model_view import outside_circles, plane_coordinates
from estimators.outline_edges import (
    OutlineEdges,
    fit_outline_edges,
    outline_edge_ends,
    outline_observations,
)
from estimators.panel_edges import (
    LAST_SIDE_REACH,
    LAST_SIDE_Z,
    EdgeStrips,
    PanelEdges,
    corner_sigma_px,
    find_last_side,
    fit_panel_edges,
    panel_edge_ends,
    shift_strips_onto,
    strips_from_pose,
)
from estimators.planar_pose import (
    MIN_SCALE2,
    POSE_METHODS,
    CorrelatedEdgeObservations,
    EdgeObservations,
    PointObservations,
    PoseChoice,
    PoseFit,
    choose_pose,
    fit_from_starts,
    ippe_poses,
    profile_widened,
    project_ideal,
    refine_pose,
)
from estimators.target import TargetModel

SYSTEM = "lines"


@dataclass(frozen=True, slots=True)
class LineOptions:
    """Tunable settings of the line system (defaults suit the reference study's set-up).

    ``angle_gate_deg`` / ``distance_gate_m``: how far a Hough segment may lie from a predicted
    edge in direction and (metres at the panel) in position; ``strip_px`` / ``band_px``: strip
    length along an edge and half width across it; ``min_contrast_snr``: how clearly an edge's
    two sides must differ; ``fourth_side_z``: the contrast (a z-score, the best of a scan) a
    panel side must show where the other three found sides bound it, ``fourth_side_reach`` how
    far (a fraction of its distance from the opposite side) it is scanned
    (``LineEstimator._fourth_side``);
    ``max_reduced_chi2``: the largest χ²/dof of the edge points' fit;
    ``min_edge_support``: mean z-score the reprojected panel edges (and the strongest other
    model contour in view) must reach, ``min_panel_edge_support`` the z-score each panel edge
    must (``Support.panel_unsupported``); ``turn_margin``: by how much (z units) the model's
    asymmetric parts must favour one quarter turn of the square panel (acquisition needs it; in
    tracking a clearly better turn means a wrong lock), ``confirm_margin`` when it confirms the
    turn the acquisition hypothesis already chose; ``pose_method``: ``gauss_newton`` or ``lhm``.
    """

    angle_gate_deg: float = 10.0
    distance_gate_m: float = 0.04
    strip_px: float = 6.0
    band_px: float = 3.0
    min_contrast_snr: float = 3.5
    fourth_side_z: float = LAST_SIDE_Z
    fourth_side_reach: float = LAST_SIDE_REACH
    max_reduced_chi2: float = 5.0
    min_edge_support: float = 3.0
    min_panel_edge_support: float = 2.5
    pose_method: str = "gauss_newton"
    max_hypotheses: int = 3
    turn_margin: float = 6.0
    confirm_margin: float = 3.0
    use_outline: bool = True
    max_outline_search_px: float = 20.0
    outline_strips: int = 20
    tilt_change_deg: float = 2.0
    edge_point_floor_px: float = 0.03
    edge_offset_sigma_px: float = 0.08
    edge_offset_noise_ratio: float = 0.1
    edge_turn_sigma_px: float = 0.05
    covariance_scale: float = 1.0

    def __post_init__(self) -> None:
        for name in (
            "edge_point_floor_px",
            "edge_offset_sigma_px",
            "edge_turn_sigma_px",
            "covariance_scale",
        ):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive; got {getattr(self, name)}")
        if self.pose_method not in POSE_METHODS:
            raise ValueError(
                f"pose_method must be one of {', '.join(POSE_METHODS)}; got {self.pose_method!r}"
            )
        if not 0.0 < self.angle_gate_deg < 45.0:
            raise ValueError(f"angle_gate_deg must be in (0, 45); got {self.angle_gate_deg}")


@dataclass(frozen=True, slots=True, eq=False)
class _Solution:
    X_CT: Pose
    covariance: np.ndarray
    rms_px: float
    ambiguous: bool
    segments: np.ndarray  # (S,4) Hough segments x1 y1 x2 y2
    edge_points: np.ndarray  # (M,2) image px
    corners_uv: np.ndarray  # (4,2) image px
    reason: str = ""
    roll_undecided: bool = False  # no part in view tells the panel's quarter turns apart
    from_prior: bool = False  # ... and the turn was kept from the prior
    unconfirmed: bool = False  # other parts in view, none supported: the prior stood in


#: A joint fit is taken as found when it used this share of the outline's strips in view.
_GOOD_OUTLINE_SHARE = 0.7


@dataclass(frozen=True, slots=True, eq=False)
class _Joint:
    """A joint fit of panel and outline: the pose choice and the edges it used."""

    choice: PoseChoice
    outline: OutlineEdges
    panel: PanelEdges  # the panel's edges the fit used (measured again if they disagreed)

    @property
    def points(self) -> int:
        return self.outline.points

    @property
    def good(self) -> bool:
        """Most of the outline in view was found and used."""
        return self.outline.points >= _GOOD_OUTLINE_SHARE * self.outline.expected


def _outline_turns(target: TargetModel, turns: tuple[Pose, ...]) -> list[int]:
    """The panel's quarter turns under which the face's outline lands differently (only 0
    for a square face centred on the panel's axis; 0 and 1 for a centred rectangle)."""
    outline = target.outline_corners_T
    if outline is None:
        return [0]
    distinct: list[int] = []
    seen: list[np.ndarray] = []
    for k, turn in enumerate(turns):
        moved = turn.apply(outline)
        if not any(
            np.max(np.min(np.linalg.norm(moved[:, None] - other[None], axis=2), axis=1)) < 0.01
            for other in seen
        ):
            distinct.append(k)
            seen.append(moved)
    return distinct


def _polarity(target: TargetModel) -> float:
    corners = [f for f in target.point_features if f.kind == "corner"]
    return 1.0 if (not corners or corners[0].brighter) else -1.0


class LineEstimator:
    """Pose of the mock-up from its panel's edges (see module docstring)."""

    system = SYSTEM

    def __init__(self, target: TargetModel, camera: CameraInfo, options: LineOptions):
        self.target = target
        self.camera = camera
        self.options = options
        self.support = ModelSupport(target, camera)
        self.polarity = _polarity(target)
        if camera.has_distortion:
            camera.undistorted_grid()  # (the pixel masks look it up: built now, not in a frame)
        self._z_panel = float(target.panel_corners_T[:, 2].mean())
        discs = [f for f in target.point_features if f.kind == "disc"]
        self._disc_xy = np.array([f.p_T[:2] for f in discs]).reshape(-1, 2)
        self._disc_r = np.array([f.diameter / 2 for f in discs])
        self._ring_inner = (
            target.circle("ring_inner").radius if target.has_circle("ring_inner") else math.inf
        )
        self.turns = TurnChecker(target, self.support)
        self.axis_circle = turn_axis_circle(target)
        warn_if_roll_ambiguous(SYSTEM, target, self.turns)
        self._outline_ends = outline_edge_ends(target) if options.use_outline else None
        self._outline_names = frozenset(n for n in self.support.names if n.startswith("outline_"))
        self._outline_turns = _outline_turns(target, self.turns.turns)
        self._panel_ends = panel_edge_ends(target)
        # Parts that may stand in front of the outline's edges (fasteners, circles and their
        # feet on the face): their images are masked out of the outline's edge fits.
        z_face = (
            float(target.outline_corners_T[:, 2].mean())
            if target.outline_corners_T is not None
            else self._z_panel
        )
        centres = [f.p_T for f in discs]
        radii = [f.diameter / 2 for f in discs]
        for circle in target.circles:
            centres += [circle.center_T, np.array([*circle.center_T[:2], z_face])]
            radii += [circle.radius, circle.radius]
        self._masked_T = np.array(centres).reshape(-1, 3)
        self._masked_radius = np.array(radii)

    # --- entry point ----------------------------------------------------------------------
    def estimate(self, frame: Frame, prior_X_CT: Pose | None = None) -> Measurement:
        started = time.perf_counter()
        image = image_stack(frame)
        if isinstance(image, str):
            return Measurement.lost(SYSTEM, frame, image, started=started)
        gradients = image.gradients(2.0)
        reasons = []
        segments = np.zeros((0, 4))
        if prior_X_CT is not None:
            solution = self._solve(image, gradients, prior_X_CT, tracking=True)
            if not solution.reason and not solution.unconfirmed:
                return self._measurement(frame, solution, "tracking", started)
            if not solution.reason:
                # The mock-up's other parts are in view and none is where the track puts
                # them: a prior that lost the tilt holds the panel's edges at it. A search
                # that finds them wins; without one the prior stands in, as it may.
                acquired = self._acquire(image, gradients) if search_allowed() else None
                if acquired is not None and not acquired.reason:
                    return self._measurement(frame, acquired, "acquired", started)
                return self._measurement(frame, solution, "tracking", started)
            segments = solution.segments
            reasons.append(f"tracking failed ({solution.reason})")
            if not search_allowed():
                return Measurement.lost(
                    SYSTEM, frame, f"{reasons[0]}; {NO_TIME_FOR_SEARCH}", started=started
                )
        solution = self._acquire(image, gradients)
        if not solution.reason:
            return self._measurement(frame, solution, "acquired", started)
        reasons.append(f"acquisition failed ({solution.reason})")
        features = {"extracted": segments.reshape(-1, 2)} if len(segments) else {}
        return Measurement.lost(
            SYSTEM, frame, "; ".join(reasons), started=started, features=features
        )

    def _measurement(self, frame: Frame, s: _Solution, status: str, started: float) -> Measurement:
        features = {
            "extracted": s.segments.reshape(-1, 2),
            "labeled": s.edge_points,
            "corners": s.corners_uv,
        }
        return roll_free_measurement(SYSTEM, frame, s, status, self.axis_circle, started, features)

    @staticmethod
    def _failure(reason: str, segments: np.ndarray | None = None) -> _Solution:
        empty = np.zeros((0, 2))
        return _Solution(
            Pose.identity(),
            np.eye(6),
            math.nan,
            False,
            np.zeros((0, 4)) if segments is None else segments,
            empty,
            empty,
            reason,
        )

    # --- acquisition ------------------------------------------------------------------------
    def _acquire(self, image: ImageStack, gradients: GradientImage) -> _Solution:
        solution, reason = first_solved(
            image,
            gradients,
            self.camera,
            self.target,
            self.support,
            self.turns,
            lambda X_CT: self._solve(image, gradients, X_CT, tracking=False),
            self.options.max_hypotheses,
        )
        return solution if solution is not None else self._failure(reason)

    # --- extraction and labeling ------------------------------------------------------------
    def _segments(self, image: ImageStack, corners_uv: np.ndarray, margin: float) -> np.ndarray:
        """Hough segments (S,4) near the predicted panel, in image pixels."""
        h, w = image.shape
        lo = np.maximum(np.floor(corners_uv.min(axis=0) - margin), 0).astype(int)
        hi = np.minimum(np.ceil(corners_uv.max(axis=0) + margin), [w - 1, h - 1]).astype(int)
        if np.any(hi - lo < 8):
            return np.zeros((0, 4))
        crop = image.pixels[lo[1] : hi[1] + 1, lo[0] : hi[0] + 1]
        smoothed = smooth(crop, max(1.0, smoothing_sigma_px(image.noise_sigma)))
        as_uint8 = np.clip(smoothed * 255.0, 0, 255).astype(np.uint8)
        gx = cv2.Sobel(as_uint8, cv2.CV_32F, 1, 0, ksize=3)
        gy = cv2.Sobel(as_uint8, cv2.CV_32F, 0, 1, ksize=3)
        magnitude = np.abs(gx) + np.abs(gy)
        # Edges are sparse: the median gradient is the noise's; Canny's hysteresis above it.
        reference = _integer_median(magnitude) + 1.0
        edges = cv2.Canny(as_uint8, 1.5 * reference, 3.0 * reference, L2gradient=False)
        lengths = np.linalg.norm(corners_uv - np.roll(corners_uv, -1, axis=0), axis=1)
        shortest = float(lengths.min())
        lines = cv2.HoughLinesP(
            edges,
            rho=1.0,
            theta=math.pi / 180.0,
            threshold=max(8, int(0.25 * shortest)),
            minLineLength=max(6.0, 0.3 * shortest),
            maxLineGap=max(3.0, 0.1 * shortest),
        )
        if lines is None:
            return np.zeros((0, 4))
        return lines.reshape(-1, 4).astype(float) + np.array([lo[0], lo[1], lo[0], lo[1]])

    def _label(
        self, segments: np.ndarray, corners_uv: np.ndarray, gradients: GradientImage, gate_px: float
    ) -> list[np.ndarray | None]:
        """Per model edge, the search line (point, direction) from its labeled segments, or
        None when no segment passes the gates."""
        centre = corners_uv.mean(axis=0)
        lines: list[np.ndarray | None] = []
        gate_angle = math.radians(self.options.angle_gate_deg)
        for i in range(4):
            a, b = corners_uv[i], corners_uv[(i + 1) % 4]
            length = float(np.linalg.norm(b - a))
            direction = (b - a) / max(length, 1e-9)
            normal = np.array([-direction[1], direction[0]])
            if normal @ (centre - a) < 0:
                normal = -normal  # toward the panel
            chosen = []
            for x1, y1, x2, y2 in segments:
                p, q = np.array([x1, y1]), np.array([x2, y2])
                seg = q - p
                seg_length = float(np.linalg.norm(seg))
                if seg_length < 1e-6:
                    continue
                angle = math.acos(min(1.0, abs(float(seg @ direction)) / seg_length))
                middle = 0.5 * (p + q)
                offset = float((middle - a) @ normal)
                along = float((middle - a) @ direction)
                if angle > gate_angle or abs(offset) > gate_px:
                    continue
                if not -0.1 * length <= along <= 1.1 * length:
                    continue
                # Polarity: brighter (or darker) on the panel's side of the segment.
                samples = p + np.linspace(0.2, 0.8, 5)[:, None] * seg
                strength = self.polarity * float(np.mean(gradients.directional(samples, normal)))
                if strength <= 0:
                    continue
                chosen.append((seg_length * strength, p, q))
            if not chosen:
                lines.append(None)
                continue
            # The segment with the most gradient along it: a shadow or a side band beside the
            # panel has an edge of the panel's polarity too, faint and as long or longer
            # (held-out random:117 at 3 m, noise-free, tracked from the truth: a band 6 px
            # wide beside the dark panel, a fifth of its contrast; taken for the panel's
            # edge as the longer segment, it gave a pose 33° and 0.49 m off).
            chosen.sort(key=lambda c: -c[0])
            _, p0, q0 = chosen[0]
            d0 = (q0 - p0) / np.linalg.norm(q0 - p0)
            n0 = np.array([-d0[1], d0[0]])
            points = [p0, q0]
            for _, p, q in chosen[1:]:
                if abs((p - p0) @ n0) < 1.5 and abs((q - p0) @ n0) < 1.5:
                    points += [p, q]
            points = np.array(points)
            middle = points.mean(axis=0)
            _, _, vt = np.linalg.svd(points - middle)
            lines.append(np.concatenate([middle, vt[0]]))
        return lines

    def _fourth_side(
        self, image: ImageStack, edges: PanelEdges, side: int, X0: Pose
    ) -> PanelEdges | None:
        """The panel's edges with its one missing ``side`` found where the other three bound
        it (``find_last_side``, scanned within ``fourth_side_reach`` of where ``X0`` puts it,
        at ``fourth_side_z``), or None.

        Without a prior only: a track that misses a side at the prior's place falls back to
        acquisition, which measures every side afresh. Scanned in tracking, the default
        mock-up's matrix kept 23 more tracks of 420, 0.93 → 1.21 mm off and less honest (NEES
        up to 33): there a side is missed where something of the other polarity stands beside
        it, not for being faint (docs/any_mockup_heldout.md)."""
        options = self.options
        guess = project_ideal(X0, self.target.panel_corners_T, self.camera.K)
        return find_last_side(
            image.pixels,
            edges,
            side,
            guess,
            self.camera,
            self.polarity,
            image.noise_sigma,
            clip_sigma=image.clip_sigma,
            keep=self._keep_mask(X0),
            strip_px=options.strip_px,
            half_width_px=options.band_px,
            min_z=options.fourth_side_z,
            reach=options.fourth_side_reach,
        )

    def _keep_mask(self, X_CT: Pose):
        """Pixels to use for edge fits: not on a disc (bolt head near the panel) and inside the
        ring's inner rim, judged on the panel plane under ``X_CT``."""
        depth = median(X_CT.apply(self.target.panel_corners_T)[:, 2])
        margin_m = 1.5 * depth / self.camera.K[0, 0]
        ring_limit = self._ring_inner - margin_m
        disc_xy, disc_r = self._disc_xy, self._disc_r

        clearance = disc_r + margin_m

        def keep(coords: np.ndarray) -> np.ndarray:
            xy = plane_coordinates(coords, X_CT, self.camera, self._z_panel)
            return outside_circles(xy, disc_xy, clearance, within=ring_limit)

        return keep

    # --- the pipeline from a pose guess -----------------------------------------------------
    def _solve(
        self,
        image: ImageStack,
        gradients: GradientImage,
        X0: Pose,
        *,
        tracking: bool,
        retry: bool = True,
        turn_retry: bool = True,
    ) -> _Solution:
        """Fit the panel's edges (and the outline's) from the pose guess ``X0`` (the prior when
        ``tracking``, an acquisition hypothesis otherwise). Without a prior, a flip that the
        whole model judges better is measured again from there once (``retry``), and so is a
        better quarter turn (``turn_retry``), also after a flip's: at the wrong quarter turn
        of a face that is not square the outline fits neither flip, and the flip is
        misjudged."""
        options = self.options
        strips = strips_from_pose(X0, self.camera, self.target, options.strip_px)
        if strips is None:
            return self._failure("the panel is not fully in view at the prior")
        corners_uv = self.camera.project(X0.apply(self.target.panel_corners_T))
        depth = median(X0.apply(self.target.panel_corners_T)[:, 2])
        gate_px = float(np.clip(options.distance_gate_m * self.camera.K[0, 0] / depth, 4.0, 40.0))
        segments = self._segments(image, corners_uv, gate_px + 6.0)
        labeled = self._label(segments, corners_uv, gradients, gate_px)
        search_strips: list[EdgeStrips] = []
        search = []
        for strip, line in zip(strips, labeled, strict=True):
            if line is None:
                search_strips.append(strip)
                search.append(min(gate_px, 3.0 * options.band_px))
            else:
                search_strips.append(shift_strips_onto(strip, line[:2], line[2:]))
                search.append(2.0)
        edges = fit_panel_edges(
            image.pixels,
            search_strips,
            self.camera,
            half_width_px=options.band_px,
            search_px=search,
            min_contrast_snr=options.min_contrast_snr,
            polarity=self.polarity,
            keep=self._keep_mask(X0),
            fallback=strips,  # a wrong segment must not hide an edge the prior predicts
            fallback_search_px=min(gate_px, 2.0 * options.band_px),
            # Without a prior, a wrong segment costs a wrong lock: every edge is also fitted
            # from the hypothesis itself (in tracking only a poorly covered one: time), whose
            # strips may be tilted against the edge.
            rough=not tracking,
            noise_sigma=image.clip_sigma,
        )
        missing = [i for i, e in enumerate(edges.edges) if not e.found]
        if len(missing) == 1 and not tracking:
            edges = self._fourth_side(image, edges, missing[0], X0) or edges
        if not edges.all_found:
            missing = [i for i, e in enumerate(edges.edges) if not e.found]
            return self._failure(f"panel edge(s) {missing} not found", segments)
        joint = self._with_outline(image, edges, X0, tracking)
        if joint is not None:
            choice, outline, edges = joint.choice, joint.outline, joint.panel
        else:
            panel = self._fit_pose(edges, X0, tracking)
            if panel is None:
                return self._failure("no pose fits the edges", segments)
            choice, outline = panel, None
        fit = choice.fit
        support = self.support.score(gradients, fit.X_CT)
        # The planar flip: decided by the residuals, or taken from the prior (a lock only if
        # the prior's was decided: the Tracker knows), or undecided.
        ambiguous = choice.decided_by == "lower_residual"
        from_prior = choice.decided_by == "prior"
        if not tracking and choice.ambiguous and choice.alternative is not None:
            # The residuals did not decide the planar flip: the ring, standing in front of the
            # panel, moves differently in the two poses — the whole model's support decides.
            other = self.support.score(gradients, choice.alternative.X_CT)
            if other.total > support.total:
                fit, support = choice.alternative, other
        X = fit.X_CT
        reason, confirmed_by_prior = self._unfit(fit.reduced_chi2, support), False
        if not reason:
            reason, confirmed_by_prior = support.confirmation(
                options.min_edge_support, tracking=tracking
            )
            if reason and not tracking and turn_retry:
                # A panel off the ring's axis taken at a wrong quarter turn puts the ring off
                # its edges too: the turns judge the hypothesis before the ring refuses it
                # (held-out random:101 at 0.5 m: a half turn off, the ring at z −1.3).
                turn, judged = self._check_turn(gradients, X, fit.covariance, outline is None)
                if judged == "other":
                    return self._solve_turned(image, gradients, X, turn)
        from_prior = from_prior or confirmed_by_prior
        unconfirmed = confirmed_by_prior and bool(support.others())
        if (
            not reason
            and tracking
            and prior_tilt_fits_better(self.support, gradients, X, X0, self.target, fit.covariance)
        ):
            reason = "the prior's tilt fits the ring and outline better than the pose's"
        if not reason and tracking:
            flipped = flip_overturning_track(
                self.support, gradients, X, self.target, fit.covariance
            )
            if flipped is not None:
                # Measured afresh from the flip, free of the prior that held the fit on this
                # side; where that fails the track stands, flagged: frame and prior disagree.
                other = self._solve(image, gradients, flipped, tracking=False, retry=False)
                if not other.reason:
                    return other
                ambiguous = True
        roll_undecided = False
        if not reason and not tracking:
            # Without the outline the panel's edges alone may favour the wrong flip (a small
            # or faint panel, an edge partly on clutter) even decisively: the whole model
            # judges the pose against its flip.
            flip, flipped = judge_flip(self.support, gradients, X, self.target, fit.covariance)
            if flip == "other" and retry:
                return self._solve(
                    image, gradients, flipped, tracking=False, retry=False, turn_retry=turn_retry
                )
            if flip != "kept":
                ambiguous = True
            elif flipped is not None and outline is not None and retry:
                verdict = self._measured_flip(
                    image, gradients, X, fit.covariance, flipped, turn_retry
                )
                if isinstance(verdict, _Solution):
                    return verdict
                ambiguous = ambiguous or verdict == "undecided"
        if not reason:
            # The square panel looks the same after a quarter turn: the model's asymmetric
            # parts (the thruster) decide — in tracking too, so that a wrong lock cannot last.
            rough = not tracking and outline is None  # (a pose from the panel's edges alone)
            turn, judged = self._check_turn(gradients, X, fit.covariance, rough)
            # The hypothesis came with its turn already chosen (on smoother gradients, from the
            # quad): confirming it needs less margin than overturning it. Undecided (nothing
            # asymmetric in view, or too faint): in tracking the turn is the prior's (a lock
            # only if the prior's was decided: the Tracker knows); without a prior the pose is
            # reported without its roll.
            if judged == "other":
                if tracking:
                    reason = "a quarter turn of the pose fits the image better"
                elif turn_retry:
                    # Measured again from the turned pose: a face that is not square, fitted
                    # at the wrong turn, does not fit at the right one.
                    return self._solve_turned(image, gradients, X, turn)
                else:
                    reason = "a quarter turn of the pose fits the image better"
            elif judged == "undecided":
                if tracking:
                    from_prior = True
                elif self.axis_circle is not None:
                    roll_undecided = True
                else:
                    reason = f"the panel's quarter turn is undecided (margin {turn.margin:.1f})"
        if not reason:
            # The covariance reported (the judges above test against the fit's own): widened
            # where the tilt lies in a flat, bent χ² valley that the covariance at the minimum
            # understates — the panel's edges alone, or a track from a prior far off that
            # holds the tilt near the prior (``profile_widened``).
            fit = profile_widened([self._observations(edges, outline)], fit, self.camera.K)
        corners_image = self.camera.project(X.apply(self.target.panel_corners_T))
        points = edges.image_points()
        if outline is not None:
            points = np.concatenate([points, outline.image_points()])
        return _Solution(
            X,
            options.covariance_scale * fit.covariance,
            fit.rms_px,
            ambiguous,
            segments,
            points,
            corners_image,
            reason,
            roll_undecided,
            from_prior,
            unconfirmed,
        )

    def _check_turn(
        self, gradients: GradientImage, X_CT: Pose, covariance: np.ndarray, rough: bool
    ) -> tuple[TurnCheck, str]:
        """The quarter turns of ``X_CT`` compared by the model's asymmetric parts, and the
        verdict (``judge_turn``). A rough pose (fitted without the outline or a prior: degrees
        off in tilt, which moves the parts far from the panel by pixels) lets them search as far
        as its ``covariance`` places them, at most 6 px; else a search only lets noise compete."""
        search = self.turns.search_px(X_CT, covariance, 6.0) if rough else 0.0
        turn = self.turns.check(gradients, X_CT, search_px=search)
        return turn, judge_turn(turn, self.options.turn_margin, self.options.confirm_margin)

    def _solve_turned(
        self, image: ImageStack, gradients: GradientImage, X_CT: Pose, turn: TurnCheck
    ) -> _Solution:
        """Measured again, without a prior, from the better quarter turn of ``X_CT``."""
        turned = X_CT @ self.turns.turns[turn.best]
        return self._solve(image, gradients, turned, tracking=False, retry=False, turn_retry=False)

    def _measured_flip(
        self,
        image: ImageStack,
        gradients: GradientImage,
        X_CT: Pose,
        covariance: np.ndarray,
        flipped: Pose,
        turn_retry: bool,
    ) -> _Solution | str:
        """The planar flip of an acquired pose fitted to the face's outline, measured as the
        pose was and weighed against it: the flip's solution where it is clearly better, else
        ``kept`` or ``undecided``. The whole model's judge compares the pose with its flip as
        predicted, but the outline, five times the panel's size, is where a tilt error shows
        most: the fitted pose lays it on the image and the unfitted flip leaves it pixels off,
        so the judge favours the fitted one whichever it is (held-out random:107 at 1.2 m with
        auto-exposure: a pose 14° off kept by 64 z units over its flip; the flip measured
        beat it by 113 and lay 0.02° from the truth)."""
        rival = self._solve(
            image, gradients, flipped, tracking=False, retry=False, turn_retry=turn_retry
        )
        # Measured from the flip, the fit may come back to the pose's own side: no rival then.
        if (
            rival.reason
            or not rotation_beyond(rival.X_CT, X_CT, covariance)
            or rotation_error_geodesic(rival.X_CT, flipped)
            >= rotation_error_geodesic(rival.X_CT, X_CT)
        ):
            return "kept"
        own = self.support.score(gradients, X_CT, shift_px=2.0).total
        other = self.support.score(gradients, rival.X_CT, shift_px=2.0).total
        if other - own >= FLIP_MARGIN:
            return rival
        return "kept" if own - other >= FLIP_MARGIN else "undecided"

    def _observations(
        self, edges: PanelEdges, outline: OutlineEdges | None = None
    ) -> CorrelatedEdgeObservations:
        """The panel's (and the outline's) edge points as one set of observations, with each
        edge's common error (``CorrelatedEdgeObservations``)."""
        panel = edges.observations(self.target)
        extra = outline_observations(self.target, outline) if outline is not None else None
        if extra is None:
            ends, index, uv, sigma = panel.ends_T, panel.edge, panel.uv, panel.sigma_px
        else:
            ends = np.concatenate([panel.ends_T, extra.ends_T])
            index = np.concatenate([panel.edge, extra.edge + len(panel.ends_T)])
            uv = np.concatenate([panel.uv, extra.uv])
            sigma = np.concatenate([panel.sigma_px, extra.sigma_px])
        options = self.options
        # A floor under each point's σ: the edge's fine shape departs from a straight step by a
        # few hundredths of a pixel (rendering, relief) even where the noise is nil.
        sigma = np.hypot(sigma, options.edge_point_floor_px)
        # Each edge's common offset: a part of its own (pixel quantisation) and a small part
        # that grows with the noise, in proportion to the edge's point σ (noise over contrast).
        # The noise part was 0.4 σ while clipped noise shifted steps toward the bright side
        # and the plate's side walls were not modelled; both are now (the clipped likelihood,
        # the side's width in the strips), and 0.1 σ keeps the NEES at its χ² interval
        # (tests/hil/evaluation/test_documented_accuracy.py).
        typical = np.full(len(ends), np.inf)
        for e in np.unique(index):
            typical[e] = median(sigma[index == e])
        offset = np.hypot(
            options.edge_offset_sigma_px,
            options.edge_offset_noise_ratio * np.where(np.isfinite(typical), typical, 0.0),
        )
        return CorrelatedEdgeObservations(
            EdgeObservations(ends, index, uv, sigma),
            offset,
            np.full(len(ends), options.edge_turn_sigma_px),
        )

    def _outline_keep(self, X_CT: Pose):
        """Pixels to use for outline edge fits: not on the image of a fastener or circle."""
        P = X_CT.apply(self._masked_T)
        in_front = P[:, 2] > 1e-6
        uv = self.camera.project(P[in_front])
        radius = self._masked_radius[in_front] * self.camera.K[0, 0] / P[in_front, 2] + 2.0

        def keep(coords: np.ndarray) -> np.ndarray:
            if not len(coords):
                return np.ones(0, bool)
            # Only the circles that reach the pixels' bounding box (column by column: a
            # reduction along the first axis of an (N, 2) array is an order of magnitude slower).
            u, v = coords[:, 0], coords[:, 1]
            lo, hi = np.array([u.min(), v.min()]), np.array([u.max(), v.max()])
            near = np.all((uv + radius[:, None] >= lo) & (uv - radius[:, None] <= hi), axis=1)
            return outside_circles(coords, uv[near], radius[near])

        return keep

    def _with_outline(
        self, image: ImageStack, edges: PanelEdges, X0: Pose, tracking: bool
    ) -> _Joint | None:
        """The pose from the panel's and the outline's edges together (None when the model has
        no outline or none of it is found).

        Where to look for the outline: the panel alone fixes the target's position and roll
        well but its tilt poorly (degrees at 3 m, sometimes tens at high noise), and the
        outline, five times larger, moves with the tilt. So it is predicted first with the
        tilt of ``X0`` (the prior; or an acquisition hypothesis, found from the outline itself
        when it was in view) and the panel's position and roll, searched within what the tilt
        may have changed since (``tilt_change_deg``) in tracking. When that finds less than
        most of the outline in view, the panel's own pose (all starts, as without an outline)
        predicts it, searched within its covariance, and the prediction that explains more of
        the outline wins. Without a prior every distinct quarter turn predicts it too, each
        again at the tilt the outline supports best when none found most of it
        (``_outline_tilt``), and the whole model's support at each joint pose decides."""
        if self._outline_ends is None:
            return None
        best: _Joint | None = None
        tried: list[np.ndarray] = []
        X_tilt = self._with_tilt_of(X0, edges)
        if X_tilt is not None and tracking:
            best = self._joint_fit(image, edges, X_tilt, self._tilt_change(X_tilt), [], X0)
            tried.append(self._outline_image(X_tilt))
            if best is not None and best.good:
                return best
        panel = self._fit_pose(edges, X0, tracking)
        if panel is None:
            return best
        fit = panel.fit
        # Without a prior the planar flip is a distinct start while it is undecided.
        flip = (
            [panel.alternative.X_CT]
            if panel.ambiguous and panel.alternative and not tracking
            else []
        )
        prior = X0 if tracking else None
        predictions = [fit.X_CT] + ([X_tilt] if X_tilt is not None and not tracking else [])
        if not tracking:
            # Which of the outline's edges is which depends on the panel's quarter turn, still
            # undecided here when the face is not square: each distinct turn predicts it (with
            # the panel's edges measured again under that turn's labels, or relabeled where a
            # faint one, found along its image line, is not found again narrowly), and the one
            # that explains more of the outline wins — a single edge fitted as the wrong one
            # drags the tilt by degrees.
            predictions = [(X, edges) for X in predictions]
            for k in self._outline_turns[1:]:
                turned = fit.X_CT @ self.turns.turns[k]
                relabeled = self._panel_edges_at(image, turned)
                predictions.append(
                    (turned, relabeled if relabeled is not None else edges.turned(k))
                )
        else:
            predictions = [(X, edges) for X in predictions]
        # In tracking the prior fixes the turn, and the joint fit that found more of the
        # outline wins. Without one, a wrong turn at a wrong tilt may line up as much of the
        # outline as the right turn (a panel off the face's centre, a face not square): the
        # whole model at each joint pose — the ring, which moves with the tilt alone — decides.
        gradients = image.gradients(2.0)
        best_score = -math.inf if best is None else float(best.points)  # tracking's X_tilt fit

        def consider(predictions: list[tuple[Pose, PanelEdges]]) -> None:
            nonlocal best, best_score
            for X_pred, panel_edges in predictions:
                corners = self._outline_image(X_pred)
                if any(np.max(np.abs(corners - c)) < 2.0 for c in tried):
                    continue
                tried.append(corners)
                starts = flip if panel_edges is edges else []
                joint = self._joint_fit(image, panel_edges, X_pred, fit.covariance, starts, prior)
                if joint is None:
                    continue
                score = (
                    float(joint.points)
                    if tracking
                    else self.support.score(gradients, joint.choice.fit.X_CT).total
                )
                if best is None or score > best_score:
                    best, best_score = joint, score
                if best.good and len(self._outline_turns) == 1:
                    return

        consider(predictions)
        if not tracking and (best is None or not best.good):
            # The panel's edges may leave the tilt 10° off: the outline at the right turn then
            # lies beyond its search, while the wrong turn, tilted further, lines one of its
            # edges up with one in the image. When no prediction found most of the outline,
            # each predicts it again at the tilt its edges support best.
            searched = [(self._outline_tilt(image, X, e), e) for X, e in predictions]
            consider([(X, e) for X, e in searched if X is not None])
        return best

    def _outline_tilt(self, image: ImageStack, X_CT: Pose, edges: PanelEdges) -> Pose | None:
        """The tilt at which the outline's edges find the most support on the coarse gradients
        (``search_tilt``), with the position and roll that fit the panel's ``edges`` there;
        None when ``X_CT`` puts none of the outline in view or no tilt explains it better."""
        found = search_tilt(
            self.support, coarse_gradients(image), X_CT, self.target, self._outline_names
        )
        return None if found.X_CT is None else self._with_tilt_of(found.X_CT, edges)

    def _tilt_change(self, X_CT: Pose) -> np.ndarray:
        """Covariance (6×6) of a prediction whose tilt may be ``tilt_change_deg`` off (per
        axis, about the two axes across the panel's normal); position and roll are measured."""
        normal = X_CT.R[:, 2]
        covariance = np.zeros((6, 6))
        covariance[:3, :3] = math.radians(self.options.tilt_change_deg) ** 2 * (
            np.eye(3) - np.outer(normal, normal)
        )
        return covariance

    def _outline_image(self, X_CT: Pose) -> np.ndarray:
        assert self.target.outline_corners_T is not None
        return project_ideal(X_CT, self.target.outline_corners_T, self.camera.K)

    def _with_tilt_of(self, X0: Pose, edges: PanelEdges) -> Pose | None:
        """``X0``'s tilt with the position and roll that fit the panel's edges (a pose for
        predicting the outline; None if the fit fails)."""
        normal = X0.R[:, 2]  # the panel's normal in C: rotations about it keep the tilt
        free = np.zeros((6, 4))
        free[:3, 0] = normal
        free[3:, 1:] = np.eye(3)
        try:
            return refine_pose(
                [edges.observations(self.target)], X0, self.camera.K, free=free, max_iterations=10
            ).X_CT
        except (ValueError, np.linalg.LinAlgError):
            return None

    def _joint_fit(
        self,
        image: ImageStack,
        edges: PanelEdges,
        X_pred: Pose,
        covariance: np.ndarray,
        other_starts: list[Pose],
        prior: Pose | None,
    ) -> _Joint | None:
        """Outline edges searched around ``X_pred`` (within 4σ of its ``covariance``), then
        the joint fit of panel and outline from ``X_pred`` (and ``other_starts``).

        An outline edge that disagrees with the rest (χ² per point, common error included,
        above ``max_reduced_chi2``) is something else: it is dropped and the pose refitted. A
        panel edge that disagrees was measured partly on something else (a fastener, the ring):
        the panel's edges are measured again, narrowly, around the joint pose — which the
        outline holds far better than the panel alone did. When the joint pose predicts the
        outline well away (3 px) from where ``X_pred`` did, or most of it was not found, the
        outline is fitted once more, narrowly, around the joint pose's prediction."""
        options = self.options
        starts = [X_pred, *other_starts]
        refreshed = remeasured = False
        while True:
            outline = fit_outline_edges(
                image.pixels,
                X_pred,
                covariance,
                self.camera,
                self.target,
                strip_px=options.strip_px,
                band_px=options.band_px,
                min_contrast_snr=options.min_contrast_snr,
                max_search_px=options.max_outline_search_px,
                max_strips=options.outline_strips,
                keep=self._outline_keep(X_pred),
                noise_sigma=image.clip_sigma,
            )
            joint = None
            while outline.found:
                observations = self._observations(edges, outline)
                fits = fit_from_starts([observations], starts, self.camera.K, min_scale2=MIN_SCALE2)
                if not fits:
                    return None
                joint = choose_pose(fits, prior)
                chi2 = self._edge_chi2(observations, joint.fit)
                panel_count = len(self._panel_ends)
                worst = max(range(panel_count, len(chi2)), key=lambda e: chi2[e])
                if chi2[worst] > options.max_reduced_chi2:
                    outline = outline.without(worst - panel_count)
                    joint = None
                    continue
                if not remeasured and max(chi2[:panel_count]) > options.max_reduced_chi2:
                    remeasured = True
                    again = self._panel_edges_at(image, joint.fit.X_CT)
                    if again is not None:
                        edges, starts = again, [joint.fit.X_CT]
                        continue
                break
            if joint is None:
                return None
            moved = np.max(
                np.abs(self._outline_image(joint.fit.X_CT) - self._outline_image(X_pred))
            )
            result = _Joint(joint, outline, edges)
            if refreshed or (moved < 3.0 and result.good):
                return result
            # Predict again from the joint pose, narrowly (its own covariance): strips that
            # missed the edge, or ran past its corners, are placed right.
            X_pred, covariance, refreshed = joint.fit.X_CT, joint.fit.covariance, True
            starts = [X_pred]

    def _panel_edges_at(self, image: ImageStack, X_CT: Pose) -> PanelEdges | None:
        """The panel's edges measured narrowly (±2 px) around their projection under a pose
        held by more than the panel (None when one is not found)."""
        strips = strips_from_pose(X_CT, self.camera, self.target, self.options.strip_px)
        if strips is None:
            return None
        edges = fit_panel_edges(
            image.pixels,
            strips,
            self.camera,
            half_width_px=self.options.band_px,
            search_px=2.0,
            min_contrast_snr=self.options.min_contrast_snr,
            polarity=self.polarity,
            keep=self._keep_mask(X_CT),
            noise_sigma=image.clip_sigma,
        )
        return edges if edges.all_found else None

    def _edge_chi2(self, observations: CorrelatedEdgeObservations, fit: PoseFit) -> np.ndarray:
        """χ² per point of every model edge's points at ``fit`` (their common error included;
        0 for an edge without points): panel edges first, then the outline's."""
        _, r_w, _ = observations.edges.linearize(fit.X_CT, self.camera.K)
        whitened = observations.whiten(r_w)
        count = len(r_w)
        chi2 = np.zeros(len(observations.edges.ends_T))
        for k, index in enumerate(observations.group_points):
            edge = int(observations.edges.edge[index[0]])
            total = float(whitened[index] @ whitened[index])
            total += float(np.sum(whitened[count + 2 * k : count + 2 * k + 2] ** 2))
            chi2[edge] = total / len(index)
        return chi2

    def _fit_pose(self, edges: PanelEdges, X0: Pose, tracking: bool) -> PoseChoice | None:
        observations = self._observations(edges)
        K = self.camera.K
        starts = [X0] + ippe_poses(self.target.panel_corners_T, edges.corners_ideal, K)
        lhm_points = None
        if self.options.pose_method == "lhm":
            sigma = corner_sigma_px(edges)
            covariance = np.tile(np.eye(2) * max(sigma, 0.05) ** 2, (4, 1, 1))
            lhm_points = PointObservations(
                self.target.panel_corners_T, edges.corners_ideal, covariance
            )
        fits = fit_from_starts(
            [observations],
            starts,
            K,
            method=self.options.pose_method,
            lhm_points=lhm_points,  # type: ignore[arg-type]
            min_scale2=MIN_SCALE2,
        )
        if not fits:
            return None
        return choose_pose(fits, X0 if tracking else None)

    def _unfit(self, reduced_chi2: float, support: Support) -> str:
        """Why the fit is not a pose of the panel ('' if it is): its edge points disagree, or
        the reprojected panel does not stand out of the noise. (Whether the mock-up's other
        parts confirm it is ``Support.confirmation``'s to say.)"""
        options = self.options
        if reduced_chi2 > options.max_reduced_chi2:
            return f"edge points disagree with the model (χ²/dof {reduced_chi2:.1f})"
        return support.panel_unsupported(options.min_edge_support, options.min_panel_edge_support)


def _integer_median(values: np.ndarray) -> float:
    """``np.median`` of non-negative integer values (an 8-bit image's Sobel magnitudes, held as
    floats) from their histogram: linear in the pixel count, where sorting a close-up crop's
    hundred thousand values took a millisecond."""
    counts = np.bincount(values.astype(np.int64).ravel())
    cumulative = np.cumsum(counts)
    n = int(cumulative[-1])
    lower = int(np.searchsorted(cumulative, (n - 1) // 2, side="right"))
    upper = int(np.searchsorted(cumulative, n // 2, side="right"))
    return 0.5 * (lower + upper)


def build(target: TargetModel, camera: CameraInfo, **options) -> LineEstimator:
    """The registry's factory: options are ``LineOptions`` fields."""
    return LineEstimator(target, camera, LineOptions(**options))
