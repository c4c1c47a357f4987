"""The one image stack of a frame, shared by every estimator: a usable grey image or the reason
there is none, the image noise level, smoothing matched to it, smoothed images and gradients
(computed once, lazily, and only over the regions asked for). The noise clipped by the sensor
at black and white is ``clipped_noise``'s.

``image_stack(frame)`` returns the same ``ImageStack`` to every estimator that asks for the
same frame, so gray conversion, noise estimate and smoothing happen once per frame however
many systems look at it. Nothing here knows about the target.
"""

from __future__ import annotations

import functools
import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from estimators.clipped_noise import clipped_moments
from estimators.frame import Frame, frame_problem

#: Smallest image side an estimator will look at (px).
MIN_IMAGE_SIDE_PX = 24
#: The least noise σ a frame is judged to have (intensity on [0, 1]). The estimators weigh
#: what they see in z units against margins set under the reference study's noise (σ 0.22 and
#: 0.32); the model — planes, circles and discs — leaves 0.01–0.02 of residual in its own fits
#: on a noise-free rendering, and more where it leaves parts out (a box's sides, a ring's
#: walls, shading). Against a camera's own noise (the sensor model's: 0.0065) those errors
#: become hundreds of z units and decide a pose's tilt and quarter turn; against this floor
#: they stay a few, and whatever the study's noise lets the systems see stays seen.
#: Below it the fits take least squares instead of the likelihood of clipped noise
#: (``ImageStack.clip_sigma``).
NOISE_FLOOR = 0.05
#: A region of a gradient field this large (fraction of the image) has the whole image filtered.
WHOLE_FIELD_FRACTION = 0.5
#: A region of a gradient field is filtered this much larger on each side (fraction of its
#: width and height): the stages of one frame ask for nearly the same region, a few pixels
#: larger or shifted as the pose moves, and each would otherwise filter it afresh.
FIELD_REGION_GROWTH = 0.15
#: Below this spread of intensities (on [0, 1]) there is nothing to see.
MIN_INTENSITY_SPREAD = 0.03

_REMAP_COLUMNS = 4096


