"""The data a camera hands to the estimators: its intrinsics (``CameraInfo``) and its frames.

These are contracts between layers: drivers produce frames, simulated cameras render them,
estimators consume them. They live here, at the bottom of the stack, so that every layer can
import them without a cycle (DESIGN.md: imports go down).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field, replace

import numpy as np

from estimators.geometry import (
    Pose,
    as_points,
    check_distortion,
    in_view,
    lens_terms,
    project,
    undistort_pixels,
)


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

    def undistort(self, uv: np.ndarray) -> np.ndarray:
        """Normalized, undistorted image coordinates (N,2) of pixel coordinates (N,2)
        (``geometry.undistort_pixels``). Whole pixels inside the image are looked up in a grid
        of every pixel's, computed once per camera and process by the same function (the same
        values: the inverse is computed point by point): at 1280×800 the line system undistorts
        8 000 band pixels a frame, 2.8 ms of its 32, and the grid takes 0.8 s and 16 MB."""
        uv = as_points(uv, 2, "uv")
        if not self.has_distortion or len(uv) == 0:
            return undistort_pixels(uv, self.K, self.dist)
        u, v = uv[:, 0], uv[:, 1]
        whole = (u == np.floor(u)) & (v == np.floor(v))
        whole &= (u >= 0) & (u < self.width) & (v >= 0) & (v < self.height)
        if not np.all(whole):
            return undistort_pixels(uv, self.K, self.dist)
        return self.undistorted_grid()[v.astype(np.intp), u.astype(np.intp)]

    def undistorted_grid(self) -> np.ndarray:
        """Normalized, undistorted coordinates (H, W, 2) of every pixel, as ``undistort`` looks
        them up; computed on first use (an estimator that undistorts whole pixels asks for it
        when it is built, so that no frame waits for it)."""
        return _undistorted_grid(self)

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


#: Each camera's grid of undistorted pixels (``CameraInfo.undistort``), by ``CameraInfo.key``;
#: the last two cameras' are kept.
_UNDISTORTED_GRIDS: dict[tuple, np.ndarray] = {}
_GRIDS_LOCK = threading.Lock()


def _undistorted_grid(camera: CameraInfo) -> np.ndarray:
    """Normalized, undistorted coordinates (H, W, 2) of every pixel of ``camera``."""
    grid = _UNDISTORTED_GRIDS.get(camera.key)
    if grid is None:
        v, u = np.mgrid[0 : camera.height, 0 : camera.width]
        pixels = np.column_stack([u.ravel(), v.ravel()]).astype(float)
        grid = undistort_pixels(pixels, camera.K, camera.dist)
        grid = grid.reshape(camera.height, camera.width, 2)
        grid.flags.writeable = False
        with _GRIDS_LOCK:  # (a twin computed by a racing thread is equal)
            _UNDISTORTED_GRIDS[camera.key] = grid
            while len(_UNDISTORTED_GRIDS) > 2:
                del _UNDISTORTED_GRIDS[next(iter(_UNDISTORTED_GRIDS))]
    return grid


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
