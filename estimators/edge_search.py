"""Sub-pixel edge points: a smoothed gradient field and 1-D searches along curve normals.

The image is smoothed with a Gaussian whose scale is matched to the noise, differentiated
(Sobel), and searched along the normals of a predicted curve for the strongest gradient of the
expected polarity; the maximum is located to sub-pixel precision by a parabola through the three
samples around it (the classic gradient-maximum edge localisation, as in Canny's detector and
"moving edges" trackers — Bouthemy 1989; Drummond & Cipolla 2002).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from estimators.geometry import as_points

#: Immerkær's noise-estimation kernel (a Laplacian difference that cancels planes and edges
#: to first order): "Fast noise variance estimation", CVIU 64(2), 1996.
_NOISE_KERNEL = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], dtype=np.float32)


def to_gray_float(image: np.ndarray) -> np.ndarray:
    """A float32 mono image in [0, 1] from uint8/float mono or BGR input."""
    array = np.asarray(image)
    if array.ndim == 3:
        if array.shape[2] == 1:
            array = array[:, :, 0]
        else:
            array = (
                cv2.cvtColor(array[:, :, :3], cv2.COLOR_BGR2GRAY)
                if array.dtype == np.uint8
                else (
                    array[:, :, :3].astype(np.float32) @ np.array([0.114, 0.587, 0.299], np.float32)
                )
            )
    if array.dtype == np.uint8:
        return array.astype(np.float32) * np.float32(1.0 / 255.0)
    return np.asarray(array, dtype=np.float32)


def shown_noise_sigma(gray: np.ndarray) -> float:
    """Spread of the noise as the pixels of a mono image in [0, 1] show it, by Immerkær's
    method (σ = √(π/2) · mean|I ∗ N| / 6), robust to edges and shading — the scale an edge
    search's SNR thresholds are measured against.

    Pixels near black or white are left out: there the noise was clipped by the sensor, and a
    dark background would otherwise make the noise look several times smaller than it is on
    the target. Clipping still shrinks what the pixels kept show (20 % at σ = 0.32): the noise
    σ itself, for likelihoods of clipped pixels, is ``estimators.imaging.estimate_noise_sigma``."""
    if gray.shape[0] < 6 or gray.shape[1] < 6:
        return 0.0
    # Every fourth row is enough for a stable estimate (tens of thousands of pixels).
    rows = np.ascontiguousarray(gray[::4])
    response = np.abs(cv2.filter2D(rows, cv2.CV_32F, _NOISE_KERNEL)[1:-1, 1:-1])
    level = cv2.blur(rows, (5, 5))[1:-1, 1:-1]
    unclipped = (level > 0.15) & (level < 0.85)
    if unclipped.sum() >= 0.05 * unclipped.size:
        response = response[unclipped]
    return float(np.sqrt(np.pi / 2.0) * response.mean() / 6.0)


def gradient_noise_gain(sigma_px: float) -> float:
    """Std of one component of ``smoothed_gradient`` for unit-variance white noise (measured
    by pushing an impulse through the same filters: the gain is the kernel's L2 norm)."""
    half = int(np.ceil(4.0 * max(sigma_px, 0.5))) + 3
    impulse = np.zeros((2 * half + 1, 2 * half + 1), np.float32)
    impulse[half, half] = 1.0
    gx, _ = _gradient(impulse, sigma_px)
    return float(np.sqrt((gx.astype(np.float64) ** 2).sum()))


def _gradient(gray: np.ndarray, sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    smoothed = cv2.GaussianBlur(gray, (0, 0), sigma_px) if sigma_px > 0 else gray
    gx = cv2.Sobel(smoothed, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(smoothed, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    return gx, gy


@dataclass(frozen=True, slots=True, eq=False)
class GradientField:
    """Smoothed gradient (intensity per px) of the region [x0, x0+w) × [y0, y0+h) of an image.

    ``noise`` is the std of one gradient component caused by the image noise; an edge's
    strength divided by it is its signal-to-noise ratio.
    """

    gxy: np.ndarray  # float32 (h, w, 2): d/dx, d/dy
    x0: int
    y0: int
    sigma_px: float
    noise: float

    @property
    def shape(self) -> tuple[int, int]:
        return self.gxy.shape[0], self.gxy.shape[1]


def smoothed_gradient(
    gray: np.ndarray,
    sigma_px: float,
    noise_sigma: float,
    roi: tuple[int, int, int, int] | None = None,
) -> GradientField:
    """Gradient of ``gray`` (float32) smoothed at ``sigma_px``, over ``roi`` = (x0, y0, x1, y1)
    (clipped to the image; the whole image when None). A margin of 3σ is filtered with the
    region so its border is not degraded."""
    h, w = gray.shape
    if roi is None:
        x0, y0, x1, y1 = 0, 0, w, h
    else:
        x0, y0, x1, y1 = (int(v) for v in roi)
    margin = int(np.ceil(3.0 * sigma_px)) + 2
    x0c, y0c = max(0, x0 - margin), max(0, y0 - margin)
    x1c, y1c = min(w, x1 + margin), min(h, y1 + margin)
    if x1c - x0c < 3 or y1c - y0c < 3:
        return GradientField(np.zeros((1, 1, 2), np.float32), 0, 0, sigma_px, 1.0)
    gx, gy = _gradient(np.ascontiguousarray(gray[y0c:y1c, x0c:x1c]), sigma_px)
    noise = max(noise_sigma, 1e-4) * gradient_noise_gain(sigma_px)
    return GradientField(cv2.merge([gx, gy]), x0c, y0c, sigma_px, noise)


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
