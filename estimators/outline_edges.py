"""The face outline's visible edges: the straight silhouette of the face the panel sits on
(``TargetModel.outline_corners_T``) against what lies behind it, to sub-pixel accuracy.

The outline is several times larger than the panel, so its edges fix the target's tilt far
better than the panel's (hil.evaluation.feature_bounds: 0.02–0.10° against 0.8–6° at 1.2–3 m). It is
also often only partly in view: at close range the face is larger than the image, so only the
stretches of its edges inside the image are used, and at the stand-off (0.5 m) none may be.

Labeling is by prediction: the edges are projected with a pose measured on the panel in the
same frame, and each is searched within the distance its prediction can be off — four
standard deviations of the edge's image offset under that pose's covariance (a pose from the
panel alone may be degrees off in tilt, which moves the far-away outline by pixels). The
search is coarse then fine: step-edge points within the window give a robust line, and the
strips are then moved onto that line and fitted again in a narrow band
(``estimators.panel_edges``). The face may be brighter or darker than its background; all
edges found must agree on which.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from estimators.edge_fit import coarse_edge_offsets
from estimators.frame import CameraInfo
from estimators.geometry import Pose
from estimators.least_squares import median
from estimators.panel_edges import (
    EdgeStrips,
    FittedEdge,
    edge_observations,
    fit_edge,
    shift_strips,
    strips_along_edge,
)
from estimators.planar_pose import EdgeObservations, projection_jacobian
from estimators.target import TargetModel


def outline_edge_ends(target: TargetModel) -> np.ndarray | None:
    """The outline's four edges as (4,2,3) end points in T (edge i from corner i to i+1), or
    None when the model has no outline."""
    corners = target.outline_corners_T
    if corners is None:
        return None
    return np.stack([corners, np.roll(corners, -1, axis=0)], axis=1)


@dataclass(frozen=True, slots=True, eq=False)
class OutlineEdges:
    """The outline's four edges as far as they were found: ``edges[i]`` is model edge i's fit
    (None when it is out of view or was not found), ``polarity`` +1 when the face is brighter
    than its background, −1 when darker (0 when no edge was found)."""

    edges: tuple[FittedEdge | None, ...]
    polarity: float
    expected: int = 0  # strips predicted in view (the most points there could be)

    @property
    def found(self) -> int:
        return sum(e is not None and e.found for e in self.edges)

    @property
    def points(self) -> int:
        """Edge points used (inliers of the found edges)."""
        return sum(len(e.used) for e in self.edges if e is not None and e.found)

    def without(self, index: int) -> OutlineEdges:
        edges = list(self.edges)
        edges[index] = None
        return OutlineEdges(tuple(edges), self.polarity, self.expected)

    def image_points(self) -> np.ndarray:
        parts = [e.points.uv[e.used] for e in self.edges if e is not None and e.found]
        return np.concatenate(parts) if parts else np.zeros((0, 2))


def predicted_offset_sigma_px(
    X_CT: Pose, covariance: np.ndarray, strips: EdgeStrips, camera: CameraInfo
) -> float:
    """Largest standard deviation (px) of a predicted edge's image position along its normals,
    over its strips, under the pose covariance (first order, ideal pixels)."""
    if strips.points_T is None:
        raise ValueError("predicted_offset_sigma_px needs strips predicted from a pose")
    _, J, _ = projection_jacobian(X_CT, strips.points_T, camera.K)
    across = np.einsum("ni,nij->nj", strips.normals, J)  # (K,6): ∂(offset)/∂δ
    variance = np.einsum("nj,jk,nk->n", across, covariance, across)
    return float(math.sqrt(max(float(np.max(variance)), 0.0)))


#: Parts of an edge closer than this (px) to the image border are not used: the step fits
#: need a few pixels on both of its sides (bands running off the image are cut to it).
BORDER_PX = 3.0

#: Search windows (px) up to this go straight to the step fits, without the coarse search.
_NARROW_PX = 3.0


def _coarse_offsets(
    pixels: np.ndarray,
    strips: EdgeStrips,
    search_px: float,
    keep: Callable[[np.ndarray], np.ndarray] | None,
    min_strength: float = 3.0,
) -> np.ndarray | None:
    """Each strip's offset (K,) along its normal to the edge: the pieces' coarse offsets
    (``estimators.edge_fit.coarse_edge_offsets``; a prediction off in tilt is off by different
    amounts along the edge) joined by a robust straight line against the strips' places — in
    image pixels, so a curved (distorted) edge is followed too. None when fewer than two
    pieces show a step of z ≥ ``min_strength``."""
    coarse = coarse_edge_offsets(
        pixels, strips.centers_uv, strips.normals, strips.half_length_px, search_px, keep=keep
    )
    if coarse is None:
        return None
    strong = coarse.strength >= min_strength
    if strong.sum() < 2:
        return None
    x, y = coarse.place[strong], coarse.offset[strong]
    w = coarse.strength[strong] ** 2
    # Tukey-like reweighting: pieces on something else must not pull the line.
    fit = np.ones(len(x), bool)
    coefficients = np.array([median(y), 0.0])
    for _ in range(5):
        if fit.sum() < 2:
            return None
        if fit.sum() == 2 or np.ptp(x[fit]) == 0:
            coefficients = np.array([float(np.average(y[fit], weights=w[fit])), 0.0])
        else:
            coefficients = _weighted_line(x[fit], y[fit], w[fit])
        residual = y - coefficients[0] - coefficients[1] * x
        fit = np.abs(residual) <= max(1.5, 2.5 * 1.4826 * median(np.abs(residual)))
    return coefficients[0] + coefficients[1] * np.arange(len(strips.centers_uv), dtype=float)


def _weighted_line(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """[intercept, slope] of the line minimising Σ w (y − intercept − slope·x)², by the normal
    equations about the weighted centroid (x must not be constant)."""
    total = w.sum()
    x_mean, y_mean = (w @ x) / total, (w @ y) / total
    dx = x - x_mean
    slope = (w * dx) @ (y - y_mean) / ((w * dx) @ dx)
    return np.array([y_mean - slope * x_mean, slope])


def fit_outline_edges(
    pixels: np.ndarray,
    X_CT: Pose,
    covariance: np.ndarray,
    camera: CameraInfo,
    target: TargetModel,
    *,
    strip_px: float = 6.0,
    band_px: float = 3.0,
    min_contrast_snr: float = 3.5,
    min_length_px: float = 30.0,
    max_search_px: float = 20.0,
    max_strips: int = 20,
    keep: Callable[[np.ndarray], np.ndarray] | None = None,
    noise_sigma: float = 0.0,
) -> OutlineEdges:
    """Find the visible outline edges near their projection under ``X_CT`` (covariance 6×6
    over [δθ, δp]; see module docstring). Edges with less than ``min_length_px`` in view are
    not searched; the search window is 4σ of the prediction + 2 px, at most ``max_search_px``.
    At most ``max_strips`` strips per edge, spread along it: the outline's edges carry far more
    information than the pose needs (their common errors, not the noise, limit it)."""
    ends = outline_edge_ends(target)
    if ends is None:
        return OutlineEdges((None, None, None, None), 0.0, 0)
    inside_T = target.outline_corners_T.mean(axis=0)
    border = BORDER_PX
    fitted: list[FittedEdge | None] = []
    expected = 0
    for a, b in ends:
        strips = strips_along_edge(
            X_CT,
            camera,
            a,
            b,
            inside_T,
            strip_px,
            border_px=border,
            min_length_px=min_length_px,
            max_strips=max_strips,
        )
        if strips is None:
            fitted.append(None)
            continue
        expected += len(strips.centers_uv)
        sigma = predicted_offset_sigma_px(X_CT, covariance, strips, camera)
        search = float(np.clip(4.0 * sigma + 2.0, 2.0, max_search_px))
        settings = dict(
            half_width_px=band_px,
            min_contrast_snr=min_contrast_snr,
            polarity=0.0,
            keep=keep,
            noise_sigma=noise_sigma,
        )
        if search <= _NARROW_PX:
            # The prediction is good to a pixel or two: the step fits search that far alone.
            fine = fit_edge(pixels, strips, camera, search_px=search, **settings)
            fitted.append(fine if fine.found else None)
            continue
        shift = _coarse_offsets(pixels, strips, search, keep)
        if shift is None:
            fitted.append(None)
            continue
        fine = fit_edge(pixels, shift_strips(strips, shift), camera, search_px=1.5, **settings)
        fitted.append(fine if fine.found else None)
    signs = [math.copysign(1.0, e.points.contrast) if e is not None else 0.0 for e in fitted]
    weight = sum(
        s * abs(e.points.contrast_snr) for s, e in zip(signs, fitted, strict=True) if e is not None
    )
    polarity = math.copysign(1.0, weight) if weight != 0 else 0.0
    # A face is brighter (or darker) than its background all round: an edge of the other sign
    # is something else.
    agreed = tuple(
        e if e is not None and s == polarity else None for s, e in zip(signs, fitted, strict=True)
    )
    return OutlineEdges(agreed, polarity, expected)


def outline_observations(target: TargetModel, outline: OutlineEdges) -> EdgeObservations | None:
    """The found outline edges' points as pose observations (None when none was found)."""
    ends = outline_edge_ends(target)
    if ends is None or outline.found == 0:
        return None
    return edge_observations(ends, outline.edges)
