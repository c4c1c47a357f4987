"""Image preparation shared by the estimators: a usable grey image or the reason there is none,
the image noise level, and smoothing matched to it.

Pure functions of the pixels; nothing here knows about the target.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from estimators.frame import Frame, frame_problem

#: Smallest image side an estimator will look at (px).
MIN_IMAGE_SIDE_PX = 24
#: Below this spread of intensities (on [0, 1]) there is nothing to see.
MIN_INTENSITY_SPREAD = 0.03


@dataclass(frozen=True, slots=True, eq=False)
class GrayImage:
    """A frame as float32 intensities on [0, 1] (HxW) with its estimated noise level.

    ``noise_sigma`` is the standard deviation of the pixel noise (same units), from
    ``estimate_noise_sigma``.
    """

    pixels: np.ndarray
    noise_sigma: float

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
    return GrayImage(pixels, estimate_noise_sigma(pixels))


def estimate_noise_sigma(pixels: np.ndarray) -> float:
    """Standard deviation of additive white noise in an image, from its Laplacian.

    J. Immerkær, "Fast noise variance estimation", Computer Vision and Image Understanding
    64(2), 1996: the mask [[1,-2,1],[-2,4,-2],[1,-2,1]] cancels smooth image structure and
    σ = √(π/2) · mean|I ∗ M| / 6. Two guards: pixels where the image is nearly black or white
    are left out (clipping hides noise there), and so are the strongest 10 % of responses (edges
    inflate them); the truncated mean of |N(0, s)| below its 90th percentile is 0.8238 of the
    full mean, which the estimate divides out.
    """
    mask = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], dtype=np.float32)
    # Every third pixel each way is plenty for a global statistic.
    response = np.abs(cv2.filter2D(pixels, cv2.CV_32F, mask))[1:-1:3, 1:-1:3]
    level = cv2.blur(pixels, (5, 5))[1:-1:3, 1:-1:3]
    usable = response[(level > 0.2) & (level < 0.8)]
    if usable.size < 100:
        usable = response.ravel()
    trimmed = usable[usable <= np.percentile(usable, 90.0)]
    return float(math.sqrt(math.pi / 2.0) * trimmed.mean() / 6.0 / 0.8238)


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
