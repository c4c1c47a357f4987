"""Sub-pixel edge points: 1-D searches along curve normals in a smoothed gradient field.

The field (``imaging.ImageStack.gradient_field``) is the image smoothed with a Gaussian whose
scale is matched to the noise and differentiated (Sobel); it is searched along the normals of a
predicted curve for the strongest gradient of the expected polarity; the maximum is located to sub-pixel precision by a parabola through the three
samples around it (the classic gradient-maximum edge localisation, as in Canny's detector and
"moving edges" trackers — Bouthemy 1989; Drummond & Cipolla 2002).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from estimators.geometry import as_points
from estimators.imaging import GradientField


@dataclass(frozen=True, slots=True, eq=False)
class EdgeHits:
    """Result of searching along N normals: ``found`` (N,) bool; ``uv`` (N,2) sub-pixel edge
    positions (NaN where not found); ``offset_px`` (N,) position along the normal; ``snr`` (N,)
    edge strength over the gradient noise."""

    uv: np.ndarray
    found: np.ndarray
    offset_px: np.ndarray
    snr: np.ndarray

    @property
    def count(self) -> int:
        return int(self.found.sum())


def search_edges(
    field: GradientField,
    points_uv: np.ndarray,
    normals: np.ndarray,
    polarity: int,
    half_width_px: float,
    *,
    step_px: float = 0.5,
    min_snr: float = 3.0,
    max_angle_deg: float = 50.0,
    prior_sigma_px: float | None = None,
) -> EdgeHits:
    """Strongest edge of the given polarity along each normal, within ±``half_width_px``.

    ``polarity`` +1 looks for intensity increasing along the normal, −1 decreasing. A hit needs
    SNR ≥ ``min_snr``, a gradient within ``max_angle_deg`` of the normal, and a maximum strictly
    inside the search window (a maximum at the window's end is an edge beyond it). With
    ``prior_sigma_px`` the choice among several edges favours those near the prediction (the
    strength is weighted by a Gaussian of the offset), so a strong neighbour — a bolt hole
    next to the ring's edge — does not win over the expected edge.
    """
    points = as_points(points_uv, 2, "points_uv")
    normals = as_points(normals, 2, "normals")
    n = len(points)
    empty = EdgeHits(np.full((n, 2), np.nan), np.zeros(n, bool), np.full(n, np.nan), np.zeros(n))
    if n == 0 or polarity not in (1, -1):
        return empty
    offsets = np.arange(-half_width_px, half_width_px + 1e-9, step_px, dtype=np.float64)
    if len(offsets) < 3:
        return empty
    px = points[:, 0:1] + offsets[None, :] * normals[:, 0:1] - field.x0
    py = points[:, 1:2] + offsets[None, :] * normals[:, 1:2] - field.y0
    h, w = field.shape
    inside = (px.min(axis=1) >= 0) & (py.min(axis=1) >= 0)
    inside &= (px.max(axis=1) <= w - 1) & (py.max(axis=1) <= h - 1)
    if not inside.any():
        return empty
    samples = cv2.remap(
        field.gxy,
        px.astype(np.float32),
        py.astype(np.float32),
        cv2.INTER_CUBIC,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )  # (n, L, 2)
    along = samples[:, :, 0] * normals[:, 0:1] + samples[:, :, 1] * normals[:, 1:2]
    score = polarity * along
    rows = np.arange(n)
    if prior_sigma_px is not None:
        weight = np.exp(-0.5 * (offsets / prior_sigma_px) ** 2)
        best = np.argmax(np.maximum(score, 0.0) * weight[None, :], axis=1)
        # The weighted maximum sits on the flank of the edge's peak, nearer the prediction;
        # climb to the peak itself.
        last = len(offsets) - 1
        for _ in range(len(offsets)):
            up = np.minimum(best + 1, last)
            down = np.maximum(best - 1, 0)
            step = np.where(
                score[rows, up] > score[rows, best],
                1,
                np.where(score[rows, down] > score[rows, best], -1, 0),
            )
            if not np.any(step):
                break
            best = best + step
    else:
        best = np.argmax(score, axis=1)
    peak = score[rows, best]
    interior = (best > 0) & (best < len(offsets) - 1)
    b = np.clip(best, 1, len(offsets) - 2)
    s_minus, s0, s_plus = score[rows, b - 1], score[rows, b], score[rows, b + 1]
    # The peak of a Gaussian-smoothed step's derivative is a Gaussian: a parabola through the
    # logarithms of the three samples around it locates it exactly (Fisher & Naidu's Gaussian
    # peak interpolation); samples that are not all positive fall back to a plain parabola.
    positive = (s_minus > 0) & (s0 > 0) & (s_plus > 0)
    l_minus = np.log(np.where(positive, s_minus, 1.0))
    l0 = np.log(np.where(positive, s0, 1.0))
    l_plus = np.log(np.where(positive, s_plus, 1.0))
    v_minus = np.where(positive, l_minus, s_minus)
    v0 = np.where(positive, l0, s0)
    v_plus = np.where(positive, l_plus, s_plus)
    curvature = v_minus - 2.0 * v0 + v_plus
    delta = np.where(
        curvature < 0, 0.5 * (v_minus - v_plus) / np.where(curvature < 0, curvature, -1), 0.0
    )
    delta = np.clip(delta, -0.5, 0.5)
    offset = offsets[b] + delta * step_px
    magnitude = np.hypot(samples[rows, best, 0], samples[rows, best, 1])
    aligned = peak >= np.cos(np.radians(max_angle_deg)) * magnitude
    snr = peak / field.noise
    local_maximum = (s0 >= s_minus) & (s0 >= s_plus)
    found = inside & interior & local_maximum & aligned & (snr >= min_snr)
    uv = points + offset[:, None] * normals
    uv[~found] = np.nan
    offset[~found] = np.nan
    return EdgeHits(uv, found, offset, np.where(found, snr, 0.0))
