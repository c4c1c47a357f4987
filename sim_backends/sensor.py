"""The image sensor: motion blur during the exposure, noise, and 8-bit quantisation.

Noise models (on [0, 1] intensities, then clipped to [0, 1] and rounded to 8 bits):

* the reference study's additive Gaussian presets — variance 0 (``none``), 0.05 (``low``) and
  0.1 (``high``); σ ≈ 0.22 and 0.32 of full scale;
* ``sensor``: photon shot noise and read noise from a photon-transfer model — an intensity I
  collects I·full_well electrons, with Poisson variance I·full_well (drawn as a Gaussian, exact
  to well under 1 % above ~20 e⁻) plus read noise σ_read electrons.

Auto-exposure (``NoiseConfig.auto_exposure``) scales the frame before its noise so that the
brightest 1 % of the target's pixels reach 0.9 of full scale: highlight metering on the
target, as a machine-vision camera's auto-exposure region set on the mock-up, within a gain
range of 1/8–8×. The noise is then added at its configured level, as on a camera that lengthens
its exposure (the study's noise is fixed on the recorded intensities, whatever the exposure).

Motion blur integrates the image over the exposure while the camera moves with twist (v, ω)
relative to the target: each pixel's image velocity comes from the interaction matrix of an
image point at depth Z (Chaumette & Hutchinson, "Visual servo control I", IEEE RAM 2006):
ẋ = −v_x/Z + x·v_z/Z + x·y·ω_x − (1 + x²)·ω_y + y·ω_z,
ẏ = −v_y/Z + y·v_z/Z + (1 + y²)·ω_x − x·y·ω_y − x·ω_z.
"""

from __future__ import annotations

import cv2
import numpy as np

from configuration.render import NoiseConfig

_BLUR_SUBFRAMES = 9

#: Auto-exposure: the percentile of the target's pixels metered, the level it is brought to,
#: and the gain's range (exposure time and analog gain together, around the nominal exposure).
AUTO_EXPOSURE_PERCENTILE = 99.0
AUTO_EXPOSURE_LEVEL = 0.9
AUTO_EXPOSURE_GAIN_RANGE = (0.125, 8.0)


def frame_rng(seed: int, seq: int = 0) -> np.random.Generator:
    """The random generator for frame ``seq`` of a run seeded ``seed``: a frame's noise depends
    only on (seed, seq), not on what was drawn before — same seed, identical frames."""
    return np.random.default_rng([int(seed), int(seq)])


class NoisePool:
    """Standard normal draws for a camera that must keep up with its frame rate (the camera
    process of ``--clock wall``), in place of ``frame_rng``: two frames' worth drawn once, and
    each frame's read from a new random offset into them (``standard_normal``, the one call
    ``add_noise`` makes). Drawing a 1280×800 colour frame's 3 M normals took 29 ms a frame; with
    the rest of the sensor model and the render that process used 72 % of one of the two cores
    the estimators share.

    A frame's noise is white, and a pixel's noise in two frames comes from different draws (the
    offsets differ); what two frames share is a pattern shifted by the offsets' difference, which
    no estimator looks for. Frames are then not reproducible from the seed, which a wall-clock
    camera's never are (which frames it renders depends on the timing); ``frame_rng`` keeps
    ``--clock sim`` and every evaluation exact."""

    def __init__(self, seed: int):
        self._rng = np.random.default_rng([int(seed), 0x9001])
        self._draws = np.zeros(0, np.float32)
        self._offset = -1

    def standard_normal(self, shape: tuple[int, ...], dtype: type = np.float32) -> np.ndarray:
        """Normal draws of ``shape`` (float32: what ``add_noise`` asks for)."""
        if np.dtype(dtype) != np.float32:
            raise ValueError(f"NoisePool draws float32 only; asked for {np.dtype(dtype)}")
        n = int(np.prod(shape))
        if 2 * n > len(self._draws):
            self._draws = self._rng.standard_normal(2 * n, dtype=np.float32)
        offset = self._offset
        while offset == self._offset:  # never the previous frame's noise again
            offset = int(self._rng.integers(0, len(self._draws) - n + 1))
        self._offset = offset
        return self._draws[offset : offset + n].reshape(shape)


