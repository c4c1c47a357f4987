"""Device protocols and the data that flows out of and into devices.

One ``typing.Protocol`` per device — ``Camera``, ``Arm``, ``Gripper``, ``Track`` — implemented by
real drivers, simulated backends and emulated ones alike; configuration picks one and nothing
downstream branches on which. Lifecycle (ros2_control style): constructed = not connected;
``connect()`` establishes communication or raises ``DeviceError``; ``close()`` releases it and
is safe to call twice. Time stamps are host ``time.monotonic()`` seconds (or the injected clock
of a simulation).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from estimators.geometry import Pose, check_distortion, in_view, project


class DeviceError(RuntimeError):
    """A device could not be reached or refused a request."""


class DeviceTimeout(DeviceError):
    """A device did not answer within its deadline."""


class DeviceFault(DeviceError):
    """A device reports a fault (protective stop, gripper fault, track fault, …)."""


def _readonly(array: np.ndarray, shape: tuple[int, ...], name: str) -> np.ndarray:
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
        K = _readonly(self.K, (3, 3), "CameraInfo.K")
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
    def shape(self) -> tuple[int, ...]:
        """Expected image array shape."""
        return (self.height, self.width) if self.channels == 1 else (self.height, self.width, 3)

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist != 0))

    def project(self, points_C: np.ndarray) -> np.ndarray:
        return project(points_C, self.K, self.dist)

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
    """One camera image with its time stamp and intrinsics.

    ``image`` is uint8 HxW (mono) or HxWx3 in BGR order (OpenCV's and depthai's).

    The constructor does not judge the pixels — a driver hands on what the device gave;
    ``frame_problem`` says whether a frame is usable, and consumers must ask it.
    """

    image: np.ndarray
    stamp: float
    info: CameraInfo
    seq: int
    truth: GroundTruth | None = field(default=None)


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


@runtime_checkable
class Camera(Protocol):
    """A source of frames. ``read`` blocks up to ``timeout_s`` for the next frame (newest
    first: a stale frame is never returned twice) and raises ``DeviceTimeout`` when none came."""

    @property
    def info(self) -> CameraInfo: ...

    def connect(self) -> None: ...

    def close(self) -> None: ...

    def read(self, timeout_s: float = 1.0) -> Frame: ...


# --- arm --------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, eq=False)
class ArmState:
    """Arm state: joints (rad), flange pose ``X_BE``, TCP twist ``V_BE`` = [v (m/s), ω (rad/s)]
    expressed in B, and the controller's safety flags."""

    stamp: float
    q: np.ndarray
    X_BE: Pose
    V_BE: np.ndarray
    protective_stop: bool = False
    emergency_stop: bool = False
    fault: str | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "q", _readonly(self.q, (6,), "ArmState.q"))
        object.__setattr__(self, "V_BE", _readonly(self.V_BE, (6,), "ArmState.V_BE"))

    @property
    def fault_reason(self) -> str | None:
        """Why the arm cannot move, or None when it can."""
        if self.emergency_stop:
            return "emergency stop"
        if self.protective_stop:
            return "protective stop"
        return self.fault


@dataclass(frozen=True, slots=True, eq=False)
class ServoCommand:
    """A streamed Cartesian velocity set-point (UR speedL) for the flange, in B, limits already
    applied; or a stop. ``reason`` says why a stop was commanded."""

    stamp: float
    V_BE: np.ndarray
    stop: bool = False
    reason: str = ""

    def __post_init__(self) -> None:
        V = _readonly(self.V_BE, (6,), "ServoCommand.V_BE")
        if not np.all(np.isfinite(V)):
            raise ValueError("ServoCommand.V_BE contains NaN or infinite values")
        object.__setattr__(self, "V_BE", V)

    @staticmethod
    def halt(stamp: float, reason: str) -> ServoCommand:
        return ServoCommand(stamp, np.zeros(6), stop=True, reason=reason)


@runtime_checkable
class Arm(Protocol):
    """A robot arm streaming Cartesian velocity commands (UR speedL semantics: the arm keeps the
    last twist until told otherwise or until its watchdog stops it)."""

    def connect(self) -> None: ...

    def close(self) -> None: ...

    def state(self) -> ArmState: ...

    def servo(self, command: ServoCommand) -> None: ...

    def stop(self, deceleration: float = 2.0) -> None: ...


# --- gripper ----------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class GripperState:
    """Gripper state: ``position`` 0 (open) … 1 (closed), motion and object detection."""

    stamp: float
    activated: bool
    position: float
    moving: bool
    object_detected: bool
    fault: str | None = None


@runtime_checkable
class Gripper(Protocol):
    def connect(self) -> None: ...

    def close(self) -> None: ...

    def activate(self) -> None: ...

    def open(self) -> None: ...

    def grip(self) -> None: ...

    def state(self) -> GripperState: ...


# --- linear track -----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class TrackState:
    """Linear axis carrying the mock-up: carriage position (m) and velocity (m/s) along it."""

    stamp: float
    position: float
    velocity: float
    moving: bool
    fault: str | None = None


@runtime_checkable
class Track(Protocol):
    def connect(self) -> None: ...

    def close(self) -> None: ...

    def state(self) -> TrackState: ...

    def move_velocity(self, velocity: float) -> None: ...

    def move_to(self, position: float, speed: float) -> None: ...

    def stop(self) -> None: ...
