"""The ellipse estimator: the marman ring's circle pose (5-DOF) and, with the thruster, 6-DOF.

Pipeline (FEDALPE: extract → detect/label → pose), see DESIGN.md:

* **Tracking** (a prior ``X_CT`` is given): the model's circles — the ring's two edges and the
  thruster's — are projected with the prior and their edges searched along the normals, first
  smoothed more in a window sized to the image (coarse), then in a narrow window (fine): the
  predicted ellipses verified by their edge support, a region-of-interest search. Should the
  ring not verify, the arc-based extractor runs in a region around the prediction and its
  ellipses are labeled against the predicted ones (``ellipse_detection.label_with_prior``).
* **Acquisition** (no prior, or tracking failed): the extractor runs on the whole frame; the
  ring is hypothesised from concentric pairs of ellipses of opposite polarity in the ratio of
  its radii (then lone ellipses); each hypothesis gives two closed-form circle poses
  (``circle_pose``), refined and verified by the support of both ring edges. The thruster is
  then found by a 1-D search over the roll about the ring's axis
  (``ellipse_detection.search_roll``).
* **Pose**: robust least squares of the sub-pixel edge points' distances to the projected
  circles (``circle_fit``): 5-DOF from the ring's coaxial edges, 6-DOF ``X_CT`` when the
  thruster is found.
* **Ring holes**: once the roll is known (6-DOF), the small holes on the ring's face are
  labeled by projection and fitted as discs on the raw pixels (``point_fit.fit_discs``, as the
  corner system does), and join the edges in one last 6-DOF fit. Near a head-on view the
  edges fix one tilt axis only weakly (a circle's tilt shows in its outline to second order);
  a labeled point moves to first order with it, so a handful of holes cuts that axis's error
  several-fold at 2–3 m (``hil.evaluation.circle_bounds``).
* **Ambiguity**: one circle has two poses. A prior picks the one nearer its normal; without a
  prior the thruster (found for only one of them) or the lower cost decides, and when nothing
  decides the measurement says ``ambiguous``.

Bad frames (wrong size, blank, no ring) come back ``lost`` with a reason, never an exception.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from estimators.circle_edges import (
    CircleEdges,
    camera_field_radius,
    find_circle_edges,
    sample_projected_circle,
    visible_pixels,
)
from estimators.circle_fit import (
    EdgeSet,
    FitResult,
    covariance_at,
    fit_circle_pose,
    fit_target_pose,
    moved,
    pose_response,
    stacked_displacements,
)
from estimators.circle_pose import CirclePose, circle_poses_from_conic
from estimators.conics import (
    circle_cone,
    circle_image_conic,
    circle_points,
    fit_ellipse_direct,
    sampson_distances,
)
from estimators.corners import FeatureLayout
from estimators.deadline import NO_TIME_FOR_SEARCH, search_allowed
from estimators.ellipse_detection import (
    pose_with_roll,
    projected_ellipse,
    ring_hypotheses,
    roll_of,
    search_roll,
)
from estimators.ellipse_extraction import ExtractedEllipse, ExtractorSettings, extract_ellipses
from estimators.frame import CameraInfo, Frame
from estimators.geometry import Pose, normal_angle, rotation_between
from estimators.imaging import GradientField, ImageStack, image_stack
from estimators.measurement import (
    Measurement,
    circle_covariance_from_pose,
    normal_sigma,
    normals_apart,
)
from estimators.model_view import head_extrusion, local_affine
from estimators.planar_pose import PointObservations, ideal_pixels
from estimators.point_fit import fit_discs
from estimators.target import Circle3D, TargetModel

SYSTEM = "ellipses"
#: Roll search: the best roll's mean edge SNR per sample (each clipped at 8) must reach this,
#: and stand this many times above the median over all rolls (a real circle, not clutter).
_ROLL_SCORE_MIN = 3.0
_ROLL_DISTINCTNESS = 4.0
#: The ring's two poses refitted with its holes: a truncated-χ² difference this large (≈ 5σ)
#: decides between them.
_HOLES_DECIDE_CHI2 = 25.0
#: Two poses of the ring (its mirror, or fits from two starts) judged on the same edge points:
#: the image decides between them when the worse one's truncated χ² is this much higher.
_POSES_DECIDE_CHI2 = 25.0
#: ... and each fit's own cost (over the points it found) must be this much lower for the same.
_POSES_DECIDE_COST_RATIO = 1.15
#: Where the image does not decide, a prior picks the ring's pose whose normal it is nearer
#: only when it lies clearly on that pose's side: at most this fraction of its angle to the
#: other. The two poses lie symmetric about the line of sight, so a prior about midway — the
#: ring turned by about its own tilt since, or a prior as uncertain as the poses are apart —
#: is nearly as near the wrong pose as the right one.
_PRIOR_DECIDES_RATIO = 0.5
#: A stage needs the ring's outer edge found at this many samples (``_enough_of_outer``).
_MIN_OUTER_EDGES = 12
#: An edge found at fewer samples than this is left out of a fit.
_MIN_EDGES = 8
#: A track's fine stage is abandoned when its outer edge lies beyond the window its caller
#: accepts by this much (px): the error of ``_edge_shift_px``'s fit at a track's noise, a tenth
#: of it.
_SHIFT_MARGIN_PX = 0.25
#: A fit whose ring's outer edge lies off its fitted image along a smooth curve by more than
#: this (px; ``_outer_misfit_px``) is the pose of something else.
_MAX_OUTER_MISFIT_PX = 1.0
#: The bore's rim/foot split redone at the fitted pose at most this many times (it settles in
#: one or two: each refit moves the pose by a fraction of the foot's distance from the rim).
_MAX_RESPLITS = 3
#: The fixed point that finds the outer wall's band where the fit would have landed without
#: it (``_outer_wall_covariance``): at most this many steps, until a step changes the shift
#: by less than this fraction of it (each step shrinks the change by about 0.6).
_WALL_STEPS = 30
_WALL_TOLERANCE = 0.02


@dataclass(frozen=True, slots=True)
class EllipseSettings:
    """Tuning of the ellipse estimator (pixels at full resolution)."""

    extractor: ExtractorSettings = field(default_factory=ExtractorSettings)
    coarse_sigma_px: float = 2.0
    #: SNR an edge sample must reach (its gradient over the noise the pixels show).
    min_edge_snr: float = 3.0
    #: Smoothing scales tried in turn (every stage's σ times each) until the ring is found.
    smoothing_scales: tuple[float, ...] = (1.0, 2.0)
    #: Smoothing of the final edge search: this at low noise, growing with the noise (σ_n × 5)
    #: up to ``fine_sigma_max_px`` so that edges stay well above the noise.
    fine_sigma_px: float = 1.0
    fine_sigma_max_px: float = 1.6
    sample_spacing_px: float = 2.0
    #: At most this many samples around a circle (large rings at close range are sampled
    #: more sparsely: plenty for sub-0.1° there, and the cost stays bounded).
    max_samples_per_circle: int = 320
    fine_half_width_px: float = 3.0
    #: A 6-DOF track held within the fine window whose ring turned more than this (°) from its
    #: prior was not held by the prior: it is weighed against the ring's other pose as a track
    #: beyond the window is (``_against_mirror``) — far above a loop's frame-to-frame motion
    #: and the bench's 1° prior (the corner system's ``judge_tilt_beyond_deg``).
    judge_mirror_beyond_deg: float = 5.0
    min_outer_support: float = 0.35
    min_inner_support: float = 0.25
    min_thruster_support: float = 0.45
    #: The bore's foot stands in for an unseen rim only when found over this much of its
    #: length: a deep bore holds several circular edges, and a pose 4 cm off found half of a
    #: foot (``rendered.DEEP_BORE_MOCKUP`` at 0.6 m), where a rim without contrast leaves the
    #: foot found all round (random:101: 0.98).
    min_bore_foot_support: float = 0.7
    max_hypotheses: int = 6
    #: Of the ring hypotheses that verify, a later one replaces the one kept only when its
    #: ring's edges are found over this much more of their lengths (mean support of the outer
    #: and inner edge); a ring found over ``full_ring_support`` ends the search.
    support_margin: float = 0.1
    full_ring_support: float = 0.9
    #: Operating range of the ring's centre (m): a ring "found" beyond it is a smaller look-alike
    #: (the thruster's lip is a bright annulus too) and is rejected.
    min_range_m: float = 0.2
    max_range_m: float = 5.0
    #: Scale on the covariances, measured against ground truth: with the model-based terms
    #: alone (edge noise, sample correlation, head-on linearisation) the mean NEES over the
    #: matrix's frames was 1.1–1.7× its degrees of freedom (small biases of the rendered edges
    #: — pixel quantisation, the thin lip, the wall — that no noise model holds). See
    #: docs/ellipses.md, "Covariance".
    covariance_scale: float = 1.5
    #: The inner edge joins the fit (free radius) when its image lies this far inside the outer
    #: one: closer, the unresolved inner wall biases it (the wall's shading is unknown).
    inner_edge_min_gap_px: float = 15.0
    #: Use the holes on the ring's face (the model's disc features there) in the 6-DOF fit:
    #: at least ``min_holes`` fits, each with contrast SNR ≥ ``min_hole_snr`` and at least
    #: ``min_hole_radius_px`` in radius.
    ring_holes: bool = True
    min_holes: int = 3
    min_hole_snr: float = 4.0
    min_hole_radius_px: float = 1.0
    #: With a prior, a frame is not searched when the prior shows less than this much of the
    #: ring's outer edge in view (px of arc): too little to fit, and a search of the whole frame
    #: (120–220 ms) finds nothing either — as when the camera closes in past the ring.
    min_outer_edge_in_view_px: float = 60.0


@dataclass(frozen=True, slots=True, eq=False)
class _Image:
    """The frame's image stack as the stages see it at one smoothing scale."""

    stack: ImageStack
    camera: CameraInfo
    fine_sigma: float
    scale: float = 1.0  # smoothing of every stage, relative to the settings' (low contrast: > 1)
    # Whether the bore's foot may stand in for an unseen rim (``_bore_edges``): in acquisition
    # only. A track from a prior far off finds the true rim where it predicts the foot.
    foot_for_rim: bool = False
    # Samples of a projected circle by (pose, circle, spacing, margin): the ring's polarity
    # probes and the search after them sample the same curve up to three times a stage.
    samples: dict = field(default_factory=dict, repr=False)

    @property
    def gray(self) -> np.ndarray:
        return self.stack.pixels

    @property
    def noise(self) -> float:
        """The noise σ the pixels show."""
        return self.stack.noise_sigma

    @property
    def clip_sigma(self) -> float:
        """The noise σ before the sensor clipped it."""
        return self.stack.clip_sigma

    def field(self, sigma_px: float, roi=None) -> GradientField:
        """The smoothed gradient at ``sigma_px`` over ``roi`` (x0, y0, x1, y1) or the frame."""
        return self.stack.gradient_field(sigma_px, roi)


@dataclass(frozen=True, slots=True, eq=False)
class _Fit:
    """A refined pose: 5-DOF (``ring``) or 6-DOF (``X_CT`` too), the least-squares result, the
    edges found per circle, and a cost that compares candidates on the same footing."""

    ring: CirclePose
    X_CT: Pose | None
    result: FitResult
    edges: dict[str, CircleEdges]
    cost: float
    sigma_px: float  # smoothing of the final edge search
    spacing_px: float  # spacing of the reference circle's edge samples
    holes: PointObservations | None = None  # ring holes in the fit, if any
    sets: tuple[EdgeSet, ...] = ()  # the edge sets of the fit (``result`` is in their order)
    roll_known: bool = (
        True  # X_CT's roll is measured (False: the holes' pattern's, up to its symmetry)
    )
    #: Its edges passed the support checks. An unverified fit — the ring's other pose, whose
    #: edges were found too sparsely to verify it — can leave a choice undecided (``_better_of``)
    #: but never wins one: failing a support threshold is not evidence that a pose is wrong.
    verified: bool = True
    #: Whether the ring's holes, once fitted (``_with_holes``), decided between the ring's two
    #: poses — nothing is then left for the other pose to settle; None before they are fitted.
    holes_decided: bool | None = None

    @property
    def polarities(self) -> dict[str, int]:
        return {name: e.polarity for name, e in self.edges.items()}


