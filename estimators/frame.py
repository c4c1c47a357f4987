"""The data a camera hands to the estimators: its intrinsics (``CameraInfo``) and its frames.

These are contracts between layers: drivers produce frames, simulated cameras render them,
estimators consume them. They live here, at the bottom of the stack, so that every layer can
import them without a cycle (DESIGN.md: imports go down).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from estimators.geometry import Pose, check_distortion, in_view, lens_terms, project


def readonly_array(array: np.ndarray, shape: tuple[int, ...], name: str) -> np.ndarray:
    """A read-only float copy of ``array``, checked to have ``shape`` (``name`` in the error)."""
    out = np.array(array, dtype=float)
    if out.shape != shape:
        raise ValueError(f"{name} must have shape {shape}; got {out.shape}")
    out.flags.writeable = False
    return out


# --- camera -----------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, eq=False)
class CameraInfo:
    """Intrinsics of a camera: image size (px), K (3×3), OpenCV distortion, channel count."""

    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    model: str
    channels: int = 1

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"CameraInfo size must be positive; got {self.width}x{self.height}")
        K = readonly_array(self.K, (3, 3), "CameraInfo.K")
        if not (K[0, 0] > 0 and K[1, 1] > 0 and np.allclose(K[2], [0, 0, 1]) and K[1, 0] == 0):
            raise ValueError(
                f"CameraInfo.K is not an upper-triangular intrinsic matrix: {K.tolist()}"
            )
        object.__setattr__(self, "K", K)
        dist = check_distortion(self.dist).copy()
        dist.flags.writeable = False
        object.__setattr__(self, "dist", dist)
        if self.channels not in (1, 3):
            raise ValueError(f"CameraInfo.channels must be 1 or 3; got {self.channels}")

    @property
    def lens(self) -> tuple[np.ndarray, np.ndarray, bool, bool]:
        """The compiled lens model's arguments (``geometry.lens_terms``) and whether the camera
        distorts at all."""
        return (*lens_terms(self.dist), self.dist.size > 0)

    @property
    def shape(self) -> tuple[int, ...]:
        """Expected image array shape."""
        return (self.height, self.width) if self.channels == 1 else (self.height, self.width, 3)

    @property
    def key(self) -> tuple:
        """The intrinsics' content (size, channels, K, distortion) as a hashable value: two
        infos with the same key image the world identically, whatever their ``model`` name."""
        return (
            self.width,
            self.height,
            self.channels,
            self.K.tobytes(),
            self.dist.tobytes(),
        )

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist != 0))

    def as_mono(self) -> CameraInfo:
        """The same camera delivering one channel (the intensities the estimators read)."""
        return self if self.channels == 1 else replace(self, channels=1)

    def project(self, points_C: np.ndarray) -> np.ndarray:
        return project(points_C, self.K, self.dist)

    def image_of_ideal(self, uv_ideal: np.ndarray) -> np.ndarray:
        """Pinhole ("ideal") pixels (N,2) of this K as the camera images them, its lens
        distortion applied (``planar_pose.ideal_pixels`` undoes it)."""
        uv = np.asarray(uv_ideal, dtype=float).reshape(-1, 2)
        K = self.K
        y = (uv[:, 1] - K[1, 2]) / K[1, 1]
        x = (uv[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
        return self.project(np.column_stack([x, y, np.ones(len(uv))]))

    def in_view(self, points_C: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        """Mask of points (N,3) in C imaged at least ``margin_px`` inside the borders."""
        return in_view(points_C, self.K, self.dist, self.width, self.height, margin_px=margin_px)

    def to_dict(self) -> dict:
        return {
            "model": self.model,
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
            "channels": self.channels,
        }


@dataclass(frozen=True, slots=True, eq=False)
class GroundTruth:
    """Simulator ground truth attached to a rendered frame (never present on real hardware)."""

    X_CT: Pose
    X_WC: Pose


@dataclass(frozen=True, slots=True, eq=False)
class Frame:
    """One camera image with its time stamps and intrinsics.

    ``image`` is uint8 HxW (mono) or HxWx3 in BGR order (OpenCV's and depthai's). ``stamp`` is
    the capture time — the middle of the exposure — on the host's monotonic clock (or the
    simulation's); ``exposure_s`` the exposure time; ``arrival_stamp`` when the host received
    the frame (None when the source does not say). The world in the image is the world at
    ``stamp``: a real camera delivers it 100–130 ms later.

    The constructor does not judge the pixels — a driver hands on what the device gave;
    ``frame_problem`` says whether a frame is usable, and consumers must ask it.
    """

    image: np.ndarray
    stamp: float
    info: CameraInfo
    seq: int
    truth: GroundTruth | None = field(default=None)
    exposure_s: float = 0.0
    arrival_stamp: float | None = None

    @property
    def latency_s(self) -> float | None:
        """Capture to arrival (s), when the arrival is known."""
        return None if self.arrival_stamp is None else self.arrival_stamp - self.stamp


def frame_problem(frame: Frame) -> str | None:
    """Why a frame cannot be used (empty, wrong shape or type, NaN, stale stamp), or None."""
    image = frame.image
    if not isinstance(image, np.ndarray):
        return f"image is a {type(image).__name__}, not an array"
    if image.size == 0:
        return "image is empty"
    if image.shape != frame.info.shape:
        return f"image shape {image.shape} does not match the camera's {frame.info.shape}"
    if image.dtype != np.uint8:
        if not np.issubdtype(image.dtype, np.floating):
            return f"image dtype {image.dtype} is neither uint8 nor float"
        if not np.all(np.isfinite(image)):
            return "image contains NaN or infinite values"
    if not np.isfinite(frame.stamp):
        return "frame stamp is not finite"
    return None
