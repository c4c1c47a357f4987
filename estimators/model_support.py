"""How well a pose explains the image: edge support of the reprojected target model.

For every contour of the model (the panel's four edges, the outline of the face it sits on,
each circle: ring rims, the bore's foot, thruster exit)
sample points are projected with the pose and the smoothed image gradient is read there. On a
true edge the gradient is across the contour (|g·n| large); off any edge it is isotropic noise,
so |g·n| and |g·t| (along the contour) have the same distribution. The support of a contour is
the z-score of mean|g·n| − mean|g·t| over its samples (counting as independent only samples a
correlation length, 2σ of the smoothing, apart) — near 0 for a wrong pose, large for a right
one, and independent of contrast calibration. Point discs contribute a polarity test
(darker or brighter than their surroundings, as the model says).

This is the validation of every pose an estimator returns (a wrong lock is reported ``lost``)
and the tie-breaker among hypotheses the features themselves cannot separate: the square
panel's four-fold symmetry (the thruster breaks it) and the planar two-fold ambiguity (the ring
stands in front of the panel, so it moves differently). ``shift_px`` lets each contour take its
best image offset within a few pixels, so that rough hypotheses can still be ranked.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimators.compiled import compiled
from estimators.frame import CameraInfo
from estimators.geometry import Pose, field_radius
from estimators.imaging import NOISE_FLOOR, GradientImage
from estimators.lens_distortion import pixel_in_view, visible_pixels
from estimators.small_linalg import rigid_transform
from estimators.target import TargetModel

_SAMPLES_PER_EDGE = 24
_SAMPLES_PER_CIRCLE = 96
_MIN_SAMPLES = 8
#: A model point is in front of the camera beyond this depth (m).
_MIN_DEPTH_M = 1e-6
#: Standard deviation of |X| for X ~ N(0, 1).
HALF_NORMAL_SPREAD = math.sqrt(1.0 - 2.0 / math.pi)


@dataclass(frozen=True, slots=True)
class Support:
    """Edge support z-score per contour in view (with at least 8 samples), the disc polarity
    z-score (NaN without discs in view), and how many non-panel contours were in view."""

    contours: dict[str, float]
    discs: float

    def panel(self) -> list[float]:
        return [z for name, z in self.contours.items() if name.startswith("panel_edge")]

    def others(self) -> dict[str, float]:
        return {n: z for n, z in self.contours.items() if not n.startswith("panel_edge")}

    def panel_unsupported(self, min_mean: float, min_each: float) -> str:
        """Why the reprojected panel does not stand out of the noise ('' if it does): all four
        edges in view, their mean z-score at least ``min_mean`` and none below ``min_each``.
        The mean weighs the four edges' evidence together; each edge's own floor keeps a quad
        with one side on nothing from passing on the other three. A faint panel's weakest edge
        reads below its mean by the noise alone: four edges each of expected z 4 (unit noise)
        have even odds that one reads below 3, and one in four that one reads below 2.5."""
        panel = self.panel()
        if len(panel) < 4:
            return f"only {len(panel)} reprojected panel edges in view"
        if min(panel) < min_each:
            return f"a reprojected panel edge has no edge support (z {min(panel):.1f})"
        mean = sum(panel) / len(panel)
        if mean < min_mean:
            return f"the reprojected panel edges have too little edge support (mean z {mean:.1f})"
        return ""

    def confirmation(self, min_edge_support: float, *, tracking: bool) -> tuple[str, bool]:
        """Whether another part of the mock-up (ring, its bore's foot, outline, thruster)
        confirms the panel: a quad taken for the panel at a wrong scale (the face's outline as
        the panel) puts them all out of view or off their edges. Returns (why not, '' when
        confirmed; whether the prior stands in for them). In tracking the prior fixes the
        scale, and close up the panel may be all that shows (the grasp's last 15 cm: the ring
        out of view, or a bore's foot too faint under a low sun): the prior then confirms it
        — reported as ``from_prior``, which fusion uses only on a track whose roll is
        measured, gated, and never to start one."""
        others = self.others()
        if others and max(others.values()) >= min_edge_support:
            return "", False
        if tracking:
            return "", True
        if not others:
            return "no other part of the mock-up in view to confirm the panel", False
        return "the reprojected ring/thruster have no edge support", False

    @property
    def total(self) -> float:
        """Sum of all z-scores (a log-likelihood-like score to rank hypotheses)."""
        values = list(self.contours.values())
        if math.isfinite(self.discs):
            values.append(self.discs)
        return float(sum(values))


#: What a search over image offsets gains where the image holds nothing (gradients smoothed by
#: σ = 2 px; measured on pure noise, ``tests/estimators/test_model_support.py``): at the search
#: half-widths ``_SEARCH_SHIFTS_PX``, the mean z-score of a contour at its best offset, and
#: the mean of n discs' summed responses at their best common offset, per √n.
_SEARCH_SHIFTS_PX = (0.0, 1.5, 3.0, 6.0, 9.0)
_CONTOUR_SEARCH_GAIN = (0.0, 0.8, 1.2, 1.6, 1.85)
_DISC_SEARCH_GAIN = (0.0, 0.28, 0.57, 0.94, 1.06)


def search_gain_under_noise(shift_px: float) -> tuple[float, float]:
    """(per contour, per √n discs) what the best offset within ±``shift_px`` scores on noise
    alone: the selection bias of a maximum over correlated offsets."""
    return (
        float(np.interp(shift_px, _SEARCH_SHIFTS_PX, _CONTOUR_SEARCH_GAIN)),
        float(np.interp(shift_px, _SEARCH_SHIFTS_PX, _DISC_SEARCH_GAIN)),
    )


def summed_support(z: np.ndarray) -> np.ndarray:
    """Each pose's sum of the contour z-scores in view (rows of ``ModelSupport.contour_scores``),
    added in the model's order as a sum over a ``Support``'s contours adds them."""
    total = np.zeros(len(z))
    for column in np.asarray(z).T:
        total += np.where(np.isfinite(column), column, 0.0)
    return total


class ModelSupport:
    """The target's contours, sampled once, and their support at any pose."""

    def __init__(self, target: TargetModel, camera: CameraInfo):
        self.target = target
        self.camera = camera
        names, points, across = [], [], []
        corners = target.panel_corners_T
        centre = corners.mean(axis=0)
        for i in range(4):
            a, b = corners[i], corners[(i + 1) % 4]
            t = np.linspace(0.06, 0.94, _SAMPLES_PER_EDGE)[:, None]
            out = 0.5 * (a + b) - centre
            out -= out @ (b - a) / ((b - a) @ (b - a)) * (b - a)
            names.append(f"panel_edge_{i}")
            points.append(a + t * (b - a))
            across.append(np.broadcast_to(out / np.linalg.norm(out), (len(t), 3)))
        outline = target.outline_corners_T
        if outline is not None:
            middle = outline.mean(axis=0)
            for i in range(4):
                a, b = outline[i], outline[(i + 1) % 4]
                t = np.linspace(0.03, 0.97, 2 * _SAMPLES_PER_EDGE)[:, None]
                out = 0.5 * (a + b) - middle
                out -= out @ (b - a) / ((b - a) @ (b - a)) * (b - a)
                names.append(f"outline_edge_{i}")
                points.append(a + t * (b - a))
                across.append(np.broadcast_to(out / np.linalg.norm(out), (len(t), 3)))
        # The bore's foot too: close up its wall shows as a band, the inner rim (ring against
        # wall) may not stand out at all, and the foot (wall against face) is the edge in view.
        foot = target.ring_foot
        for circle in (*target.circles, *([foot] if foot is not None else [])):
            n = circle.normal_T
            u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
            u /= np.linalg.norm(u)
            v = np.cross(n, u)
            angles = np.linspace(0.0, 2.0 * np.pi, _SAMPLES_PER_CIRCLE, endpoint=False)
            radial = np.cos(angles)[:, None] * u + np.sin(angles)[:, None] * v
            names.append(circle.name)
            points.append(circle.center_T + circle.radius * radial)
            across.append(radial)
        self.names = tuple(names)
        self._foot = foot
        self._bore_depth_m = target.bore_depth_m
        self.points_T = np.concatenate(points)
        self.across_T = np.concatenate(across)
        self.contour_of = np.concatenate([np.full(len(p), i) for i, p in enumerate(points)])
        discs = [f for f in target.point_features if f.kind == "disc"]
        self.disc_centres_T = np.array([f.p_T for f in discs]).reshape(-1, 3)
        self.disc_signs = np.array([1.0 if f.brighter else -1.0 for f in discs])
        self.disc_radius_m = np.array([f.diameter / 2 for f in discs])
        self._field_radius = field_radius(camera.K, camera.dist, camera.width, camera.height)

    def _project(self, points_C: np.ndarray, margin_px: float):
        """Pixels (N,2) and an in-view mask (N,) of model points (N,3) in the camera frame
        (``_support_pixel``'s test); pixels NaN where not in view."""
        camera = self.camera
        margin = float(margin_px)
        seen, uv = visible_pixels(
            np.ascontiguousarray(points_C, dtype=float).reshape(-1, 3),
            np.array(camera.K, dtype=float),
            *camera.lens,
            _MIN_DEPTH_M,
            1.02 * self._field_radius,
            margin, camera.width - 1 - margin, margin, camera.height - 1 - margin,
        )  # fmt: skip
        uv[~seen] = np.nan
        return uv, seen

    def symmetric_under(self, turn: Pose, tolerance_m: float = 1e-3) -> tuple[set[str], bool]:
        """Which contours map onto the model's own contours under ``turn`` (X_TT'), and whether
        the disc layout does — parts that cannot tell ``X_CT`` from ``X_CT @ turn``."""
        symmetric = set()
        for i, name in enumerate(self.names):
            own = self.points_T[self.contour_of == i]
            moved = turn.apply(own)
            gap = np.min(
                np.linalg.norm(moved[:, None, :] - self.points_T[None, :, :], axis=2), axis=1
            )
            # Within half the contour's own sample spacing of a model sample: a face 5 cm
            # longer than wide is not symmetric under a quarter turn.
            spacing = float(np.max(np.linalg.norm(np.diff(own, axis=0), axis=1)))
            if np.max(gap) < tolerance_m + 0.5 * spacing:
                symmetric.add(name)
        discs_symmetric = True
        if len(self.disc_centres_T):
            moved = turn.apply(self.disc_centres_T)
            for p, r, sign in zip(moved, self.disc_radius_m, self.disc_signs, strict=True):
                match = (
                    (np.linalg.norm(self.disc_centres_T - p, axis=1) < tolerance_m)
                    & (np.abs(self.disc_radius_m - r) < tolerance_m)
                    & (self.disc_signs == sign)
                )
                discs_symmetric &= bool(np.any(match))
        return symmetric, discs_symmetric

    def score(
        self,
        gradients: GradientImage,
        X_CT: Pose,
        *,
        shift_px: float = 0.0,
        only: frozenset[str] | None = None,
        discs: bool = True,
    ) -> Support:
        """Support of every contour (or of those named in ``only``) and of the discs (unless
        ``discs`` is False) at ``X_CT`` (see module docstring)."""
        z = self.contour_scores(gradients, X_CT.R[None], X_CT.p[None], shift_px=shift_px, only=only)
        z = z[0]
        scores = {name: float(z[i]) for i, name in enumerate(self.names) if np.isfinite(z[i])}
        polarity = self._disc_polarity(gradients, X_CT, shift_px) if discs else math.nan
        return Support(scores, polarity)

    def contour_scores(
        self,
        gradients: GradientImage,
        R_CT: np.ndarray,
        p_CT: np.ndarray,
        *,
        shift_px: float = 0.0,
        only: frozenset[str] | None = None,
        frame_noise: bool = False,
    ) -> np.ndarray:
        """Edge support z-score (k, len(names)) of every contour (or of those named in
        ``only``) at each of k poses (rotations ``R_CT`` (k,3,3), translations ``p_CT``
        (k,3)), NaN where a contour has fewer than 8 samples in view. All poses in one pass:
        a grid search scores a hundred poses of the same contours, and one pass over their
        samples costs a fraction of a hundred.

        Each z-score is measured in the spread of the derivative along the contour, where it
        lies; with ``frame_noise`` in no less than the frame's noise gives it. The local
        spread is lower on an edge's clipped black side than on the edge, so a pose that
        moves a contour half off its edge, into the dark, may outscore the pose on it
        (held-out random:119 at 2 m: an outline edge 2 px off scored 167 against 127); a
        search over poses asks for the frame's noise."""
        margin = 4.0 + shift_px
        count = len(self.names)
        if only is None:
            points_T, across_T, contour_of = self.points_T, self.across_T, self.contour_of
        else:
            chosen = np.isin(self.contour_of, [i for i, n in enumerate(self.names) if n in only])
            points_T = self.points_T[chosen]
            across_T = self.across_T[chosen]
            contour_of = self.contour_of[chosen]
        k = len(R_CT)
        R_CT = np.ascontiguousarray(R_CT, dtype=float).reshape(k, 3, 3)
        p_CT = np.ascontiguousarray(p_CT, dtype=float).reshape(k, 3)
        if self._foot is not None:
            on_foot = contour_of == self.names.index("ring_foot")
            camera_T = -np.einsum("kji,kj->ki", R_CT, p_CT)
            foot_seen = np.ones((k, len(points_T)), bool)
            foot_seen[:, on_foot] = self._foot_unoccluded(camera_T, points_T[on_foot])
        else:
            foot_seen = np.ones((k, len(points_T)), bool)
        camera = self.camera
        points, n, group, counts, length = _contour_samples(
            np.ascontiguousarray(points_T, dtype=float),
            np.ascontiguousarray(across_T, dtype=float),
            np.ascontiguousarray(contour_of, dtype=np.int64),
            count,
            R_CT,
            p_CT,
            foot_seen,
            np.array(camera.K, dtype=float),
            *camera.lens,
            float(margin),
            1.02 * self._field_radius,
            camera.width,
            camera.height,
        )
        groups = k * count
        z = np.full(groups, np.nan)
        if not np.any(counts >= _MIN_SAMPLES):
            return z.reshape(k, count)
        shifts = [(0.0, 0.0)]
        if shift_px > 0:
            # A grid of image offsets 1.5 px apart within ±shift_px.
            half = max(1, round(shift_px / 1.5))
            steps = np.linspace(-shift_px, shift_px, 2 * half + 1)
            shifts = [(dx, dy) for dx in steps for dy in steps]
        best = np.full(groups, -np.inf)
        tangent = np.column_stack([-n[:, 1], n[:, 0]])
        # Samples closer than the smoothing's correlation length (≈ 2σ) are not independent:
        # count the contour's image length in units of it.
        independent = np.clip(length / (2.0 * gradients.sigma_px), 1.0, np.maximum(counts, 1))
        safe = np.maximum(counts, 1)
        # The spread of |g·t| is never taken below what noise of ``NOISE_FLOOR`` would give it
        # (the spread of |N(0, s)| is √(1 − 2/π) s; under the reference study's noise it is a
        # third of what the noise gives, and does not bind). On a clean frame (a camera's shot
        # and read noise is a thirty-fifth of the study's low noise) the spread along a contour
        # lying on an edge is near zero, and the ratio then ranks poses by how uniform their
        # along-contour gradients are, not by how well they sit on the edges: a pose tilted 8°
        # outscored the truth by 490 z units, and the quarter-turn check chose a wrong turn.
        spread_floor = (
            HALF_NORMAL_SPREAD * GradientImage.noise_after(gradients.sigma_px, NOISE_FLOOR)[1]
        )
        if frame_noise:
            spread_floor = max(spread_floor, HALF_NORMAL_SPREAD * gradients.gradient_noise)
        for dx, dy in shifts:
            shifted = points + np.array([dx, dy])
            across = np.abs(gradients.directional(shifted, n))
            along = np.abs(gradients.directional(shifted, tangent))
            diff_sum, along_sq, along_sum = _group_sums(group, across, along, groups)
            spread = np.sqrt(np.maximum(along_sq / safe - (along_sum / safe) ** 2, 0))
            spread = np.maximum(spread, spread_floor)  # positive: noise_after floors it
            best = np.maximum(best, (diff_sum / safe) / (spread * np.sqrt(2.0 / independent)))
        seen = counts >= _MIN_SAMPLES
        z[seen] = best[seen]
        return z.reshape(k, count)

    def _foot_unoccluded(self, camera_T: np.ndarray, feet_T: np.ndarray) -> np.ndarray:
        """Which points (n,3) of the bore's foot the bore's own wall does not hide from cameras
        at ``camera_T`` (k,3), as a (k, n) mask.

        The ray from a foot point F up to the camera c stays inside the bore (radius r about
        its axis) up to the rim, a height h above the foot, when its horizontal part
        q(s) = F + s·(c − F), s = z / z_c, has |q(s)| ≤ r at s = h / z_c; |q(0)| = r, and |q|²
        is convex in s, so that end decides: 2 F·(c − F) + (h / z_c)·|c − F|² ≤ 0 (horizontal
        parts, about the axis; s at most 1, where the ray reaches a camera below the rim). Foot
        points on the camera's side of the bore are behind its wall."""
        foot = self._foot
        assert foot is not None
        n = foot.normal_T
        height = (camera_T - foot.center_T) @ n  # (k,)
        radial = feet_T - foot.center_T
        radial -= np.outer(radial @ n, n)
        toward = camera_T - foot.center_T
        toward = toward - np.outer(toward @ n, n)
        toward = toward[:, None, :] - radial[None]  # horizontal part of c − F, (k, n, 3)
        # (a camera below the rim, inside the bore, ends the ray before it: s ≤ 1)
        reach = 2.0 * np.einsum("nj,knj->kn", radial, toward)
        rim = np.minimum(self._bore_depth_m / np.maximum(height, 1e-9), 1.0)
        reach += rim[:, None] * np.einsum("knj,knj->kn", toward, toward)
        # A camera behind the face sees none of it.
        return (reach <= 1e-12) & (height > 1e-9)[:, None]

    def _disc_polarity(self, gradients: GradientImage, X_CT: Pose, shift_px: float) -> float:
        """z-score of Σ sign·(disc centre − ring around it) over the discs in view."""
        if len(self.disc_centres_T) == 0:
            return math.nan
        best = -math.inf
        for z in self._disc_responses(gradients, X_CT, np.arange(len(self.disc_signs)), shift_px):
            seen = z[np.isfinite(z)]
            if len(seen) >= 2:
                best = max(best, float(seen.sum() / math.sqrt(len(seen))))
        return best if math.isfinite(best) else math.nan

    def disc_responses(
        self, gradients: GradientImage, X_CT: Pose, discs: np.ndarray, *, shift_px: float = 0.0
    ) -> np.ndarray:
        """Each disc's (indices ``discs`` into the model's discs) polarity response at
        ``X_CT`` as a z-score (NaN out of view): sign·(centre − ring around it) over its noise,
        at the common image offset within ±``shift_px`` that makes their sum largest."""
        best, best_sum = np.full(len(discs), np.nan), -math.inf
        for z in self._disc_responses(gradients, X_CT, np.asarray(discs, int), shift_px):
            total = float(np.nansum(z))
            if total > best_sum:
                best, best_sum = z, total
        return best

    def _disc_responses(self, gradients, X_CT: Pose, discs: np.ndarray, shift_px: float):
        """Per-disc z-scores (NaN out of view) at each trial offset within ±``shift_px``."""
        centres = self.disc_centres_T[discs]
        uv, visible = self._project(X_CT.apply(centres), 6.0 + shift_px)
        if not np.any(visible):
            return [np.full(len(discs), np.nan)]
        depth = X_CT.apply(centres[visible])[:, 2]
        radius_px = np.maximum(
            self.disc_radius_m[discs][visible] * self.camera.K[0, 0] / depth, 0.5
        )
        signs = self.disc_signs[discs][visible]
        angles = np.linspace(0.0, 2 * np.pi, 8, endpoint=False)
        ring_offsets = (2.2 * radius_px + 1.0)[:, None, None] * np.stack(
            [np.cos(angles), np.sin(angles)], axis=1
        )
        shifts = [(0.0, 0.0)]
        if shift_px > 0:
            steps = (-0.5 * shift_px, 0.0, 0.5 * shift_px)
            shifts = [(dx, dy) for dx in steps for dy in steps]
        out = []
        for dx, dy in shifts:
            centre = uv[visible] + np.array([dx, dy])
            inner = gradients.sample(centre)
            ring = gradients.sample((centre[:, None, :] + ring_offsets).reshape(-1, 2))
            difference = signs * (inner - ring.reshape(-1, 8).mean(axis=1))
            # Noise of one smoothed sample minus the mean of eight: σ_s·√(1 + 1/8).
            z = np.full(len(discs), np.nan)
            z[visible] = difference / (gradients.noise_sigma * math.sqrt(1.125))
            out.append(z)
        return out


@compiled
def _contour_samples(
    points_T,
    across_T,
    contour_of,
    count,
    R_CT,
    p_CT,
    foot_seen,
    K,
    d,
    M,
    tilted,
    distorted,
    margin_px,
    field_limit,
    width,
    height,
):
    """The contours' samples seen at each of k poses, as ``ModelSupport.contour_scores``
    reads them: their pixels (V,2) and unit image normals (V,2), each sample's group (pose ×
    count + contour; the samples of a group contiguous and in order), the samples per group
    and each group's image length (px, summed over neighbouring samples). A sample is seen
    when it and a point 2 mm (× depth) across the contour from it are in front (z > 1 µm),
    within the field (normalised radius ≤ ``field_limit``) and imaged ``margin_px`` (the
    point across: 0) inside the borders, where the bore's wall does not hide it
    (``foot_seen``). Compiled: a grid search scores a hundred poses, and tracking three a
    frame, each a few dozen NumPy calls."""
    k, m = R_CT.shape[0], len(points_T)
    uv, normal = np.empty((k * m, 2)), np.empty((k * m, 2))
    group = np.empty(k * m, np.int64)
    counts, length = np.zeros(k * count, np.int64), np.zeros(k * count)
    seen = 0
    for j in range(k):
        R, p = R_CT[j], p_CT[j]
        last_group, last_u, last_v = -1, 0.0, 0.0
        for i in range(m):
            if not foot_seen[j, i]:
                continue
            X, Y, Z = rigid_transform(R, p, points_T[i, 0], points_T[i, 1], points_T[i, 2])
            ok, u, v = pixel_in_view(
                X, Y, Z, K, d, M, tilted, distorted, _MIN_DEPTH_M, field_limit,
                margin_px, width - 1 - margin_px, margin_px, height - 1 - margin_px,
            )  # fmt: skip
            if not ok:
                continue
            step = 0.002 * max(abs(Z), 1e-3)
            X, Y, Z = rigid_transform(
                R,
                p,
                points_T[i, 0] + step * across_T[i, 0],
                points_T[i, 1] + step * across_T[i, 1],
                points_T[i, 2] + step * across_T[i, 2],
            )
            ok, au, av = pixel_in_view(
                X, Y, Z, K, d, M, tilted, distorted, _MIN_DEPTH_M, field_limit,
                0.0, width - 1.0, 0.0, height - 1.0,
            )  # fmt: skip
            nu, nv = au - u, av - v
            norm = math.sqrt(nu * nu + nv * nv)
            if not ok or not norm > 1e-9:
                continue
            g = j * count + contour_of[i]
            uv[seen, 0], uv[seen, 1] = u, v
            normal[seen, 0], normal[seen, 1] = nu / norm, nv / norm
            group[seen] = g
            counts[g] += 1
            if g == last_group:
                length[g] += math.sqrt((u - last_u) ** 2 + (v - last_v) ** 2)
            last_group, last_u, last_v = g, u, v
            seen += 1
    return uv[:seen].copy(), normal[:seen].copy(), group[:seen].copy(), counts, length


@compiled
def _group_sums(group, across, along, groups):
    """Per group: Σ(across − along), Σ along² and Σ along."""
    diff_sum, along_sq, along_sum = np.zeros(groups), np.zeros(groups), np.zeros(groups)
    for i in range(len(group)):
        g = group[i]
        diff_sum[g] += across[i] - along[i]
        along_sq[g] += along[i] * along[i]
        along_sum[g] += along[i]
    return diff_sum, along_sq, along_sum