class EllipseEstimator:
    """Ring (and thruster) pose from ellipses; see the module docstring."""

    system = SYSTEM

    def __init__(
        self, target: TargetModel, camera: CameraInfo, settings: EllipseSettings | None = None
    ):
        if not target.has_circle("ring_outer"):
            raise ValueError(f"target {target.name!r} has no 'ring_outer' circle to track")
        self.target = target
        self.camera = camera
        self.settings = settings or EllipseSettings()
        self.outer = target.circle("ring_outer")
        self.inner = target.circle("ring_inner") if target.has_circle("ring_inner") else None
        if self.inner is not None and not _coaxial(self.inner, self.outer):
            raise ValueError("target circle 'ring_inner' must be coaxial with 'ring_outer'")
        self.off_axis = tuple(c for c in target.circles if not _coaxial(c, self.outer))
        self.foot = target.ring_foot
        self.outer_foot = target.ring_outer_foot
        self._bore_depth_m = target.bore_depth_m
        # The outer edge's polarity when the model knows which side is brighter (an edge
        # search's polarity is −1 where the image darkens outward): a light that darkens or
        # lights the ring's surroundings unevenly must not make the image choose it.
        self._outer_polarity = (
            None if target.ring_brighter is None else (-1 if target.ring_brighter else 1)
        )
        self._circles = {c.name: c for c in (*target.circles, self.foot) if c is not None}
        self.holes = ring_hole_layout(target, self.outer, self.inner)
        self._holes_symmetric = _rotationally_symmetric(self.holes, self.outer)
        self._K_inv = np.linalg.inv(camera.K)
        self._field_radius = camera_field_radius(camera)  # a property of the camera

    # --- entry point ----------------------------------------------------------------------
    def estimate(self, frame: Frame, prior_X_CT: Pose | None = None) -> Measurement:
        started = time.perf_counter()
        # estimators.registry builds one estimator per CameraInfo: another camera here is a bug.
        assert frame.info.key == self.camera.key, "frame intrinsics differ from the estimator's"
        stack = image_stack(frame)
        if isinstance(stack, str):
            return Measurement.lost(SYSTEM, frame, stack, started=started)
        s = self.settings
        if prior_X_CT is not None:
            in_view_px = self._outer_edge_in_view_px(prior_X_CT)
            if in_view_px < s.min_outer_edge_in_view_px:
                reason = f"the ring's outer edge is out of view at the prior ({in_view_px:.0f} px)"
                return Measurement.lost(SYSTEM, frame, reason, started=started)
        fine_sigma = float(np.clip(5.0 * stack.noise_sigma, s.fine_sigma_px, s.fine_sigma_max_px))
        # The smoothing suits a ring of the usual contrast (≈ 0.4 at this noise). A ring that
        # shows far less — a low sun from the side leaves 0.15 — has its edges below the
        # search's SNR sample by sample: every stage is tried again smoothed more (an edge's
        # SNR grows with the smoothing).
        for scale in s.smoothing_scales:
            image = _Image(stack, self.camera, fine_sigma * scale, scale=scale)
            found = self._track(image, prior_X_CT) if prior_X_CT is not None else None
            status = "tracking"
            extracted: list[ExtractedEllipse] = []
            if found is None and prior_X_CT is not None and not search_allowed():
                reason = f"tracking failed; {NO_TIME_FOR_SEARCH}"
                return Measurement.lost(SYSTEM, frame, reason, started=started)
            if found is None:
                status = "acquired"
                image = replace(image, foot_for_rim=True)
                extractor = s.extractor
                if scale != 1.0:
                    extractor = replace(
                        extractor,
                        sigma_px=extractor.sigma_px * scale,
                        fine_sigma_px=extractor.fine_sigma_px * scale,
                    )
                extracted = extract_ellipses(
                    stack.pixels,
                    stack.noise_sigma,
                    settings=extractor,
                    field=image.field(image.fine_sigma),
                    reduced=stack.reduced(2**extractor.level),
                )
                found = self._acquire(image, extracted)
            if found is not None:
                break
        if found is None:
            reason = (
                f"no ring among {len(extracted)} extracted ellipses"
                if extracted
                else "no ellipse extracted"
            )
            return Measurement.lost(SYSTEM, frame, reason, started=started)
        fit, ambiguous, from_prior = found
        fit, decided = self._with_holes(image, fit)
        if fit.X_CT is None and self.inner is not None:
            # The ring alone — no thruster, no holes to label: near head-on its outer edge holds
            # its tilt only to second order, and the one first-order measure left is the
            # perspective offset between its two concentric edges (issue 13, point 6). At long
            # range the inner edge is otherwise left out (the bore's wall, unresolved, may bias
            # it), but without it the normal is several times worse (random mock-ups at 3 m:
            # median 4° → 1.4°).
            with_inner = self._refine_ring(image, fit.ring, fit.polarities, inner_always=True)
            if with_inner is not None:
                fit = with_inner
        ambiguous = ambiguous and not decided
        from_prior = from_prior and not decided
        alternative = self._mirror_pose(fit) if ambiguous or from_prior else None
        if alternative is None:  # the two poses are one (near head-on): nothing to choose
            ambiguous = from_prior = False
        return self._measurement(
            frame, status, fit, (ambiguous, from_prior, alternative), prior_X_CT, extracted, started
        )

    # --- tracking -------------------------------------------------------------------------
    def _track(self, image: _Image, prior: Pose):
        """Refine from the prior (ring and thruster together); fall back to the ring alone and
        a roll search, then to an extraction around the predicted ring."""
        ring0 = CirclePose(prior.apply(self.outer.center_T), prior.R @ self.outer.normal_T)
        predicted = projected_ellipse(
            ring0.center_C, ring0.normal_C, self.outer.radius, self.camera
        )
        if predicted is None:
            return None
        width = float(np.clip(0.1 * predicted.a + 4.0, 6.0, 30.0))
        fit = None
        off_axis = self._visible_off_axis(prior)
        if off_axis:
            # Small motion since the prior (the usual case): one fine stage settles it; a
            # larger one fails its verification and gets the coarse-to-fine search.
            fit = self._refine_full(
                image, prior, off_axis, None, None,
                abandon_beyond_px=self.settings.fine_half_width_px + _SHIFT_MARGIN_PX,
            )  # fmt: skip
            if (
                fit is not None
                and self._moved_px(prior, fit.X_CT) > self.settings.fine_half_width_px
            ):
                # The ring moved nearly as far as the window reaches: edges may have been
                # beyond it (a neighbour taken instead); search coarse-to-fine.
                fit = None
            if fit is not None and normal_angle(fit.ring.normal_C, ring0.normal_C) > np.radians(
                self.settings.judge_mirror_beyond_deg
            ):
                # Held within the window, yet turned far from the prior: a turn across the line
                # of sight about the ring's own centre leaves the ring's image in place, and the
                # fit may have stopped short of the other side (held-out random:116 at 3 m, the
                # matrix's 17° turn: 12° off as decided).
                return self._against_mirror(image, fit, fit, prior, width)
            if fit is None:
                fit = self._refine_full(image, prior, off_axis, None, width)
                if fit is not None:
                    # Moved beyond the fine window since the prior: a prior that far off may
                    # have led the fit to the ring's other pose.
                    return self._against_mirror(image, fit, fit, prior, width)
        if fit is None:
            # The ring alone, as the full pose above: one fine stage first. Close up, where
            # only arcs at the image's corners are left in view, the coarse stage's window
            # reaches outside the image and finds too little.
            fine_width = self.settings.fine_half_width_px + 1.0
            ring = self._refine_ring(
                image, ring0, None, abandon_beyond_px=fine_width + _SHIFT_MARGIN_PX
            )
            if ring is not None and self._ring_moved_px(ring0, ring.ring) > fine_width:
                ring = None
            held = ring is not None  # found within the fine window of the prior
            if ring is None:
                ring = self._refine_ring(image, ring0, None, coarse_half_width=width)
            if ring is None or off_axis or self._ring_moved_px(ring0, ring.ring) > width:
                # No ring, or the ring and thruster that should be there did not verify, or the
                # ring moved beyond the window: edges of something else may have been taken.
                # The extraction around the prediction does not depend on the window.
                extracted = self._track_by_extraction(image, ring0, predicted)
                if ring is None or (extracted is not None and extracted.cost < ring.cost):
                    ring, held = extracted, False
            if ring is None:
                return None
            fit = self._find_thruster(image, ring, prior)
            if fit is None:
                return self._choose_mirror(image, ring, prior, held=held)
            # The ring alone settled on the pose nearer the prior; a prior far off (a turn
            # since) may have chosen its mirror, and the thruster is found there too.
            return self._against_mirror(image, ring, fit, prior, width)
        return fit, False, False

    def _against_mirror(self, image: _Image, ring: _Fit, full: _Fit, prior: Pose, width: float):
        """A track's 6-DOF fit ``full``, not found within the fine window of its prior (or
        its thruster out of view there, or turned far from the prior within it), weighed against
        the ring's other pose (``ring``: the ring's fit it came from, or ``full`` itself): the
        image decides between the two fits, or the answer — the pose nearer the prior — says it
        is ambiguous. Returns (fit, ambiguous, from_prior).

        Near head-on the ring's two poses lie on either side of the line of sight, and a prior
        on the wrong side — the target turned since — leads the fit to the wrong one, where
        the thruster is found too, at some roll: a local minimum of the 6-DOF fit, reported as
        decided (held-out random mock-ups, a 17° turn between frames: 15° off at NEES up to
        5740). The other pose is fitted as acquisition fits it (``_other_full``), coarse to
        fine in ``width`` — unless the ring's holes decide first (``_with_holes``: the joint
        fit of edges and holes started at both poses), as they would after it, in a fraction of
        its time (the bench at 1.2 m: about 5 ms against 15–25 ms). The holes' decision depends
        on the side they are fitted from (in acquisition they decided for the wrong pose they
        were fitted from, random:105 at 2 m, which is why acquisition fits the other pose
        first); for a track it changed 2 of the held-out matrix's 3840 answers, no wrong lock."""
        holed, decided = self._with_holes(image, full)
        if decided:
            return holed, False, False
        mirror_pose = self._mirror_pose(ring)
        other = (
            None
            if mirror_pose is None
            else self._other_full(image, ring, full, mirror_pose, width, near_roll=True)
        )
        if other is None:
            return holed, False, False
        best, decided = self._better_of(full, other)
        if decided:
            return (holed if best is full else best), False, False
        # The prior did not predict ring and thruster within the fine window (and the ring's
        # image is the same at both poses): which side of the line of sight the ring turned to
        # is not the prior's to say.
        nearer, _, _ = self._by_prior(full, other, prior)
        return (holed if nearer is full else nearer), True, False

    def _other_full(
        self,
        image: _Image,
        ring: _Fit,
        full: _Fit,
        mirror_pose: CirclePose,
        coarse_half_width: float | None,
        *,
        near_roll: bool = False,
    ) -> _Fit | None:
        """The 6-DOF fit at the ring's other pose ``mirror_pose``, given the fit ``full`` of
        the thruster found on ``ring``'s: started from the other normal with the roll the
        thruster fixed (coarse to fine in ``coarse_half_width`` when given, else one fine
        stage), or, where that roll does not suit it (its thruster then lies elsewhere), with
        the thruster searched round the other ring — within 12° of that roll only when
        ``near_roll`` (a track: the thruster's image is where ``full`` found it, so the other
        pose holds it near the roll carried over — 0.9° and 3.6° from it on the two held-out
        frames that needed this search — and a whole turn is 10–20 ms at 1.2 m). Failing
        those, the fit started from the other normal whose thruster did not verify
        (``verified`` False: a faint thruster a pixel or two from where ``full`` found it is
        not found "missing" at the other pose — random:112 at 2 m, 17° turned since the prior:
        support 0.36 at the true pose, and the wrong one was taken as decided, NEES 2750).
        None when there is none, or it converges back to ``full``'s normal (the thruster pulls
        it: no ambiguity)."""
        X0 = pose_with_roll(mirror_pose, self.outer, roll_of(full.X_CT, mirror_pose, self.outer))
        other = self._refine_full(
            image,
            X0,
            self._visible_off_axis(X0),
            full.polarities,
            coarse_half_width,
            verify=False,
        )
        if other is None or not other.verified:
            mirror = self._mirror(image, ring, mirror_pose)
            if mirror is not None and mirror.verified:
                near = full.X_CT if near_roll else None
                other = self._find_thruster(image, mirror, near, whole_turn=not near_roll) or other
        if other is None or self._same_normal(full, other):
            return None
        return other

    def _by_prior(self, a: _Fit, b: _Fit, prior: Pose):
        """Of two poses the image does not decide between, the one whose normal is nearer the
        prior's: kept because of the prior where the prior lies clearly on its side
        (``_PRIOR_DECIDES_RATIO``), else ambiguous. Returns (fit, ambiguous, from_prior)."""
        prior_normal = prior.R @ self.outer.normal_T
        (near, nearer), (far, _) = sorted(
            ((normal_angle(f.ring.normal_C, prior_normal), f) for f in (a, b)),
            key=lambda pair: pair[0],
        )
        if not nearer.verified:  # the prior does not pick a pose the image did not verify
            return (b if nearer is a else a), True, False
        if near > _PRIOR_DECIDES_RATIO * far:
            return nearer, True, False
        return nearer, False, True

    def _choose_mirror(self, image: _Image, fit: _Fit, prior: Pose, *, held: bool):
        """The ring alone while tracking: its two poses, and which the frame supports. The
        image decides when the other pose does not fit it (or is the same pose, near head-on),
        shows the thruster, or costs clearly more (15 %); otherwise, where the ring ``held``
        within the fine window of its prior, the pose nearer the prior's normal is kept
        *because of the prior* (``from_prior``: a lock only if the prior's choice was itself
        decided, which the Tracker knows — issue 13: a mirror taken at acquisition must not
        become a confident track) — where the prior sides with it (``_by_prior``). A ring
        found beyond that window says the prior is off, and which side of the line of sight
        the ring turned to is then not the prior's to say (as in ``_against_mirror``): random:107
        at 0.5 m, 17° turned since the prior, the ring found by extraction, its other pose
        unverified (the bore's rim at 0.14 of its length), the wrong pose kept as decided 13°
        and 35 mm off. Before a tie goes to the prior, where neither pose shows the thruster,
        the ring's holes decide if they can. Returns (fit, ambiguous, from_prior)."""
        mirror = self._mirror(image, fit)
        if mirror is None:
            return fit, False, False
        mirror_full = self._find_thruster(image, mirror, None) if mirror.verified else None
        if mirror_full is not None:
            best, decided = self._thruster_found_on(image, mirror, mirror_full, fit)
        else:
            best, decided = self._better_of(fit, mirror)
        if decided:
            return best, False, False
        holed = None
        if mirror_full is None:
            # No thruster on either pose: the holes, labeled from the ring's own fit, may still
            # tell the two apart (held-out random:102 at 1.2 m after the 17° turn: the pose
            # nearer the prior, flagged, was 15° off; the holes decide for the true one). With
            # a thruster on the other pose its roll labels the holes, as the answer's holes
            # fit does (asked here, the holes' own pattern roll decided the default mock-up
            # 6° off at 3 m, high noise, where the thruster's gave 0.9°).
            holed, decided = self._with_holes(image, fit)
            if decided:
                return holed, False, False
        nearer, ambiguous, from_prior = self._by_prior(fit, mirror_full or mirror, prior)
        if nearer is fit and holed is not None:
            nearer = holed  # (its holes fitted, undecided: not fitted again for the answer)
        return nearer, ambiguous or not held, from_prior and held

    def _thruster_found_on(
        self, image: _Image, mirror: _Fit, mirror_full: _Fit, ring: _Fit
    ) -> tuple[_Fit, bool]:
        """The thruster found at the ring's other pose (``mirror_full``, on ``mirror``) and
        not at ``ring``'s: the 6-DOF fit at ``ring``'s normal with the thruster where
        ``mirror_full`` found it (``_other_full``) is weighed against it (``_better_of``). A
        thruster found a pixel or two from where the other pose puts it is no decision:
        random:112 at 3 m, 9° turned, high noise, the thruster verified at 0.46 of its length
        (0.45 needed) on the pose 14° off and not at the true one. Without such a fit the
        thruster decides — unless the ring's own edges clearly refute the pose it was found
        on: what a roll search finds there may be anything of its size (random:116 at 1.2 m,
        its thruster out of view: a bolt 96° round taken for it on the pose 16° off, whose
        ring edges cost ten times the true pose's). Returns (fit, decided)."""
        other = self._other_full(image, mirror, mirror_full, ring.ring, None, near_roll=True)
        if other is not None:
            return self._better_of(mirror_full, other)
        by_ring, decided = self._better_of(mirror_full, ring)
        if decided and by_ring is ring:
            return ring, True
        return mirror_full, True

    def _track_by_extraction(self, image: _Image, ring0: CirclePose, predicted) -> _Fit | None:
        """Extract ellipses around the prediction and keep the best ring they verify, as
        acquisition does (``_best_ring``), if it lies within the box's margin of the predicted
        ring (farther, it was found by a search of its own, not tracked); the prior then only
        chooses between its two poses.

        Labeling the ellipses against the predicted edges instead took the nearest in size
        for the ring: a deep bore's rim and foot, when the ring's own faint edge was not
        extracted — random:104 at 0.85 m, a prior 2.3 cm behind on the approach path: the
        ring 12.8 cm too far, tracked so down to the stand-off (NEES ~10⁵). The hypotheses
        also read such a pair as the bore's, and the ring verified over its edges wins."""
        margin = 0.3 * predicted.a + 20.0
        box = (
            int(predicted.cx - predicted.a - margin),
            int(predicted.cy - predicted.a - margin),
            int(predicted.cx + predicted.a + margin),
            int(predicted.cy + predicted.a + margin),
        )
        extracted = extract_ellipses(
            image.gray,
            image.noise,
            roi=box,
            settings=self.settings.extractor,
            field=image.field(image.fine_sigma, box),
        )
        ring = self._best_ring(image, extracted)
        if ring is None or self._ring_moved_px(ring0, ring.ring) > margin:
            return None
        return ring

    # --- acquisition ----------------------------------------------------------------------
    def _acquire(self, image: _Image, extracted: list[ExtractedEllipse]):
        """The best verified ring (``_best_ring``), its pose resolved without a prior."""
        best = self._best_ring(image, extracted)
        return None if best is None else (*self._resolve(image, best), False)

    def _best_ring(self, image: _Image, extracted: list[ExtractedEllipse]) -> _Fit | None:
        """Verify the ring hypotheses in order and keep the best that verified: the ring
        whose edges are found over most of their lengths. A stray ellipse — arcs of the ring
        and the bore at close range, where the ring runs out of the frame, joined into one —
        can verify too, with the ring it implies found only in part; earlier hypotheses win
        ties (``support_margin``), and a ring found all round ends the search."""
        s = self.settings
        hypotheses = ring_hypotheses(
            extracted,
            self.outer,
            self.inner,
            max_count=s.max_hypotheses,
            bore_depth_m=self._bore_depth_m,
            focal_px=float(self.camera.K[0, 0]),
        )
        best, best_support = None, 0.0
        for hypothesis in hypotheses:
            if hypothesis.outer is not None:
                labeled, circle = hypothesis.outer, self.outer
            elif hypothesis.inner is not None:
                labeled, circle = hypothesis.inner, self.inner
            else:  # a lone ellipse taken for the bore's foot
                labeled, circle = hypothesis.bore_foot, self.foot
            assert labeled is not None and circle is not None
            polarities = {}
            if hypothesis.outer is not None:
                polarities[self.outer.name] = hypothesis.outer.polarity
                if self._outer_polarity not in (None, hypothesis.outer.polarity):
                    continue  # the ring the model describes is the other way round
            if hypothesis.inner is not None and self.inner is not None and self.foot is None:
                # (with a deep bore the ellipse taken for the inner edge may be the bore's
                # foot, of the other polarity: the image chooses, ``_ring_polarities``)
                polarities[self.inner.name] = hypothesis.inner.polarity
            ring = None
            for candidate in self._closed_form(labeled, circle):
                ring = self._refine_ring(image, candidate, polarities)
                if ring is not None:
                    break
            if ring is None:
                continue
            support = self._ring_support(image, ring)
            if best is None or support > best_support + s.support_margin:
                best, best_support = ring, support
            if best_support >= s.full_ring_support:
                break
        return best

    def _closed_form(self, labeled: ExtractedEllipse, circle: Circle3D) -> list[CirclePose]:
        """The two closed-form poses of the ring's reference circle from one labeled ellipse
        (its conic refitted on the undistorted support points)."""
        try:
            Q = fit_ellipse_direct(ideal_pixels(labeled.points, self.camera.K, self.camera.dist))
            poses = circle_poses_from_conic(Q, circle.radius, self.camera.K)
        except ValueError:
            return []
        # The labeled circle is coaxial with the reference: move its centre along the axis.
        height = float((circle.center_T - self.outer.center_T) @ self.outer.normal_T)
        return [CirclePose(p.center_C - height * p.normal_C, p.normal_C) for p in poses]

    def _resolve(self, image: _Image, ring: _Fit):
        """Without a prior: add the thruster (6-DOF) and settle the two-fold ambiguity of the
        ring's pose with it or with the costs. Returns (fit, ambiguous)."""
        full = self._find_thruster(image, ring, None)
        mirror_pose = self._mirror_pose(ring)
        if mirror_pose is None:  # both poses are one (near head-on)
            return full or ring, False
        if full is not None:
            other = self._other_full(image, ring, full, mirror_pose, None)
            if other is None:
                return full, False
            best, decided = self._better_of(full, other)
            return best, not decided
        mirror = self._mirror(image, ring, mirror_pose)
        if mirror is None:
            return ring, False
        mirror_full = self._find_thruster(image, mirror, None) if mirror.verified else None
        if mirror_full is not None:
            best, decided = self._thruster_found_on(image, mirror, mirror_full, ring)
            return best, not decided
        best, decided = self._better_of(ring, mirror)
        return best, not decided

    def _better_of(self, a: _Fit, b: _Fit) -> tuple[_Fit, bool]:
        """The better of two fits of one frame (the ring's two poses), and whether the image
        decides between them.

        Each fit's own cost counts the edges *it* found — misses at 4 px² each —, so two fits
        that found different samples compare their luck as much as their poses (issue 13: a
        15 % cost ratio took the mirror pose, 15° off, as decided in 2 of 60 frames of an
        approach). Here both poses are judged on the same points — every edge point either fit
        found, each fit's set weighted ½ — in units of the residuals' own robust spread: the
        worse pose's truncated χ² must be higher by ``_POSES_DECIDE_CHI2`` after allowing for
        the samples' correlation (a likelihood-ratio test with a ≈ 5σ threshold). That test
        trusts the edge model; where the model is off (shading, a bore wall, bolts on the
        edge), low noise makes a model error look significant. So the image decides only when
        both tests — this one and the costs 15 % apart — name the same pose; otherwise the
        answer says it is undecided (held-out random mock-ups, acquisition: docs/any_mockup.md).

        The ring's own edges count where either fit found them (an unverified fit may lack
        the inner one: near the camera the inner edge's offset from the outer is what tells
        the two poses apart — random:114 at 0.5 m, 9° turned: 129 samples at the true pose,
        none at the other); an off-axis circle only where both found it (a 5-DOF fit's roll
        says nothing about where it lies)."""
        ring_names = {c.name for c in self._ring_circles()}
        points = {
            n: tuple(f.edges[n].uv_ideal for f in (a, b) if n in f.edges)
            for n in {**a.edges, **b.edges}
            if n in ring_names or (n in a.edges and n in b.edges)
        }
        residuals = [self._edge_residuals(points, self._pose_of(f)) for f in (a, b)]
        sq_a, sq_b = (np.concatenate([r**2 for r in pair]) for pair in residuals)
        weights = np.concatenate([np.full(len(r), 0.5) for r in residuals[0]])
        if not len(weights):
            return (a if (a.verified, -a.cost) >= (b.verified, -b.cost) else b), False
        # the noise scale from the better pose at each point (MAD of a half-normal: 0.455)
        spread = max(float(np.median(np.minimum(sq_a, sq_b))) / 0.455, 0.05**2)
        chi2_a, chi2_b = (float(weights @ np.minimum(sq / spread, 9.0)) for sq in (sq_a, sq_b))
        gap = abs(chi2_a - chi2_b) / _correlation_inflation(a.sigma_px, a.spacing_px)
        best = a if chi2_a <= chi2_b else b
        other = b if best is a else a
        if not best.verified:  # it may leave the choice open, not win it
            return other, False
        # An unverified fit's own cost covers the few edges it found (the inner one may be
        # missing altogether): there the test on the same points decides alone — where before
        # such a fit was taken as absent, and the verified pose as decided without a test.
        costs_agree = not other.verified or other.cost > _POSES_DECIDE_COST_RATIO * best.cost
        return best, gap > _POSES_DECIDE_CHI2 and costs_agree

    def _pose_of(self, fit: _Fit) -> Pose:
        return fit.X_CT if fit.X_CT is not None else pose_with_roll(fit.ring, self.outer, 0.0)

    def _edge_residuals(
        self, points: dict[str, tuple[np.ndarray, ...]], X_CT: Pose
    ) -> list[np.ndarray]:
        """``_residuals`` of each circle's point sets under ``X_CT`` (a circle's sets together,
        so that a free radius is centred on all of them), one array per set."""
        out = []
        for name, sets in points.items():
            every = self._residuals(name, X_CT, np.vstack(sets))
            split = np.cumsum([len(uv) for uv in sets])[:-1]
            out.extend(np.split(every, split))
        return out

    def _same_normal(self, a: _Fit, b: _Fit) -> bool:
        """Whether two fits' normals agree within 3σ of ``a``'s (and 1°)."""
        return not normals_apart(normal_angle(a.ring.normal_C, b.ring.normal_C), self._cov5(a))

    def _cov5(self, fit: _Fit) -> np.ndarray:
        """The 5-DOF covariance of a fit's ring (from its 6-DOF pose's when it has one)."""
        if fit.X_CT is not None:
            return circle_covariance_from_pose(fit.result.covariance, fit.X_CT, self.outer)
        return fit.result.covariance[:5, :5]

    def _mirror_pose(self, ring: _Fit) -> CirclePose | None:
        """The ring's other closed-form pose, when it differs from ``ring`` by more than 3σ of
        its normal (and 1°); None otherwise."""
        Q = circle_image_conic(
            ring.ring.center_C, ring.ring.normal_C, self.outer.radius, self.camera.K
        )
        try:
            candidates = circle_poses_from_conic(Q, self.outer.radius, self.camera.K)
        except ValueError:
            return None
        other = max(candidates, key=lambda c: normal_angle(c.normal_C, ring.ring.normal_C))
        if not normals_apart(normal_angle(other.normal_C, ring.ring.normal_C), self._cov5(ring)):
            return None
        return other

    def _mirror(self, image: _Image, ring: _Fit, pose: CirclePose | None = None) -> _Fit | None:
        """The ring's other pose (``pose`` when already known), refined, when distinct —
        ``verified`` or not; None otherwise."""
        if pose is None:
            pose = self._mirror_pose(ring)
        if pose is None:
            return None
        mirror = self._refine_ring(image, pose, ring.polarities, verify=False)
        if mirror is None or self._same_normal(ring, mirror):
            return None
        return mirror

    # --- refinement -----------------------------------------------------------------------
    def _ring_circles(self) -> list[Circle3D]:
        return [self.outer] if self.inner is None else [self.outer, self.inner]

    def _refine_ring(
        self,
        image: _Image,
        ring: CirclePose,
        polarities: dict[str, int] | None,
        *,
        coarse_half_width: float | None = None,
        inner_always: bool = False,
        abandon_beyond_px: float | None = None,
        verify: bool = True,
    ) -> _Fit | None:
        """5-DOF: edge search around the projected ring edges and fit, coarse-to-fine when the
        start may be several pixels off; None unless both edges are supported (without
        ``verify``: the fit regardless, marked ``verified`` or not). ``inner_always`` fits the
        inner edge whatever its distance from the outer one; ``abandon_beyond_px`` as in
        ``_refine``."""
        s = self.settings
        if coarse_half_width is None:  # a start from a fitted ellipse: within a pixel or two
            stages = ((image.fine_sigma, s.fine_half_width_px + 1.0),)
        else:
            stages = (
                (s.coarse_sigma_px * image.scale, coarse_half_width),
                (image.fine_sigma, s.fine_half_width_px),
            )
        X_CT = pose_with_roll(ring, self.outer, 0.0)
        refined = self._refine(
            image,
            X_CT,
            self._ring_circles(),
            stages,
            polarities,
            full=False,
            inner_always=inner_always,
            abandon_beyond_px=abandon_beyond_px,
        )
        if refined is None or self._ring_supported(refined.edges):
            return refined
        return replace(refined, verified=False) if not verify else None

    def _refine_full(
        self,
        image: _Image,
        X_CT: Pose,
        off_axis: list[Circle3D],
        polarities: dict[str, int] | None,
        coarse_half_width: float | None,
        off_axis_width: float | None = None,
        *,
        abandon_beyond_px: float | None = None,
        verify: bool = True,
    ) -> _Fit | None:
        """6-DOF: ring and off-axis circles searched coarse then fine around ``X_CT`` (fine
        only, in a slightly wider window, when ``coarse_half_width`` is None; the off-axis
        circles in ``off_axis_width`` when given) and fitted together; None unless the ring and
        an off-axis circle are supported and the off-axis circles' nuisance radii are
        plausible (without ``verify``: a fit with an off-axis circle's edges, supported or not,
        marked ``verified`` or not). ``abandon_beyond_px`` as in ``_refine``."""
        s = self.settings
        if not off_axis:
            return None
        if coarse_half_width is None:
            stages = ((image.fine_sigma, s.fine_half_width_px + 2.0),)
        else:
            stages = (
                (s.coarse_sigma_px * image.scale, coarse_half_width),
                (image.fine_sigma, s.fine_half_width_px),
            )
        refined = self._refine(
            image,
            X_CT,
            self._ring_circles() + off_axis,
            stages,
            polarities,
            full=True,
            off_axis_width=off_axis_width,
            abandon_beyond_px=abandon_beyond_px,
        )
        if refined is None or not any(c.name in refined.edges for c in off_axis):
            return None
        if self._full_supported(refined, off_axis):
            return refined
        return replace(refined, verified=False) if not verify else None

    def _full_supported(self, refined: _Fit, off_axis: list[Circle3D]) -> bool:
        """Whether a 6-DOF fit's ring and one of its off-axis circles are supported and the
        off-axis circles' nuisance radii plausible."""
        s = self.settings
        if not self._ring_supported(refined.edges):
            return False
        if not any(
            c.name in refined.edges and refined.edges[c.name].support >= s.min_thruster_support
            for c in off_axis
        ):
            return False
        free = [e.circle.name for e in refined.sets if e.free_radius]
        return all(
            abs(offset) <= 0.3 * self._circles[name].radius
            for name, offset in zip(free, refined.result.radius_offsets, strict=True)
        )

    def _refine(
        self,
        image: _Image,
        X_CT: Pose,
        circles: list[Circle3D],
        stages,
        polarities: dict[str, int] | None,
        *,
        full: bool,
        off_axis_width: float | None = None,
        inner_always: bool = False,
        abandon_beyond_px: float | None = None,
    ) -> _Fit | None:
        """Search every circle's edges at each (σ, window) stage and refit the pose.

        ``abandon_beyond_px`` (a track's one fine stage, whose caller discards a pose that moved
        the ring beyond the window): the stage is abandoned, None, as soon as the ring's outer
        edge is found that far from its prediction (``_edge_shift_px``) or too sparsely to fit
        — before the other circles' searches and the fit, whose result would be discarded (the
        bench's 1 cm / 1° prior at 1.2 m: 27 of 30 fine stages)."""
        polarities = dict(polarities or {})
        if self._outer_polarity is not None:
            if polarities.get(self.outer.name, self._outer_polarity) != self._outer_polarity:
                return None  # an edge of the other polarity is not the ring's outer edge
            polarities[self.outer.name] = self._outer_polarity
        edges: dict[str, CircleEdges] = {}
        result = None
        ring = CirclePose(X_CT.apply(self.outer.center_T), X_CT.R @ self.outer.normal_T)
        for sigma, width in stages:
            edges = {}
            if self.inner is not None and self.inner.name not in polarities:
                ring_polarities = self._ring_polarities(image, X_CT, sigma, width)
                for name, polarity in ring_polarities.items():
                    polarities.setdefault(name, polarity)
            for circle in circles:
                circle_width = width
                if circle in self.off_axis:
                    # Small circles get at most a window of about their own size.
                    radius_px = self._radius_px(X_CT, circle)
                    circle_width = min(
                        width if off_axis_width is None else off_axis_width,
                        max(self.settings.fine_half_width_px, 0.5 * radius_px),
                    )
                found = self._circle_edges(
                    image, X_CT, circle, sigma, circle_width, polarities.get(circle.name)
                )
                if (
                    circle is self.inner
                    and image.foot_for_rim
                    and self._bore_wall_shows(X_CT, sigma)
                ):
                    found = self._bore_edges(image, X_CT, sigma, circle_width, found)
                if abandon_beyond_px is not None and circle is self.outer:
                    if found is None or found.hits.count < _MIN_OUTER_EDGES:
                        return None  # (as below, after the other circles' searches)
                    shift = _edge_shift_px(found)
                    if shift is not None and shift > abandon_beyond_px:
                        return None
                if found is not None and found.hits.count >= _MIN_EDGES:
                    edges[circle.name] = found
                    polarities.setdefault(circle.name, found.polarity)
            edges = self._drop_blurred(edges, X_CT, sigma)
            if self.outer.name not in edges or not _enough_of_outer(edges[self.outer.name]):
                return None
            sets = self._edge_sets(edges, X_CT, inner_always=inner_always)
            # The first stage only needs to land within the second's window.
            iterations = 2 if (sigma, width) != stages[-1] else 5
            fitted = self._fit_sets(sets, X_CT, ring, full=full, iterations=iterations)
            if fitted is None:
                return None
            result, X_CT, ring = fitted
        assert result is not None
        # The bore's samples were split between its rim and its foot at the stage's start; a
        # start a few centimetres off in depth (a track's prior, one frame behind on the
        # approach) puts the foot's samples nearer the rim, and the fit then tilts the ring to
        # hold them (random:100 at 1.6 m: 1 of 219 samples on the foot at the prior, 56 at the
        # truth; the track drifted 4° over nine frames). Split again at the fitted pose, and
        # refit, until the split stands.
        for _ in range(_MAX_RESPLITS):
            resplit = self._edge_sets(edges, X_CT, inner_always=inner_always)
            if _same_sets(resplit, sets):
                break
            fitted = self._fit_sets(resplit, X_CT, ring, full=full, iterations=5)
            if fitted is None:
                return None
            sets, (result, X_CT, ring) = resplit, fitted
        distance = float(np.linalg.norm(X_CT.apply(self.outer.center_T)))
        if not self.settings.min_range_m <= distance <= self.settings.max_range_m:
            return None
        misfit = _outer_misfit_px(result, sets, self.outer.name, edges[self.outer.name], sigma)
        if misfit > _MAX_OUTER_MISFIT_PX:
            return None
        if full:
            ring = CirclePose(X_CT.apply(self.outer.center_T), X_CT.R @ self.outer.normal_T)
        return _Fit(
            ring,
            X_CT if full else None,
            result,
            edges,
            self._cost(edges, X_CT),
            stages[-1][0],
            edges[self.outer.name].samples.spacing_px,
            sets=tuple(sets),
        )

    def _fit_sets(
        self, sets: list[EdgeSet], X_CT: Pose, ring: CirclePose, *, full: bool, iterations: int
    ) -> tuple[FitResult, Pose, CirclePose] | None:
        """The 6-DOF (``full``) or 5-DOF fit of ``sets`` from ``X_CT`` / ``ring``: (result,
        pose, ring pose), the pose's roll 0 when 5-DOF; None when it fails or lands behind the
        camera."""
        try:
            if full:
                result = fit_target_pose(sets, X_CT, self.camera.K, iterations=iterations)
                X_CT = result.pose
            else:
                result = fit_circle_pose(
                    sets, ring, self.outer, self.camera.K, iterations=iterations
                )
                ring = result.pose
                X_CT = pose_with_roll(ring, self.outer, 0.0)
        except (ValueError, np.linalg.LinAlgError):
            return None
        if not np.all(np.isfinite(X_CT.p)) or X_CT.p[2] <= 0:
            return None
        return result, X_CT, ring

    def _ring_polarities(
        self, image: _Image, X_CT: Pose, sigma: float, width: float
    ) -> dict[str, int]:
        """The ring's edge polarities when unknown: the two edges of an annulus have opposite
        ones, so both assignments are scored together (edge strength on a few samples of each
        edge) — a window wide enough to hold both edges cannot then take one for the other.

        The outer edge's polarity comes from the model's colours when it says which side is
        brighter. The bore's does only while its wall does not show: where the wall is seen as
        a band of its own, the edge is between the ring's front and the wall, whose shade
        depends on the light (a bore 6.8 cm deep, its wall in shade, showed its rim with the
        outer edge's polarity; searched with the other one, the rim was never found and the
        ring was taken for its foot, 7 cm too far)."""
        assert self.inner is not None

        def strength(circle: Circle3D, polarity: int) -> float:
            found = self._circle_edges(image, X_CT, circle, sigma, width, polarity, probe=True)
            return 0.0 if found is None else float(found.hits.snr.sum())

        p = self._outer_polarity
        if p is not None:
            if not self._bore_wall_shows(X_CT, sigma):
                return {self.outer.name: p, self.inner.name: -p}
            # The outer edge's polarity is known: only the bore's is in question.
            q = max((-p, p), key=lambda q: strength(self.inner, q))
            return {self.outer.name: p, self.inner.name: q}
        pairs = [(p, -p) for p in (1, -1)]
        p, q = max(
            pairs, key=lambda pair: strength(self.outer, pair[0]) + strength(self.inner, pair[1])
        )
        return {self.outer.name: p, self.inner.name: q}

    def _bore_wall_shows(self, X_CT: Pose, sigma: float) -> bool:
        """Whether the bore's wall shows as a band of its own between rim and foot (wider
        than the smoothing), so that its shade, not the ring's colours, sets the bore edge's
        polarity; far off, rim and foot blur into one edge between the face and the ring."""
        if self.foot is None or self.inner is None:
            return False
        gap = abs(self._radius_px(X_CT, self.inner) - self._radius_px(X_CT, self.foot))
        return gap > 2.0 * sigma + 1.0

    def _bore_edges(
        self,
        image: _Image,
        X_CT: Pose,
        sigma: float,
        half_width: float,
        at_rim: CircleEdges | None,
    ) -> CircleEdges | None:
        """The bore's edge where its wall shows as a band: the rim's search (``at_rim``) or,
        when that found too little to support the ring, the foot's, if it finds the foot over
        most of its length (``min_bore_foot_support``; its samples are then fitted to the
        nearer of the two circles, ``_inner_sets``). A wall as dark as the ring's front leaves
        no rim at all — only its foot, against the face seen through the bore (random:101,
        square on at 1.2 m: the rim's search found 0 of 320 samples, the foot 9 px inside it
        stood out all round, and no ring verified). Acquisition only (``_Image.foot_for_rim``):
        after the matrix's 17° turn a track from the prior found the true rim where it put
        the foot and held a ring 12° off (random:109 at 1.2 m)."""
        assert self.foot is not None
        if at_rim is not None and at_rim.support >= self.settings.min_inner_support:
            return at_rim
        at_foot = self._circle_edges(image, X_CT, self.foot, sigma, half_width, None)
        if at_foot is None or at_foot.support < self.settings.min_bore_foot_support:
            return at_rim
        return at_foot

    def _ring_supported(self, edges: dict[str, CircleEdges]) -> bool:
        s = self.settings
        if (
            edges.get(self.outer.name) is None
            or edges[self.outer.name].support < s.min_outer_support
        ):
            return False
        if self.inner is None:
            return True
        inner = edges.get(self.inner.name)
        return inner is not None and inner.support >= s.min_inner_support

    def _ring_support(self, image: _Image, ring: _Fit) -> float:
        """Mean support of the ring's edges (the outer alone when the model has no inner),
        raised by the bore's foot where the bore's wall shows as a band of its own and the
        foot is found there (so possibly above 1).

        A deep bore's rim and foot are a concentric pair much like the ring's own two edges,
        and read as the ring they imply a ring farther off whose "inner edge" — the foot, a
        strong edge all round — is found over more of its length than the true ring's faint
        edges are (random:104 at 0.67 m: 0.41 / 0.99 against 0.47 / 0.57, the ring 10 cm too
        far won). Only the true ring also explains the foot behind its bore: the foot's
        support is added to the edges' mean as one more edge's share (there: 1.02 against
        0.80). Found, the foot counts for a hypothesis; not found, it costs nothing — whether
        it shows as an edge depends on the light (the wall's shade against the face seen
        through the bore), and averaged in as a miss it lost the default mock-up's ring at
        0.9 m (foot not found) to the thruster's lip read as a ring 4.9 m off."""
        names = [self.outer.name] + ([self.inner.name] if self.inner is not None else [])
        supports = [ring.edges[name].support for name in names]
        edges_only = float(np.mean(supports))
        X_CT = pose_with_roll(ring.ring, self.outer, 0.0)
        if self.foot is None or not self._bore_wall_shows(X_CT, ring.sigma_px):
            return edges_only
        foot = self._circle_edges(
            image, X_CT, self.foot, ring.sigma_px, self.settings.fine_half_width_px, None
        )
        return edges_only + (0.0 if foot is None else foot.support) / len(supports)

    def _radius_px(self, X_CT: Pose, circle: Circle3D) -> float:
        return float(
            self.camera.K[0, 0] * circle.radius / max(X_CT.apply(circle.center_T)[2], 1e-3)
        )

    def _drop_blurred(
        self, edges: dict[str, CircleEdges], X_CT: Pose, sigma: float
    ) -> dict[str, CircleEdges]:
        """Of two concentric off-axis circles whose images are closer than ~3σ (a thin lip at
        long range), keep the one with the stronger edges: the other is blurred into it."""
        names = [c.name for c in self.off_axis if c.name in edges]
        drop = set()
        for i, a in enumerate(names):
            for b in names[i + 1 :]:
                ca, cb = self.target.circle(a), self.target.circle(b)
                if np.linalg.norm(ca.center_T - cb.center_T) > 1e-6:
                    continue
                gap = abs(self._radius_px(X_CT, ca) - self._radius_px(X_CT, cb))
                if gap < 3.0 * sigma + 1.0:
                    weaker = min((a, b), key=lambda n: float(edges[n].hits.snr.sum()))
                    drop.add(weaker)
        return {name: e for name, e in edges.items() if name not in drop}

    def _edge_sets(
        self, edges: dict[str, CircleEdges], X_CT: Pose | None, *, inner_always: bool = False
    ) -> list[EdgeSet]:
        """Edge sets for the fit: the ring's outer edge fixes the scale; the others (inner
        edge, thruster) have free radii — their apparent size is biased by neighbours (the
        ring's inner wall, the nozzle's thin lip) while their position and shape are not. The
        inner edge joins only when it is far enough inside the outer one (see the settings).

        The bore's wall shows between the ring's inner rim and its foot on the face behind, and
        the edge found there is whichever of the two stands out: the rim where the wall is dark,
        the foot where a low sun lights the wall. With a pose (``X_CT``) each inner sample is
        fitted to the nearer of the two circles (they lie at different depths: taken for one,
        the other tilts the ring by degrees)."""
        use_inner = False
        if self.inner is not None and self.inner.name in edges:
            outer = edges[self.outer.name].samples
            inner = edges[self.inner.name].samples
            gap = 0.5 * (outer.perimeter_px - inner.perimeter_px) / np.pi
            use_inner = inner_always or gap >= self.settings.inner_edge_min_gap_px
        sets = []
        for name, e in edges.items():
            if len(e.uv_ideal) < 8:
                continue
            if self.inner is not None and name == self.inner.name:
                if use_inner:
                    sets += self._inner_sets(e.uv_ideal, X_CT)
                continue
            sets.append(
                EdgeSet(self._circles[name], e.uv_ideal, free_radius=name != self.outer.name)
            )
        return sets

    def _bore_distances(self, X_CT: Pose, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Inner-edge samples' distances (px) to the nearer of the bore's rim and foot, and
        which are nearer the foot (see ``_edge_sets``)."""
        assert self.inner is not None and self.foot is not None
        rim, foot = (self._signed_distances(c, X_CT, uv) for c in (self.inner, self.foot))
        on_foot = np.abs(foot) < np.abs(rim)
        return np.where(on_foot, foot, rim), on_foot

    def _signed_distances(self, circle: Circle3D, X_CT: Pose, uv: np.ndarray) -> np.ndarray:
        """Sampson distances (px) of ideal pixels to ``circle``'s image, negative inside."""
        centre = X_CT.apply(circle.center_T)
        cone = circle_cone(centre, X_CT.R @ circle.normal_T, circle.radius)
        Q = self._K_inv.T @ cone @ self._K_inv
        inside = self.camera.K @ (centre / centre[2])
        if inside @ Q @ inside > 0:
            Q = -Q
        return sampson_distances(Q, uv)

    def _inner_sets(self, uv: np.ndarray, X_CT: Pose | None) -> list[EdgeSet]:
        """The inner edge's samples as edge sets of the rim and of the foot (see
        ``_edge_sets``)."""
        assert self.inner is not None
        if self.foot is None or X_CT is None:
            return [EdgeSet(self.inner, uv, free_radius=True)]
        _, on_foot = self._bore_distances(X_CT, uv)
        return [
            EdgeSet(circle, uv[chosen], free_radius=True)
            for circle, chosen in ((self.inner, ~on_foot), (self.foot, on_foot))
            if chosen.sum() >= 8
        ]

    def _cost(self, edges: dict[str, CircleEdges], X_CT: Pose) -> float:
        """Truncated quadratic cost per searched sample, misses included: compares candidate
        poses on the same footing whatever their supports (residuals in px, capped at 2)."""
        total, count = 0.0, 0
        for name, e in edges.items():
            r = self._residuals(name, X_CT, e.uv_ideal)
            total += float(np.sum(np.minimum(r**2, 4.0))) + 4.0 * (len(e.samples.uv) - len(r))
            count += len(e.samples.uv)
        return total / max(count, 1)

    def _residuals(self, name: str, X_CT: Pose, uv: np.ndarray) -> np.ndarray:
        """Sampson distances (px) of ideal pixels ``uv`` to circle ``name``'s image under
        ``X_CT``, by the model the fit uses (``_edge_sets``: the bore's edge to the nearer of
        its rim and foot); for circles other than the outer edge about their median (a free
        radius: only the shape counts). Poses are judged by the model they were fitted with: a
        bore wall left out of the judging shifts the inner edge by pixels (8 cm of protrusion
        at 10° tilt, 3 m), more than the ring's mirror pose moves it."""
        if self.inner is not None and name == self.inner.name and self.foot is not None:
            r, _ = self._bore_distances(X_CT, uv)
        else:
            r = self._signed_distances(self.target.circle(name), X_CT, uv)
        if name != self.outer.name and len(r):
            r = r - np.median(r)
        return r

    def _circle_edges(
        self,
        image: _Image,
        X_CT: Pose,
        circle: Circle3D,
        sigma: float,
        half_width: float,
        polarity: int | None,
        *,
        probe: bool = False,
    ) -> CircleEdges | None:
        """Edges of one model circle near its projection with ``X_CT``; ``probe`` searches
        only every fourth sample (a quick look)."""
        spacing_px = self.settings.sample_spacing_px * max(1.0, sigma)
        key = (X_CT.R.tobytes(), X_CT.p.tobytes(), circle.center_T.tobytes())
        key += (circle.normal_T.tobytes(), circle.radius, spacing_px, half_width)
        if key not in image.samples:
            image.samples[key] = sample_projected_circle(
                X_CT.apply(circle.center_T),
                X_CT.R @ circle.normal_T,
                circle.radius,
                self.camera,
                spacing_px=spacing_px,
                margin_px=half_width + 2.0,
                field_radius_xy=self._field_radius,
                max_samples=self.settings.max_samples_per_circle,
            )
        samples = image.samples[key]
        if samples is None or len(samples.uv) < 8:
            return None
        if probe:
            samples = replace(
                samples,
                uv=samples.uv[::4],
                normals=samples.normals[::4],
                t=samples.t[::4],
                spacing_px=4 * samples.spacing_px,
            )
        lo = samples.uv.min(axis=0) - half_width - 4.0 * sigma - 4.0
        hi = samples.uv.max(axis=0) + half_width + 4.0 * sigma + 4.0
        grad = image.field(sigma, (lo[0], lo[1], hi[0], hi[1]))
        return find_circle_edges(
            grad,
            samples,
            self.camera,
            polarity=polarity,
            half_width_px=half_width,
            min_snr=self.settings.min_edge_snr,
            prior_sigma_px=max(half_width / 2.0, 1.5),
        )

    def _moved_px(self, X_a: Pose, X_b: Pose) -> float:
        """Largest image displacement (px) of the ring's outer edge between two poses."""
        rim = circle_points(self.outer.center_T, self.outer.normal_T, self.outer.radius, 24)
        a = X_a.apply(rim)
        b = X_b.apply(rim)
        if np.any(a[:, 2] <= 1e-3) or np.any(b[:, 2] <= 1e-3):
            return np.inf
        return float(
            np.max(np.linalg.norm(self.camera.project(a) - self.camera.project(b), axis=1))
        )

    def _ring_moved_px(self, a: CirclePose, b: CirclePose) -> float:
        """``_moved_px`` for two ring poses (the rim is symmetric: any common roll will do)."""
        return self._moved_px(
            pose_with_roll(a, self.outer, 0.0), pose_with_roll(b, self.outer, 0.0)
        )

    def _outer_edge_in_view_px(self, X_CT: Pose) -> float:
        """Length (px) of the ring's outer edge that ``X_CT`` puts inside the image."""
        circle = self.outer
        points = circle_points(
            X_CT.apply(circle.center_T), X_CT.R @ circle.normal_T, circle.radius, 256
        )
        mask, uv = visible_pixels(points, self.camera, 0.0, self._field_radius)
        both = mask & np.roll(mask, -1)  # arcs between neighbouring samples both in view
        steps = np.linalg.norm(np.roll(uv, -1, axis=0) - uv, axis=1)
        return float(np.sum(steps[both]))

    def _locus_in_view(self, ring: CirclePose, circle: Circle3D, radius_px: float) -> bool:
        """Whether the off-axis circle's centre can be in view at some roll."""
        rolls = np.linspace(-np.pi, np.pi, 72, endpoint=False)
        axis_point = ring.center_C
        zero = pose_with_roll(ring, self.outer, 0.0).apply(circle.center_T) - axis_point
        n = ring.normal_C
        along = (zero @ n) * n
        radial = zero - along
        ortho = np.cross(n, radial)
        locus = (
            axis_point + along + np.outer(np.cos(rolls), radial) + np.outer(np.sin(rolls), ortho)
        )
        return bool(np.any(visible_pixels(locus, self.camera, -radius_px, self._field_radius)[0]))

    def _visible_off_axis(self, X_CT: Pose) -> list[Circle3D]:
        """Off-axis circles the pose puts in view and large enough to find (radius ≥ 3 px)."""
        out = []
        for c in self.off_axis:
            center = X_CT.apply(c.center_T)
            if center[2] <= 0 or self._radius_px(X_CT, c) < 3.0:
                continue
            if visible_pixels(center[None, :], self.camera, 0.0, self._field_radius)[0][0]:
                out.append(c)
        return out

    # --- the thruster -----------------------------------------------------------------------
    def _find_thruster(
        self, image: _Image, ring: _Fit, prior: Pose | None, *, whole_turn: bool = True
    ) -> _Fit | None:
        """Search the roll about the ring's axis for the off-axis circles, largest first (near
        the prior's roll first when there is a prior, and only there unless ``whole_turn``),
        refine the best roll to a 6-DOF pose and verify it; the first circle that verifies
        settles it."""
        zero = pose_with_roll(ring.ring, self.outer, 0.0)
        for probe in sorted(self.off_axis, key=lambda c: -c.radius):
            radius_px = self._radius_px(zero, probe)
            if radius_px < 3.0 or not self._locus_in_view(ring.ring, probe, radius_px):
                continue
            # Smooth and search in proportion to the circle's image: a small one must not be
            # blurred away, a large one is displaced by the ring's tilt error times its lever.
            # (Two scales only, so the fields are shared with the other stages.)
            sigma = (
                self.settings.coarse_sigma_px * (1.0 if radius_px <= 20.0 else 2.0) * image.scale
            )
            width = float(max(2.5, 0.3 * radius_px))
            grad = image.field(sigma, None)
            # Near the prior's roll first (when there is one), else all the way round.
            roll_sets: list[np.ndarray | None] = [None]
            if prior is not None:
                local = roll_of(prior, ring.ring, self.outer) + np.radians(
                    np.arange(-12.0, 12.5, 1.0)
                )
                roll_sets = [local] + (roll_sets if whole_turn else [])
            found = None
            for rolls in roll_sets:
                found = search_roll(
                    grad,
                    ring.ring,
                    self.outer,
                    probe,
                    self.camera,
                    polarity=None,
                    rolls=rolls,
                    half_width_px=width,
                    field_radius_xy=self._field_radius,
                )
                if found is not None and found.score >= _ROLL_SCORE_MIN:
                    break
            if found is None or found.score < max(
                _ROLL_DISTINCTNESS * found.median_score, _ROLL_SCORE_MIN
            ):
                continue
            X_CT = pose_with_roll(ring.ring, self.outer, found.roll)
            polarities = {**ring.polarities, probe.name: found.polarity}
            # The ring is refined already; the circle is off by the ring's tilt error times its
            # lever: one fine stage with a window of ~0.4 of its radius for it.
            full = self._refine_full(
                image,
                X_CT,
                self._visible_off_axis(X_CT),
                polarities,
                None,
                off_axis_width=float(max(4.0, 0.4 * radius_px)),
            )
            if full is not None:
                return full
        return None

    # --- ring holes -------------------------------------------------------------------------
    def _with_holes(self, image: _Image, fit: _Fit) -> tuple[_Fit, bool]:
        """The 6-DOF fit redone with the ring's holes (``_fit_holes``), once: the fit returned
        carries whether they decided (``holes_decided``), so asking again — a track's choice
        between the ring's poses asks first, the answer after — costs nothing. Returns (fit,
        whether the holes decided between the ring's two poses)."""
        if fit.holes_decided is None:
            holed, decided = self._fit_holes(image, fit)
            fit = replace(holed, holes_decided=decided)
        return fit, fit.holes_decided

    def _fit_holes(self, image: _Image, fit: _Fit) -> tuple[_Fit, bool]:
        """The 6-DOF fit redone with the ring's holes, when enough of them are found around
        their projections (``fit`` unchanged otherwise, and for 5-DOF fits: without the roll
        the holes cannot be labeled). Returns (fit, whether the holes decided between the
        ring's two poses).

        Edges alone may have settled on the ring's other (mirror) pose — near head-on the two
        fit the edges almost equally well — while the holes tell them apart to first order:
        the joint fit starts from both and keeps the one that explains edges and holes better;
        the holes decide when the other's truncated χ² is higher by ``_HOLES_DECIDE_CHI2``.
        """
        roll_known = fit.X_CT is not None
        X_holes = fit.X_CT if roll_known else self._roll_of_holes(image, fit)
        if X_holes is None:
            return fit, False
        observed = self._find_holes(image, X_holes)
        if observed is None:
            return fit, False
        starts = [X_holes]
        mirror = self._mirror_pose(fit)
        if mirror is not None:
            starts.append(pose_with_roll(mirror, self.outer, roll_of(X_holes, mirror, self.outer)))
        roll_known = roll_known or not self._holes_symmetric
        edge_weight = 1.0 / _correlation_inflation(fit.sigma_px, fit.spacing_px)
        sets = list(fit.sets)
        tried: list[tuple[float, _Fit]] = []
        for X_start in starts:
            try:
                result = fit_target_pose(
                    sets,
                    X_start,
                    self.camera.K,
                    iterations=6,
                    points=observed,
                    edge_weight=edge_weight,
                )
            except (ValueError, np.linalg.LinAlgError):
                continue
            X_CT = result.pose
            if not np.all(np.isfinite(X_CT.p)) or not np.all(np.isfinite(result.covariance)):
                continue
            ring = CirclePose(X_CT.apply(self.outer.center_T), X_CT.R @ self.outer.normal_T)
            refit = replace(
                fit, ring=ring, X_CT=X_CT, result=result, holes=observed, roll_known=roll_known
            )
            tried.append((_joint_cost(result, fit.result.sigma_px), refit))
        if not tried:
            return fit, False
        tried.sort(key=lambda item: item[0])
        if len(tried) == 1:
            return tried[0][1], False
        (cost, best), (other_cost, other) = tried
        # Decided: the other start is clearly worse, or ends at the same pose (the holes
        # leave no second minimum).
        decided = other_cost - cost > _HOLES_DECIDE_CHI2 or self._same_normal(best, other)
        return best, decided

    def _roll_of_holes(self, image: _Image, fit: _Fit) -> Pose | None:
        """The ring alone (no thruster: roll unknown): the roll about its axis at which the
        ring's holes stand where the image shows discs of their polarity — a 1-D search (1°,
        then 0.1° about the best) of their summed matched-filter response, as the thruster's
        roll is searched. Once labeled, the holes measure the ring's tilt to first order, which
        its edges alone barely do near head-on (issue 13: faint or not, holes on a ring without
        a thruster went unused). The roll found is the pattern's, up to its symmetry. None when
        no roll's summed response reaches z 5 (each hole's disc fit is then tested too)."""
        s = self.settings
        holes = self.holes
        if not s.ring_holes or len(holes.names) < s.min_holes:
            return None
        zero = pose_with_roll(fit.ring, self.outer, 0.0)
        radius_px = float(np.median(holes.radius_m) * self.camera.K[0, 0] / max(zero.p[2], 1e-3))
        if radius_px < s.min_hole_radius_px:
            return None
        sigma = max(1.0, 0.6 * radius_px)
        smoothed = image.stack.smoothed(sigma)
        noise = image.noise / (2.0 * np.sqrt(np.pi) * sigma) * np.sqrt(1.125) + 1e-4
        ring_r = 2.2 * radius_px + 1.0
        angles = np.linspace(0.0, 2 * np.pi, 8, endpoint=False)
        around = ring_r * np.column_stack([np.cos(angles), np.sin(angles)])
        signs = np.where(holes.brighter, 1.0, -1.0)
        h, w = image.gray.shape

        # The holes turned about the ring's axis n through its centre: R_n(θ)·v = v cos θ +
        # (n × v) sin θ + n (n·v)(1 − cos θ), for every roll at once.
        n = fit.ring.normal_C
        v = (holes.points_T - self.outer.center_T) @ zero.R.T
        n_cross_v = np.cross(n, v)
        n_dot_v = v @ n

        def scores(rolls: np.ndarray) -> np.ndarray:
            c, si = np.cos(rolls)[:, None, None], np.sin(rolls)[:, None, None]
            P = fit.ring.center_C + v * c + n_cross_v * si + (n_dot_v[:, None] * n) * (1 - c)
            front = np.all(P[..., 2] > 1e-3, axis=1)
            uv = np.full(P.shape[:2] + (2,), -1e6)
            uv[front] = self.camera.project(P[front].reshape(-1, 3)).reshape(-1, len(v), 2)
            inside = np.all((uv > ring_r + 1) & (uv < [w - ring_r - 2, h - ring_r - 2]), axis=2)
            points = np.concatenate([uv[..., None, :], uv[..., None, :] + around], axis=2)
            safe = np.where(inside[..., None, None], points, 0.0).astype(np.float32)
            # (rows of nine samples: a remap map must stay under 32767 wide)
            values = cv2.remap(smoothed, safe.reshape(-1, 9, 2), None, cv2.INTER_LINEAR)
            values = values.reshape(len(rolls), len(v), 9)
            response = signs * (values[..., 0] - values[..., 1:].mean(axis=2)) * inside
            count = inside.sum(axis=1)
            out = response.sum(axis=1) / (noise * np.sqrt(np.maximum(count, 1)))
            return np.where(count >= s.min_holes, out, 0.0)

        coarse = np.radians(np.arange(0.0, 360.0, 1.0))
        coarse_scores = scores(coarse)
        best = int(np.argmax(coarse_scores))
        z = coarse_scores[best]
        if z < 5.0:  # (a pattern of many holes has as many peaks: no "distinct" test)
            return None
        fine = coarse[best] + np.radians(np.arange(-1.0, 1.01, 0.1))
        roll = float(fine[int(np.argmax(scores(fine)))])
        return pose_with_roll(fit.ring, self.outer, roll)

    def _find_holes(self, image: _Image, X_CT: Pose) -> PointObservations | None:
        """The ring's holes fitted as discs around their projections under ``X_CT``, in ideal
        pixels with their covariances; None when fewer than ``min_holes`` are found."""
        s = self.settings
        holes = self.holes
        if not s.ring_holes or len(holes.names) < s.min_holes:
            return None
        centres_C = X_CT.apply(holes.points_T)
        toward_camera = -centres_C / np.linalg.norm(centres_C, axis=1, keepdims=True)
        facing = toward_camera @ (X_CT.R @ self.outer.normal_T) > 0.3  # within ~70° of it
        A = local_affine(X_CT, holes.points_T, self.camera)
        radius_px = holes.radius_m * np.sqrt(np.abs(np.linalg.det(A)))
        reach_px = holes.window_m * np.linalg.norm(A, ord=2, axis=(1, 2)) + 2.0
        uv = self.camera.project(centres_C)
        h, w = image.gray.shape
        inside = np.all((uv >= reach_px[:, None]) & (uv <= [w - 1, h - 1] - reach_px[:, None]), 1)
        keep = np.flatnonzero(facing & inside & (radius_px >= s.min_hole_radius_px))
        if len(keep) < s.min_holes:
            return None
        fits = fit_discs(
            image.gray,
            uv[keep],
            A[keep],
            holes.radius_m[keep],
            holes.window_m[keep],
            extrusion_px=head_extrusion(
                X_CT, holes.points_T[keep], holes.height_m[keep], self.camera
            ),
            noise_sigma=image.clip_sigma,
        )
        moved = np.linalg.norm(fits.uv - uv[keep], axis=1)
        sign = np.where(holes.brighter[keep], 1.0, -1.0)
        good = fits.ok & (moved <= np.maximum(2.0, 0.5 * radius_px[keep]))
        good &= sign * fits.contrast_snr >= s.min_hole_snr
        if good.sum() < s.min_holes:
            return None
        return PointObservations.from_image(
            holes.points_T[keep[good]],
            fits.uv[good],
            fits.covariance[good],
            self.camera.K,
            self.camera.dist,
        )

    def _honest_covariance(self, fit: _Fit, inflation: float) -> np.ndarray:
        """The fit's covariance (scaled by ``inflation``), blended toward its linearisation at
        the head-on pose when the estimate is near head-on.

        A circle's tilt from the line of sight enters its image quadratically, so at a small
        estimated tilt θ̂ the tangent (the fit's own covariance) is over-confident about the
        tilt; at head-on the linearisation is as pessimistic as the edges allow. The weight
        exp(−½ (θ̂ / 1.5σ₀)²), with σ₀ the head-on weak-axis tilt sd, keeps the fit's
        covariance when the tilt is clearly measured and moves to the head-on one when the
        estimate cannot be told from head-on (noise pushes such estimates away from it).
        """
        sets = list(fit.sets)
        center = fit.ring.center_C
        head_on = -center / np.linalg.norm(center)
        tilt = normal_angle(fit.ring.normal_C, head_on)
        turn = rotation_between(fit.ring.normal_C, head_on)
        try:
            if fit.X_CT is not None:
                R = turn @ fit.X_CT.R
                X0 = Pose(R, center - R @ self.outer.center_T)
                cov0 = covariance_at(sets, fit.result, X0, self.camera.K, points=fit.holes)
                sigma0 = normal_sigma(circle_covariance_from_pose(cov0, X0, self.outer), weak=True)
            else:
                cov0 = covariance_at(
                    sets,
                    fit.result,
                    CirclePose(center, head_on),
                    self.camera.K,
                    reference=self.outer,
                )
                sigma0 = normal_sigma(cov0, weak=True)
        except (ValueError, np.linalg.LinAlgError):
            return inflation * fit.result.covariance + self._outer_wall_covariance(fit)
        sigma0 *= np.sqrt(inflation)
        weight = float(np.exp(-0.5 * (tilt / max(1.5 * sigma0, 1e-9)) ** 2))
        blended = inflation * ((1.0 - weight) * fit.result.covariance + weight * cov0)
        blended = blended + self._outer_wall_covariance(fit)
        return 0.5 * (blended + blended.T)

    def _outer_wall_covariance(self, fit: _Fit) -> np.ndarray:
        """What the ring's outer wall may do to the fit, as covariance (in the fit's own
        parameters; zeros where the wall does not show).

        Seen obliquely, the wall shows outside the ring's front on one side, as a band from
        the rim out to its foot on the face. Where the band is no wider than the smoothing it
        blurs into the edge, which then lies anywhere between rim and foot depending on the
        wall's shade — which no model here knows (fitting the samples to the nearer of rim
        and foot lost on the matrix: docs/any_mockup_heldout.md, "The ring's outer wall").
        The fit takes the rim; the edge may lie a fraction α ∈ [0, 1] of the band out. α is a
        consider parameter (``circle_fit.pose_response``): the pose's shift for the whole band
        times α's second moment about the rim, taken at its bound, 1 — a wall as dark as the
        ring puts the edge at the foot (random:101 at 3 m, rendered without noise: the edge
        1.1 px out where the foot lies 1.0 px out; the normal 2.65° off claiming 0.65°, NEES
        32 → 15 with this term). A foot beyond the final search's reach (window and
        smoothing) cannot have been found, and adds nothing.

        The band is measured where the fit would have landed without the wall: the fit leans
        toward it and so narrows the band it sees (random:109 at 3 m, rendered without noise:
        0.25 px at the fitted pose, 0.9 px at the truth, and the term held a quarter of the
        3° error). The fitted pose less the wall's whole shift is that pose; as the shift
        depends on the band there, fixed-point steps find it (``_WALL_STEPS``)."""
        size = len(fit.result.covariance)
        if self.outer_foot is None:
            return np.zeros((size, size))
        pose = fit.X_CT if fit.X_CT is not None else fit.ring
        displacements = self._wall_band(fit, pose)
        if not any(d.any() for d in displacements):
            return np.zeros((size, size))
        try:  # (only a 6-DOF fit holds points; the reference serves a 5-DOF one)
            response = pose_response(
                fit.sets, fit.result, pose, self.camera.K, reference=self.outer, points=fit.holes
            )
        except (ValueError, np.linalg.LinAlgError):
            return np.zeros((size, size))
        shift = response @ stacked_displacements(response, displacements)
        for _ in range(_WALL_STEPS):
            displacements = self._wall_band(fit, moved(pose, -shift))
            previous, shift = shift, response @ stacked_displacements(response, displacements)
            if np.linalg.norm(shift - previous) <= _WALL_TOLERANCE * np.linalg.norm(previous):
                break
        return np.outer(shift, shift)

    def _wall_band(self, fit: _Fit, pose: Pose | CirclePose) -> list[np.ndarray]:
        """Per edge set of ``fit``, how far out of the rim's image the outer wall's foot lies
        at ``pose`` (X_CT, or the ring's 5-DOF pose) along each outer-edge sample's normal
        (px; zero on other sets, where the wall is hidden, and beyond the final search's
        reach)."""
        X_CT = pose if isinstance(pose, Pose) else pose_with_roll(pose, self.outer, 0.0)
        reach = self.settings.fine_half_width_px + 1.0 + fit.sigma_px
        displacements = []
        for edge_set in fit.sets:
            band = np.zeros(len(edge_set.uv))
            if edge_set.circle.name == self.outer.name:
                # (the difference of the sample's signed distances to the two, wherever the
                # sample itself lies between them; negative: the wall is hidden there)
                uv = edge_set.uv
                band = self._signed_distances(self.outer, X_CT, uv) - self._signed_distances(
                    self.outer_foot, X_CT, uv
                )
                band = np.maximum(band, 0.0)
                band[band > reach] = 0.0
            displacements.append(band)
        return displacements

    # --- the measurement ------------------------------------------------------------------
    def _measurement(
        self,
        frame: Frame,
        status: str,
        fit: _Fit,
        choice: tuple[bool, bool, CirclePose | None],
        prior: Pose | None,
        extracted: list[ExtractedEllipse],
        started: float,
    ) -> Measurement:
        """5-DOF always (the ring's centre and normal); 6-DOF ``X_CT`` when the thruster was
        found; otherwise a full-pose hint with the roll carried over from the prior. ``choice``:
        (ambiguous, from_prior, the ring's other pose when either)."""
        ambiguous, from_prior, alternative = choice
        inflation = self.settings.covariance_scale
        if fit.holes is None:  # (a fit with holes weighed its edge samples' correlation already)
            inflation *= _correlation_inflation(fit.sigma_px, fit.spacing_px)
        X_CT = covariance = hint = None
        if fit.X_CT is not None and fit.roll_known:
            X_CT = fit.X_CT
            covariance = self._honest_covariance(fit, inflation)
            cov5 = circle_covariance_from_pose(covariance, X_CT, self.outer)
        elif fit.X_CT is not None:
            # Tilt from the holes, roll only up to their pattern's symmetry: the circle is the
            # measurement, the pose a hint (with the prior's roll among the pattern's turns).
            cov5 = circle_covariance_from_pose(
                self._honest_covariance(fit, inflation), fit.X_CT, self.outer
            )
            roll = roll_of(prior, fit.ring, self.outer) if prior is not None else 0.0
            hint = pose_with_roll(fit.ring, self.outer, roll)
        else:
            cov5 = self._honest_covariance(fit, inflation)
            roll = roll_of(prior, fit.ring, self.outer) if prior is not None else 0.0
            hint = pose_with_roll(fit.ring, self.outer, roll)
        labeled = np.vstack([e.hits.uv[e.hits.found] for e in fit.edges.values()])
        extracted_points = (
            np.vstack([e.points for e in extracted]) if extracted else np.zeros((0, 2))
        )
        return Measurement(
            system=SYSTEM,
            status=status,
            stamp=frame.stamp,
            seq=frame.seq,
            X_CT=X_CT,
            covariance=covariance,
            circle=self.outer.name,
            center_C=fit.ring.center_C,
            normal_C=fit.ring.normal_C,
            covariance_5dof=cov5,
            X_CT_hint=hint,
            residual_px=fit.result.rms_px,
            ambiguous=ambiguous,
            from_prior=from_prior,
            alternative_center_C=None if alternative is None else alternative.center_C,
            alternative_normal_C=None if alternative is None else alternative.normal_C,
            features={
                "extracted": _subsample(extracted_points, 400),
                "labeled": _subsample(labeled, 160),
            },
            time_ms=1000.0 * (time.perf_counter() - started),
        )


# --- helpers ----------------------------------------------------------------------------------


def _joint_cost(result: FitResult, edge_sigmas: tuple[float, ...]) -> float:
    """Truncated χ² of a fit with holes, edge residuals scaled by common noise scales, so that
    fits from different starts compare on the same footing."""
    total = float(np.sum(np.minimum(result.point_residuals**2, 9.0)))
    for r, sigma in zip(result.residuals, edge_sigmas, strict=True):
        total += result.edge_weight * float(np.sum(np.minimum((r / sigma) ** 2, 9.0)))
    return total


def ring_hole_layout(target: TargetModel, outer: Circle3D, inner: Circle3D | None) -> FeatureLayout:
    """The model's disc features on the ring's face: between its two edges, in its plane."""
    layout = FeatureLayout.of(target)
    if inner is None or not len(layout.names):
        return layout.select(np.zeros(len(layout.names), bool))
    offset = layout.points_T - outer.center_T
    height = offset @ outer.normal_T
    radial = np.linalg.norm(offset - height[:, None] * outer.normal_T, axis=1)
    on_face = (
        layout.is_disc
        & (np.abs(height) < outer.radius - inner.radius)
        & (radial - layout.radius_m > inner.radius)
        & (radial + layout.radius_m < outer.radius)
    )
    return layout.select(on_face)


def _rotationally_symmetric(holes: FeatureLayout, outer: Circle3D) -> bool:
    """Whether a turn about the ring's axis (other than a full one) maps the holes onto
    holes like them: their roll is then known only up to it."""
    if len(holes.names) < 2:
        return len(holes.names) == 1 and False
    centre = outer.center_T
    for k in range(2, len(holes.names) + 1):
        turn = Pose.from_rotvec(outer.normal_T * 2 * np.pi / k, np.zeros(3))
        moved = (holes.points_T - centre) @ turn.R.T + centre
        match = np.linalg.norm(moved[:, None] - holes.points_T[None], axis=2) < 1e-3
        same = (holes.brighter[:, None] == holes.brighter[None]) & (
            np.abs(holes.radius_m[:, None] - holes.radius_m[None]) < 1e-4
        )
        if np.all(np.any(match & same, axis=1)):
            return True
    return False


def _coaxial(circle: Circle3D, reference: Circle3D) -> bool:
    """True when ``circle`` shares the reference's axis (parallel normal, centre on the axis):
    such circles are fixed by the 5-DOF pose; others need the roll."""
    offset = circle.center_T - reference.center_T
    lateral = offset - (offset @ reference.normal_T) * reference.normal_T
    parallel = abs(float(circle.normal_T @ reference.normal_T)) > 1.0 - 1e-9
    return bool(np.linalg.norm(lateral) <= 1e-6 and parallel)


def _same_sets(a: list[EdgeSet], b: list[EdgeSet]) -> bool:
    """Whether two lists of edge sets hold the same samples on the same circles."""
    if len(a) != len(b):
        return False
    return all(
        x.circle.name == y.circle.name and np.array_equal(x.uv, y.uv)
        for x, y in zip(a, b, strict=True)
    )


def _low_harmonics(t: np.ndarray, values: np.ndarray) -> tuple[float, float, float] | None:
    """``values`` (px) at angles ``t`` around a circle fitted, robustly, by the first two
    harmonics (a shift, a change of scale and of tilt of the projected circle show as those):
    (the fitted curve's largest magnitude at the samples it kept, the spread of those samples
    about it, and that largest value's standard error — the spread times the root of its
    sample's leverage, large where the samples are few or bunched in short arcs); None for
    fewer than ``_MIN_OUTER_EDGES`` samples."""
    c, s = np.cos(t), np.sin(t)
    basis = np.column_stack([np.ones_like(t), c, s, c * c - s * s, 2.0 * c * s])
    keep = np.ones(len(t), bool)
    for _ in range(2):  # least squares, then again without the outliers it shows
        if keep.sum() < _MIN_OUTER_EDGES:
            return None
        kept = basis[keep]
        normal = kept.T @ kept + 1e-9 * np.eye(5)
        coefficients = np.linalg.solve(normal, kept.T @ values[keep])
        residuals = values - basis @ coefficients
        spread = 1.4826 * float(np.median(np.abs(residuals[keep])))
        inliers = np.abs(residuals) <= 3.0 * max(spread, 0.3)
        if np.array_equal(inliers, keep):
            break
        keep = inliers
    fitted = basis[keep] @ coefficients
    largest = int(np.argmax(np.abs(fitted)))
    row = basis[keep][largest]
    leverage = float(row @ np.linalg.solve(normal, row))
    return float(abs(fitted[largest])), spread, spread * math.sqrt(max(leverage, 0.0))


def _enough_of_outer(found: CircleEdges) -> bool:
    """Whether a stage found enough of the ring's outer edge to fit: ``_MIN_OUTER_EDGES``
    samples, or — where less of it is in view (close up, arcs at the image's corners) — most
    of the samples that are, and at least as many as any edge set needs (held-out random:109
    at 0.5 m, high noise: 10 of the 17 in view, the ring then fitted 1.4 mm / 0.3° off)."""
    count = found.hits.count
    in_view = len(found.hits.found)
    return count >= _MIN_OUTER_EDGES or (count >= _MIN_EDGES and 2 * count >= in_view)


def _edge_shift_px(found: CircleEdges) -> float | None:
    """The largest offset (px) along the normals of a circle's edge from its prediction, by
    its first two harmonics (``_low_harmonics``) at the samples found. An offset along the
    normal is at most the image displacement, so a shift beyond a window is a pose beyond it.
    None when in doubt: fewer than ``_MIN_OUTER_EDGES`` edges, or a fit whose residuals spread
    over more than 1.5 px (edges of other things)."""
    hits = found.hits
    fitted = _low_harmonics(found.samples.t[hits.found], hits.offset_px[hits.found])
    if fitted is None or fitted[1] > 1.5:
        return None
    return fitted[0]


def _outer_misfit_px(
    result: FitResult, sets: list[EdgeSet], name: str, outer: CircleEdges, sigma_px: float
) -> float:
    """How far (px) the ring's outer edge lies off its image at the fitted pose along a smooth
    curve: the residuals of its set (``name``) in the fit, by their first two harmonics
    (``_low_harmonics``), largest magnitude — where less than half of the edge is in view, 0
    when its samples cannot tell it from their own noise: within 3 standard errors, their
    correlation through the smoothing (``sigma_px``) counted (``_correlation_inflation``).

    The fit scales each edge set's noise by its own residuals, so a pose fitted to another pair
    of circles — a deep bore's rim and foot, a wall's band — discounts the ring's outer edge,
    its scale, rather than fail: the edge is then left off the fitted ellipse by pixels, all
    round, in a shift or scale the noise cannot make (a five-term fit to dozens of samples
    averages it out). On the open-loop path over random:100–109 (1200 frames) every fit with
    the edge a pixel or more off claimed a pose beyond its own 3σ (35 frames, median 13 cm off;
    one more flagged ambiguous); the fits within their 3σ stayed below 0.9 px, 945 of 1083
    below 0.25 px. 0 when the edge is too sparse to tell. Close up, where only arcs at the
    image's corners are in view, the harmonics rest on a few dozen bunched samples, five to a
    correlation length, and their noise alone reached 1.2 px (held-out random:109 at 0.5 m,
    high noise: 40 samples, the ring 0.3° off, dropped). A ring in view all round keeps the
    plain limit: a fit that discounts its outer edge leaves the edge's residuals spread
    widely, and so its standard error, too (2.1–2.4 px on those frames)."""
    index = next((k for k, e in enumerate(sets) if e.circle.name == name), None)
    t = outer.samples.t[outer.hits.found]
    if index is None or len(result.residuals[index]) != len(t):
        return 0.0
    fitted = _low_harmonics(t, np.asarray(result.residuals[index], dtype=float))
    if fitted is None:
        return 0.0
    misfit, _, standard_error = fitted
    samples = outer.samples
    if len(samples.t) * samples.spacing_px >= 0.5 * samples.perimeter_px:
        return misfit
    inflation = _correlation_inflation(sigma_px, samples.spacing_px)
    return misfit if misfit > 3.0 * standard_error * math.sqrt(inflation) else 0.0


def _correlation_inflation(sigma_px: float, spacing_px: float) -> float:
    """Neighbouring edge samples share pixels through the smoothing, so they are not
    independent: the fit's covariance (which assumes they are) is scaled by the number of
    samples per correlation length, 2√π·σ_eff (the width of the smoothing's autocorrelation;
    σ_eff includes the Sobel kernel's own smoothing)."""
    sigma_eff = np.hypot(sigma_px, 0.7)
    return float(max(1.0, 2.0 * np.sqrt(np.pi) * sigma_eff / spacing_px))


def _subsample(points: np.ndarray, count: int) -> np.ndarray:
    if len(points) <= count:
        return points
    return points[np.linspace(0, len(points) - 1, count).astype(int)]


def build(target: TargetModel, camera: CameraInfo, **options) -> EllipseEstimator:
    """Factory for ``estimators.registry``: options override ``EllipseSettings`` fields."""
    extractor_options = options.pop("extractor", None)
    settings = EllipseSettings()
    unknown = set(options) - set(EllipseSettings.__dataclass_fields__)
    if unknown:
        raise ValueError(f"unknown ellipse estimator option(s): {', '.join(sorted(unknown))}")
    settings = replace(settings, **options)
    if extractor_options:
        settings = replace(settings, extractor=replace(settings.extractor, **extractor_options))
    return EllipseEstimator(target, camera, settings)