@dataclass(frozen=True, slots=True, eq=False)
class GradientImage:
    """A smoothed image with the noise standard deviations left in it and in a directional
    derivative; derivatives are read on demand by central differences (``directional``)."""

    smoothed: np.ndarray
    noise_sigma: float
    gradient_noise: float
    sigma_px: float = 1.0

    @staticmethod
    def of(pixels: np.ndarray, sigma_px: float, noise_sigma: float) -> GradientImage:
        """Gaussian smoothing by ``sigma_px`` of an image with white noise ``noise_sigma``."""
        return GradientImage.from_smoothed(smooth(pixels, sigma_px), sigma_px, noise_sigma)

    @staticmethod
    def from_smoothed(smoothed: np.ndarray, sigma_px: float, noise_sigma: float) -> GradientImage:
        residual, gradient = GradientImage.noise_after(sigma_px, noise_sigma)
        return GradientImage(smoothed, residual, gradient, sigma_px)

    @staticmethod
    def noise_after(sigma_px: float, noise_sigma: float) -> tuple[float, float]:
        """Deviations of white noise ``noise_sigma`` left in an image smoothed by ``sigma_px``
        and in its derivative along one direction."""
        # White noise through a 2-D Gaussian of σ_b keeps σ / (2√π σ_b) of its deviation; its
        # derivative along one direction has deviation σ_s / (√2 σ_b). The floor keeps
        # noise-free images from dividing by zero.
        residual = noise_sigma / (2.0 * math.sqrt(math.pi) * sigma_px) + 0.002
        return residual, residual / (math.sqrt(2.0) * sigma_px)

    def sample(self, uv: np.ndarray) -> np.ndarray:
        """Bilinear samples of the smoothed image at pixel positions (N,2)."""
        points = np.asarray(uv, dtype=np.float32).reshape(-1, 2)
        if not len(points):
            return np.zeros(0)
        # OpenCV's remap takes maps of fewer than 32767 columns: lay the points out in rows.
        columns = min(max(len(points), 1), _REMAP_COLUMNS)
        rows = -(-len(points) // columns)
        map_xy = np.zeros((rows * columns, 2), np.float32)
        map_xy[: len(points)] = points
        samples = cv2.remap(
            self.smoothed,
            map_xy.reshape(rows, columns, 2),
            None,
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )
        return samples.reshape(-1)[: len(points)].astype(float)

    def directional(self, uv: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """Derivative of the smoothed image at points (N,2) along unit directions (N,2) or (2,)
        (central difference over ±1 px)."""
        direction = np.broadcast_to(np.asarray(direction, dtype=float), np.shape(uv))
        both = self.sample(np.concatenate([uv + direction, uv - direction]))
        return 0.5 * (both[: len(uv)] - both[len(uv) :])


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


def _sobel(smoothed: np.ndarray) -> np.ndarray:
    gx = cv2.Sobel(smoothed, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(smoothed, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    return cv2.merge([gx, gy])


def gradient_noise_gain(sigma_px: float) -> float:
    """Std of one component of a ``GradientField`` for unit-variance white noise (measured by
    pushing an impulse through the same filters: the gain is the kernel's L2 norm)."""
    return _gradient_noise_gain(round(float(sigma_px), 6))


@functools.lru_cache(maxsize=64)
def _gradient_noise_gain(sigma_px: float) -> float:
    half = int(np.ceil(4.0 * max(sigma_px, 0.5))) + 3
    impulse = np.zeros((2 * half + 1, 2 * half + 1), np.float32)
    impulse[half, half] = 1.0
    gxy = _sobel(smooth(impulse, sigma_px) if sigma_px > 0 else impulse)
    return float(np.sqrt((gxy[:, :, 0].astype(np.float64) ** 2).sum()))


def smoothed_gradient(
    gray: np.ndarray,
    sigma_px: float,
    noise_sigma: float,
    roi: tuple[int, int, int, int] | None = None,
) -> GradientField:
    """Gradient of ``gray`` (float32) smoothed at ``sigma_px``, over ``roi`` = (x0, y0, x1, y1)
    (clipped to the image; the whole image when None). A margin of 3σ is filtered with the
    region so its border is not degraded: inside the region the result equals the whole image's."""
    h, w = gray.shape
    x0, y0, x1, y1 = (0, 0, w, h) if roi is None else (int(v) for v in roi)
    margin = int(np.ceil(3.0 * sigma_px)) + 2
    x0c, y0c = max(0, x0 - margin), max(0, y0 - margin)
    x1c, y1c = min(w, x1 + margin), min(h, y1 + margin)
    if x1c - x0c < 3 or y1c - y0c < 3:
        return GradientField(np.zeros((1, 1, 2), np.float32), 0, 0, sigma_px, 1.0)
    crop = np.ascontiguousarray(gray[y0c:y1c, x0c:x1c])
    smoothed = smooth(crop, sigma_px) if sigma_px > 0 else crop
    return _field_of(smoothed, x0c, y0c, sigma_px, noise_sigma)


def _field_of(
    smoothed: np.ndarray, x0: int, y0: int, sigma_px: float, noise_sigma: float
) -> GradientField:
    """The ``GradientField`` of an image already smoothed at ``sigma_px`` whose corner is at
    (``x0``, ``y0``)."""
    noise = max(noise_sigma, 1e-4) * gradient_noise_gain(sigma_px)
    return GradientField(_sobel(smoothed), x0, y0, sigma_px, noise)


@dataclass(frozen=True, slots=True, eq=False)
class ImageStack:
    """A frame as float32 intensities on [0, 1] (HxW) with its estimated noise level, and the
    smoothed images and gradients the estimators ask of it, each computed once.

    ``noise_sigma`` is the standard deviation of the pixel noise as the pixels show it (same
    units; what edge strengths and smoothing are judged against; never below ``NOISE_FLOOR``),
    ``clip_sigma`` that of the noise before the sensor clipped it (for likelihoods of clipped
    pixels; 0, least squares, below ``NOISE_FLOOR``); both from ``noise_levels``. Two gradient
    views share the smoothing: ``gradients`` (the whole smoothed image, derivatives sampled
    along given directions — model-contour support and edge profiles) and ``gradient_field``
    (Sobel components over a region — searches along curve normals). The caches are guarded by
    a lock: systems on threads may share a stack.
    """

    pixels: np.ndarray
    noise_sigma: float
    clip_sigma: float = 0.0
    _cache: dict = field(default_factory=dict, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    @property
    def shape(self) -> tuple[int, int]:
        return self.pixels.shape  # type: ignore[return-value]

    def smoothed(self, sigma_px: float) -> np.ndarray:
        """The whole image smoothed by a Gaussian of ``sigma_px`` (``smooth``)."""
        return self._cached(("smoothed", sigma_px), lambda: smooth(self.pixels, sigma_px))

    def reduced(self, factor: int) -> np.ndarray:
        """The whole image reduced by an integer ``factor`` (each pixel the mean of a
        factor × factor block: OpenCV's area interpolation) — the coarse level the acquisition
        stages of every system search first."""
        h, w = self.pixels.shape
        return self._cached(
            ("reduced", factor),
            lambda: cv2.resize(
                self.pixels, (w // factor, h // factor), interpolation=cv2.INTER_AREA
            ),
        )

    def gradients(self, sigma_px: float) -> GradientImage:
        """The ``GradientImage`` at ``sigma_px``."""
        return self._cached(
            ("gradients", sigma_px),
            lambda: GradientImage.from_smoothed(
                self.smoothed(sigma_px), sigma_px, self.noise_sigma
            ),
        )

    def gradient_field(
        self, sigma_px: float, roi: tuple[int, int, int, int] | None = None
    ) -> GradientField:
        """The ``GradientField`` at ``sigma_px`` over ``roi`` = (x0, y0, x1, y1) inclusive of
        x1, y1 (clipped to the image), or the whole image. Only the region (with its filter
        margin) is filtered — inside it the values are the whole image's — unless a field
        already computed at ``sigma_px`` covers it, or it is most of the image (then the whole
        image is filtered once, for every later region). A region is filtered grown by
        ``FIELD_REGION_GROWTH`` on each side, so that the next stage's, a little larger or
        shifted, is covered."""
        whole = self._cache.get(("field", sigma_px, None))
        if whole is not None:
            return whole
        if roi is not None:
            h, w = self.pixels.shape
            x0, y0, x1, y1 = roi
            roi = (max(0, int(x0)), max(0, int(y0)), min(w, int(x1) + 1), min(h, int(y1) + 1))
            for key, field_ in list(self._cache.items()):
                if key[:2] == ("field", sigma_px) and _covers(key[2], roi):
                    return field_
            roi = _grown(roi, FIELD_REGION_GROWTH, w, h)
            if (roi[2] - roi[0]) * (roi[3] - roi[1]) < WHOLE_FIELD_FRACTION * h * w:
                return self._cached(
                    ("field", sigma_px, roi),
                    lambda: smoothed_gradient(self.pixels, sigma_px, self.noise_sigma, roi),
                )
        # The whole image: its smoothing is the one ``smoothed`` and ``gradients`` share.
        return self._cached(
            ("field", sigma_px, None),
            lambda: _field_of(self.smoothed(sigma_px), 0, 0, sigma_px, self.noise_sigma),
        )

    def _cached(self, key: tuple, compute):
        value = self._cache.get(key)
        if value is None:
            value = compute()  # (outside the lock: a twin computed by a racing thread is equal)
            with self._lock:
                value = self._cache.setdefault(key, value)
        return value


def _grown(
    roi: tuple[int, int, int, int], fraction: float, width: int, height: int
) -> tuple[int, int, int, int]:
    """``roi`` = (x0, y0, x1, y1), x1 and y1 exclusive, grown by ``fraction`` of its width and
    height on each side (at least 4 px), clipped to the image."""
    x0, y0, x1, y1 = roi
    dx = max(4, math.ceil(fraction * (x1 - x0)))
    dy = max(4, math.ceil(fraction * (y1 - y0)))
    return max(0, x0 - dx), max(0, y0 - dy), min(width, x1 + dx), min(height, y1 + dy)


def _covers(outer: tuple[int, int, int, int], inner: tuple[int, int, int, int]) -> bool:
    return (
        outer[0] <= inner[0]
        and outer[1] <= inner[1]
        and outer[2] >= inner[2]
        and outer[3] >= inner[3]
    )


_last: tuple[Frame, ImageStack | str] | None = None
_last_lock = threading.Lock()


def image_stack(frame: Frame) -> ImageStack | str:
    """The frame's ``ImageStack``, or a one-line reason why it cannot be used — the same stack
    for every call with the same frame object (the last frame's is kept), so the systems that
    look at one frame in one process prepare its pixels once."""
    global _last
    with _last_lock:
        if _last is not None and _last[0] is frame:
            return _last[1]
    stack = _prepare(frame)
    with _last_lock:
        _last = (frame, stack)
    return stack


def gray_frame(frame: Frame) -> Frame:
    """The frame with its BGR image converted to the single channel the estimators read (the
    conversion ``image_stack`` makes: its stack is the same) and its camera's info
    ``as_mono``; a mono frame, or one with a problem (``frame_problem``), as it is. For a frame
    sent to other processes: a colour frame is three times the bytes."""
    if frame.image.ndim == 2 or frame_problem(frame) is not None:
        return frame
    return replace(frame, image=_gray(frame.image), info=frame.info.as_mono())


def _gray(image: np.ndarray) -> np.ndarray:
    """uint8 stays uint8; other types become float32; BGR is converted with OpenCV's luma
    weights."""
    if image.dtype == np.uint8:
        return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    pixels = np.asarray(image, dtype=np.float32)
    return cv2.cvtColor(pixels, cv2.COLOR_BGR2GRAY) if pixels.ndim == 3 else pixels


def _prepare(frame: Frame) -> ImageStack | str:
    """uint8 images are scaled by 1/255; float images are taken as intensities on [0, 1] (the
    renderer's convention); BGR images are converted with OpenCV's luma weights."""
    problem = frame_problem(frame)
    if problem is not None:
        return problem
    image = frame.image
    if min(image.shape[:2]) < MIN_IMAGE_SIDE_PX:
        return f"image {image.shape[1]}x{image.shape[0]} is too small (< {MIN_IMAGE_SIDE_PX} px)"
    gray = _gray(image)
    if gray.dtype == np.uint8:
        pixels = gray.astype(np.float32) * np.float32(1.0 / 255.0)
    else:
        pixels = np.clip(gray, 0.0, 1.0)
    local_mean = cv2.blur(pixels, (5, 5))
    low, high = percentile(local_mean[::4, ::4], [1.0, 99.0])
    if high - low < MIN_INTENSITY_SPREAD:
        level = "black" if high < 0.1 else "saturated" if low > 0.9 else "uniform"
        return f"image has no contrast ({level}: 1–99 % intensities {low:.2f}–{high:.2f})"
    shown, sigma = noise_levels(pixels, local_mean)
    shown = max(shown, NOISE_FLOOR)
    if _only_noise(pixels, shown):
        return "image holds nothing but noise (blank)"
    # The likelihood of clipped noise takes one σ for every pixel, and matters where a level
    # lies within a few σ of black or white. Under the study's noise that is a dark panel or
    # hole; under a camera's own, only the black background — where a sensor's noise is its
    # read noise, far below the σ of the grey surfaces, so a pixel at 0 is black, not noise
    # clipped. Read as clipped noise it drew the face's outline outward (line system 3 mm
    # short in range at 3 m under the sensor's noise), and the disc fits' prior on a bolt
    # head's wall, weighed against that small σ, let the walls pull the discs inward (corner
    # system 1.2 mm long); least squares, as on a noise-free frame, has neither.
    return ImageStack(pixels, shown, sigma if sigma >= NOISE_FLOOR else 0.0)


def _only_noise(pixels: np.ndarray, noise_sigma: float) -> bool:
    """True when the frame holds nothing but noise: 16×16 block means vary no more than the
    noise averaged over a block would make them (σ/16; their spread is measured over a
    thousand blocks, so 1.5× that is far out of reach of noise alone — a dark target under a
    low sun, 0.15 on black, is not blank)."""
    h, w = pixels.shape
    blocks = cv2.resize(pixels, (w // 16, h // 16), interpolation=cv2.INTER_AREA)
    return float(blocks.std()) < max(1.5 * noise_sigma / 16.0, 0.004)


def estimate_noise_sigma(pixels: np.ndarray) -> float:
    """Standard deviation of the additive white noise of an image before the sensor clipped
    it (``noise_levels``)."""
    return noise_levels(pixels)[1]


def noise_levels(pixels: np.ndarray, local_mean: np.ndarray | None = None) -> tuple[float, float]:
    """Standard deviation of the additive white noise of an image as its pixels show it, and
    before the sensor clipped it, from its Laplacian.

    J. Immerkær, "Fast noise variance estimation", Computer Vision and Image Understanding
    64(2), 1996: the mask [[1,-2,1],[-2,4,-2],[1,-2,1]] cancels smooth image structure and
    σ = √(π/2) · mean|I ∗ M| / 6. Guards: pixels where the image is nearly black or white are
    left out, and so are the strongest 10 % of responses (edges inflate them); the truncated
    mean of |N(0, s)| below its 90th percentile is 0.8238 of the full mean, which the estimate
    divides out. Clipping still hides some of the noise of the pixels kept (at σ = 0.32, 12 %
    of a 0.37 grey is clipped): the noise σ is the one whose clipped variance, averaged over
    those pixels' levels (``clipped_moments``), gives what was measured. ``local_mean``: the
    5×5 box mean of ``pixels`` (``cv2.blur``), when the caller has it already.
    """
    mask = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], dtype=np.float32)
    if min(pixels.shape[:2]) < 6:
        return 0.0, 0.0
    # Every third pixel each way is plenty for a global statistic.
    response = np.abs(cv2.filter2D(pixels, cv2.CV_32F, mask)[1:-1:3, 1:-1:3])
    if local_mean is None:
        local_mean = cv2.blur(pixels, (5, 5))
    level = local_mean[1:-1:3, 1:-1:3]
    chosen = (level > 0.2) & (level < 0.8)
    if chosen.sum() < 100:
        chosen = np.ones_like(chosen)
    usable, levels = response[chosen], level[chosen]
    kept = usable <= percentile(usable, 90.0)
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


def percentile(values: np.ndarray, q: float | Sequence[float]) -> np.floating | np.ndarray:
    """``np.percentile(values, q)`` equal to the last bit (linear interpolation), from one
    introselect per ``q``: NumPy partitions at every neighbouring index and at the end at once,
    ten times slower on a frame's 30 000 noise responses. For one ``q`` the result is in the
    values' dtype, for a sequence a float64 array — as NumPy gives them. ``values``: finite,
    not empty."""
    flat = np.ravel(values)
    if np.ndim(q) == 0:
        return _interpolated(flat, float(q), wide=False)
    return np.array([_interpolated(flat, float(p), wide=True) for p in q])


def _interpolated(flat: np.ndarray, q: float, *, wide: bool) -> np.floating:
    """The ``q`` th percentile of ``flat`` between its two neighbouring order statistics, with
    NumPy's lerp (from the nearer end, so that t = 1 gives the upper value exactly); ``wide``:
    in float64 after the difference is taken in the values' dtype (NumPy's for a sequence of
    q)."""
    n = flat.size
    index = (n - 1) * (q / 100.0)
    k = min(math.floor(index), n - 1)
    ordered = np.partition(flat, k)
    low = ordered[k]
    high = ordered[k + 1 :].min() if k + 1 < n else low
    t = index - k
    diff = high - low
    if wide:
        low, high, diff = np.float64(low), np.float64(high), np.float64(diff)
    return high - diff * (1 - t) if t >= 0.5 else low + diff * t


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
