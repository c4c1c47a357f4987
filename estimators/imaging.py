"""Image preparation shared by the estimators: a usable grey image or the reason there is none,
the image noise level, smoothing matched to it, and the moments of noise clipped by the sensor
at black and white.

Pure functions of the pixels; nothing here knows about the target.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.special import ndtr

from estimators.frame import Frame, frame_problem

#: Smallest image side an estimator will look at (px).
MIN_IMAGE_SIDE_PX = 24
#: Below this spread of intensities (on [0, 1]) there is nothing to see.
MIN_INTENSITY_SPREAD = 0.03


@dataclass(frozen=True, slots=True, eq=False)
class GrayImage:
    """A frame as float32 intensities on [0, 1] (HxW) with its estimated noise level.

    ``noise_sigma`` is the standard deviation of the pixel noise as the pixels show it (same
    units; what edge strengths and smoothing are judged against), ``clip_sigma`` that of the
    noise before the sensor clipped it (for likelihoods of clipped pixels); both from
    ``noise_levels``.
    """

    pixels: np.ndarray
    noise_sigma: float
    clip_sigma: float = 0.0

    @property
    def shape(self) -> tuple[int, int]:
        return self.pixels.shape  # type: ignore[return-value]


def gray_image(frame: Frame) -> GrayImage | str:
    """The frame as a ``GrayImage``, or a one-line reason why it cannot be used.

    uint8 images are scaled by 1/255; float images are taken as intensities on [0, 1] (the
    renderer's convention); BGR images are converted with OpenCV's luma weights.
    """
    problem = frame_problem(frame)
    if problem is not None:
        return problem
    image = frame.image
    if min(image.shape[:2]) < MIN_IMAGE_SIDE_PX:
        return f"image {image.shape[1]}x{image.shape[0]} is too small (< {MIN_IMAGE_SIDE_PX} px)"
    if image.dtype == np.uint8:
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        pixels = gray.astype(np.float32) * np.float32(1.0 / 255.0)
    else:
        pixels = np.asarray(image, dtype=np.float32)
        if pixels.ndim == 3:
            pixels = cv2.cvtColor(pixels, cv2.COLOR_BGR2GRAY)
        pixels = np.clip(pixels, 0.0, 1.0)
    low, high = np.percentile(cv2.blur(pixels, (5, 5))[::4, ::4], [1.0, 99.0])
    if high - low < MIN_INTENSITY_SPREAD:
        level = "black" if high < 0.1 else "saturated" if low > 0.9 else "uniform"
        return f"image has no contrast ({level}: 1–99 % intensities {low:.2f}–{high:.2f})"
    shown, sigma = noise_levels(pixels)
    return GrayImage(pixels, shown, sigma)


_SQRT_2PI = math.sqrt(2.0 * math.pi)


def clipped_moments(
    intensity: np.ndarray, sigma: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean, variance and ∂mean/∂intensity of clip(I + n, 0, 1) for n ~ N(0, σ²) — what a
    sensor that clips at black and white shows of intensity I (the derivative is the chance
    that the pixel is not clipped). σ = 0: I, 0 and 1."""
    intensity = np.asarray(intensity, dtype=float)
    if sigma <= 0:
        return intensity, np.zeros_like(intensity), np.ones_like(intensity)
    alpha = -intensity / sigma
    beta = (1.0 - intensity) / sigma
    below, above = ndtr(alpha), ndtr(beta)
    pdf_a = np.exp(-0.5 * alpha * alpha) / _SQRT_2PI
    pdf_b = np.exp(-0.5 * beta * beta) / _SQRT_2PI
    inside = above - below
    mean = intensity * inside + sigma * (pdf_a - pdf_b) + (1.0 - above)
    second = (
        intensity**2 * inside
        + 2.0 * intensity * sigma * (pdf_a - pdf_b)
        + sigma**2 * (inside + alpha * pdf_a - beta * pdf_b)
        + (1.0 - above)
    )
    return mean, np.maximum(second - mean * mean, 0.0), inside


#: Pixels this close to 0 or 1 are taken as clipped (an 8-bit sensor's 0 and 255).
CLIP_TOLERANCE = 0.5 / 255.0


def clipped_likelihood_terms(
    values: np.ndarray, intensity: np.ndarray, sigma: float
) -> tuple[np.ndarray, np.ndarray]:
    """Score ∂ℓ/∂I and information −∂²ℓ/∂I² of each pixel's log-likelihood ℓ given its
    intensity I, under Gaussian noise σ clipped at black and white (a Tobit model: a clipped
    pixel only says the intensity plus noise fell beyond the clip). The maximum-likelihood fit
    of a model of I is unbiased where least squares on the clipped values is not. σ = 0: the
    least-squares terms (v − I, 1)."""
    values = np.asarray(values, dtype=float)
    intensity = np.asarray(intensity, dtype=float)
    if sigma <= 0:
        return values - intensity, np.ones_like(intensity)
    score = (values - intensity) / sigma**2
    info = np.full_like(intensity, 1.0 / sigma**2)
    # ℓ = log Φ(a) with a = −I/σ below black, (I − 1)/σ above white: ∂ℓ/∂I = ∓λ/σ and
    # −∂²ℓ/∂I² = λ(λ + a)/σ², λ = φ(a)/Φ(a).
    for sign, clipped, alpha in (
        (-1.0, values <= CLIP_TOLERANCE, -intensity / sigma),
        (1.0, values >= 1.0 - CLIP_TOLERANCE, (intensity - 1.0) / sigma),
    ):
        if not np.any(clipped):
            continue
        a = alpha[clipped]
        ratio = np.exp(-0.5 * a * a) / _SQRT_2PI / np.maximum(ndtr(a), 1e-300)
        score[clipped] = sign * ratio / sigma
        info[clipped] = ratio * (ratio + a) / sigma**2
    return score, info


def estimate_noise_sigma(pixels: np.ndarray) -> float:
    """Standard deviation of the additive white noise of an image before the sensor clipped
    it (``noise_levels``)."""
    return noise_levels(pixels)[1]


def noise_levels(pixels: np.ndarray) -> tuple[float, float]:
    """Standard deviation of the additive white noise of an image as its pixels show it, and
    before the sensor clipped it, from its Laplacian.

    J. Immerkær, "Fast noise variance estimation", Computer Vision and Image Understanding
    64(2), 1996: the mask [[1,-2,1],[-2,4,-2],[1,-2,1]] cancels smooth image structure and
    σ = √(π/2) · mean|I ∗ M| / 6. Guards: pixels where the image is nearly black or white are
    left out, and so are the strongest 10 % of responses (edges inflate them); the truncated
    mean of |N(0, s)| below its 90th percentile is 0.8238 of the full mean, which the estimate
    divides out. Clipping still hides some of the noise of the pixels kept (at σ = 0.32, 12 %
    of a 0.37 grey is clipped): the noise σ is the one whose clipped variance, averaged over
    those pixels' levels (``clipped_moments``), gives what was measured.
    """
    mask = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], dtype=np.float32)
    if min(pixels.shape[:2]) < 6:
        return 0.0, 0.0
    # Every third pixel each way is plenty for a global statistic.
    response = np.abs(cv2.filter2D(pixels, cv2.CV_32F, mask))[1:-1:3, 1:-1:3]
    level = cv2.blur(pixels, (5, 5))[1:-1:3, 1:-1:3]
    chosen = (level > 0.2) & (level < 0.8)
    if chosen.sum() < 100:
        chosen = np.ones_like(chosen)
    usable, levels = response[chosen], level[chosen]
    kept = usable <= np.percentile(usable, 90.0)
    measured = float(math.sqrt(math.pi / 2.0) * usable[kept].mean() / 6.0 / 0.8238)
    # The levels the noise sat on (a subsample is plenty), and the σ that explains the measured
    # one once clipped: a fixed point, reached in a few steps.
    levels = np.clip(levels[kept][:: max(1, int(kept.sum()) // 2000)], 0.0, 1.0)
    sigma = measured
    for _ in range(4):
        if sigma <= 0:
            break
        _, variance, _ = clipped_moments(levels, sigma)
        shown = math.sqrt(float(variance.mean())) / sigma
        sigma = measured / max(shown, 0.5)
    return float(measured), float(sigma)


def smoothing_sigma_px(noise_sigma: float, *, contrast: float = 0.3, base_px: float = 0.8) -> float:
    """Gaussian smoothing (px) that brings noise of ``noise_sigma`` down to about a fifth of an
    edge of ``contrast``: the noise of a σ_b-smoothed image is σ / (2√π σ_b), so σ_b grows with
    σ / contrast; clamped to [``base_px``, 3 px] so small features survive."""
    wanted = 5.0 * noise_sigma / (2.0 * math.sqrt(math.pi) * contrast)
    return float(min(3.0, max(base_px, wanted)))


def smooth(pixels: np.ndarray, sigma_px: float) -> np.ndarray:
    """Gaussian smoothing with a kernel of ±3σ."""
    size = 2 * math.ceil(3.0 * sigma_px) + 1
    return cv2.GaussianBlur(pixels, (size, size), sigma_px, borderType=cv2.BORDER_REPLICATE)