def image_flow(
    depth_m: np.ndarray, K: np.ndarray, twist_C: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Pixel velocity (px/s) of every pixel for a camera twist [v, ω] (m/s, rad/s) in C."""
    h, w = depth_m.shape
    # float32 throughout: cv2.remap needs float32 maps (numpy scalars would promote to float64).
    fx, fy, cx, cy = (np.float32(k) for k in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    x = (u - cx) / fx
    y = (v - cy) / fy
    inv_z = np.where(np.isfinite(depth_m), 1.0 / np.maximum(depth_m, 1e-6), 0.0).astype(np.float32)
    vx, vy, vz, wx, wy, wz = (np.float32(c) for c in twist_C)
    dx = -vx * inv_z + x * vz * inv_z + x * y * wx - (1 + x * x) * wy + y * wz
    dy = -vy * inv_z + y * vz * inv_z + (1 + y * y) * wx - x * y * wy - x * wz
    return fx * dx, fy * dy


def motion_blur(
    image: np.ndarray, depth_m: np.ndarray, K: np.ndarray, twist_C: np.ndarray, exposure_s: float
) -> np.ndarray:
    """Average of the image shifted along its flow over the exposure (centred on the stamp)."""
    if exposure_s <= 0 or not np.any(twist_C):
        return image
    flow_u, flow_v = image_flow(depth_m, K, np.asarray(twist_C, dtype=float))
    h, w = depth_m.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    out = np.zeros_like(image, dtype=np.float32)
    for t in np.linspace(-exposure_s / 2, exposure_s / 2, _BLUR_SUBFRAMES):
        # A scene point seen at u at the stamp was at u + flow·t at time t.
        t = np.float32(t)
        out += cv2.remap(
            image, u + flow_u * t, v + flow_v * t, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )
    return out / _BLUR_SUBFRAMES


def auto_exposure_gain(image: np.ndarray, depth_m: np.ndarray | None) -> float:
    """The gain that brings the target's brightest pixels (where ``depth_m`` is finite; without
    a depth, the pixels that are not black) to ``AUTO_EXPOSURE_LEVEL``, within the camera's
    range; 1 where nothing is metered."""
    image = np.asarray(image, dtype=np.float32)
    if depth_m is not None:
        metered = image[np.isfinite(depth_m)]
    else:
        metered = image[image.max(axis=-1) > 0] if image.ndim == 3 else image[image > 0]
    if metered.size == 0:
        return 1.0
    bright = float(np.percentile(metered, AUTO_EXPOSURE_PERCENTILE))
    low, high = AUTO_EXPOSURE_GAIN_RANGE
    if bright <= 0:
        return high
    return float(np.clip(AUTO_EXPOSURE_LEVEL / bright, low, high))


def noise_sigma(image: np.ndarray, noise: NoiseConfig) -> np.ndarray | float:
    """Standard deviation (on [0, 1] intensities, before clipping) of the noise at each pixel."""
    if noise.preset == "sensor":
        electrons = np.asarray(image, dtype=np.float32) * noise.full_well_e
        return np.sqrt(electrons + noise.read_noise_e**2) / noise.full_well_e
    return float(np.sqrt(noise.gaussian_variance))


def add_noise(
    image: np.ndarray, noise: NoiseConfig, rng: np.random.Generator | NoisePool
) -> np.ndarray:
    """Noisy copy of a float image in [0, 1], clipped to [0, 1]."""
    image = np.asarray(image, dtype=np.float32)
    sigma = noise_sigma(image, noise)
    if np.all(sigma == 0):
        return image.copy()
    noisy = image + np.float32(sigma) * rng.standard_normal(image.shape, dtype=np.float32)
    return np.clip(noisy, 0.0, 1.0, out=noisy)


def to_uint8(image: np.ndarray) -> np.ndarray:
    """Quantise a [0, 1] float image to 8 bits (round to nearest, ties to even; saturated).
    OpenCV does it as ``np.clip(np.rint(255 · image), 0, 255)`` would, to the bit, in a sixth of
    the time (7 → 1.3 ms for a 1280×800 colour frame, which a wall-clock camera makes 15 times a
    second)."""
    pixels = np.asarray(image, dtype=np.float32)
    column = np.ascontiguousarray(pixels).reshape(-1, 1)  # any shape, as one run of values
    _, positive = cv2.threshold(column, 0.0, 0.0, cv2.THRESH_TOZERO)  # convertScaleAbs takes |x|
    return cv2.convertScaleAbs(positive, alpha=255.0).reshape(pixels.shape)


def expose(
    image: np.ndarray,
    depth_m: np.ndarray,
    K: np.ndarray,
    noise: NoiseConfig,
    rng: np.random.Generator | NoisePool,
    twist_C: np.ndarray | None = None,
) -> np.ndarray:
    """The 8-bit frame a sensor records of a noise-free rendered ``image``; its noise drawn
    from ``rng`` (``frame_rng``, or a ``NoisePool``)."""
    if noise.motion_blur and twist_C is not None:
        image = motion_blur(image, depth_m, K, twist_C, noise.exposure_s)
    if noise.auto_exposure:
        image = np.clip(np.float32(auto_exposure_gain(image, depth_m)) * image, 0.0, 1.0)
    return to_uint8(add_noise(image, noise, rng))
