"""Device protocols and the data that flows out of and into devices.

One ``typing.Protocol`` per device — ``Camera``, ``Arm``, ``Gripper``, ``Track`` — implemented by
real drivers, simulated backends and emulated ones alike; configuration picks one and nothing
downstream branches on which.

Lifecycle (ros2_control's unconfigured → inactive → active):

* constructed: no communication;
* ``connect()``: communication established and state readable ("inactive"), or ``DeviceError``;
* ``activate()``: the device may move or stream (UR: the control script runs; track: drive
  enabled; gripper: activated; camera: streaming); commands before it raise ``DeviceError``;
* ``deactivate()``: stop and give up the right to move; state stays readable;
* ``close()``: release everything (deactivating first if needed); safe to call twice.

Time stamps are host ``time.monotonic()`` seconds (or the injected clock of a simulation).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from estimators.frame import CameraInfo, Frame, readonly_array
from estimators.geometry import Pose


class DeviceError(RuntimeError):
    """A device could not be reached or refused a request."""


class DeviceTimeout(DeviceError):
    """A device did not answer within its deadline."""


class DeviceFault(DeviceError):
    """A device reports a fault (protective stop, gripper fault, track fault, …)."""


# --- camera ---------------------------------------------------------------------------------------


@runtime_checkable
class Camera(Protocol):
    """A source of frames. ``read`` blocks up to ``timeout_s`` for the next frame (newest
    first: a stale frame is never returned twice) and raises ``DeviceTimeout`` when none came."""

    @property
    def info(self) -> CameraInfo: ...

    def connect(self) -> None: ...

    def activate(self) -> None: ...

    def deactivate(self) -> None: ...

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
    #: Wrench at the TCP [f (N), τ (N·m)] in B, where the arm measures it (UR: getActualTCPForce).
    wrench_B: np.ndarray | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "q", readonly_array(self.q, (6,), "ArmState.q"))
        object.__setattr__(self, "V_BE", readonly_array(self.V_BE, (6,), "ArmState.V_BE"))
        if self.wrench_B is not None:
            wrench = readonly_array(self.wrench_B, (6,), "ArmState.wrench_B")
            object.__setattr__(self, "wrench_B", wrench)

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
    applied; or a stop. ``reason`` says why a stop was commanded.

    ``acceleration`` (m/s²; the angular part ramps at the same number in rad/s²) is speedL's
    ``acc``: how fast the arm may reach the twist; None leaves it to the arm's configuration.
    ``duration_s`` is speedL's ``time``: 0 keeps the twist until the next command."""

    stamp: float
    V_BE: np.ndarray
    stop: bool = False
    reason: str = ""
    acceleration: float | None = None
    duration_s: float = 0.0

    def __post_init__(self) -> None:
        V = readonly_array(self.V_BE, (6,), "ServoCommand.V_BE")
        if not np.all(np.isfinite(V)):
            raise ValueError("ServoCommand.V_BE contains NaN or infinite values")
        object.__setattr__(self, "V_BE", V)
        if self.acceleration is not None and not (
            np.isfinite(self.acceleration) and self.acceleration > 0
        ):
            raise ValueError(f"ServoCommand.acceleration must be > 0; got {self.acceleration}")
        if not (np.isfinite(self.duration_s) and self.duration_s >= 0):
            raise ValueError(f"ServoCommand.duration_s must be ≥ 0; got {self.duration_s}")

    @staticmethod
    def halt(stamp: float, reason: str) -> ServoCommand:
        return ServoCommand(stamp, np.zeros(6), stop=True, reason=reason)


@runtime_checkable
class Arm(Protocol):
    """A robot arm streaming Cartesian velocity commands (UR speedL semantics: the arm keeps the
    last twist until told otherwise or until its watchdog stops it)."""

    def connect(self) -> None: ...

    def activate(self) -> None: ...

    def deactivate(self) -> None: ...

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
    """A parallel gripper. ``activate`` runs the device's own activation (Robotiq: rACT, the
    fingers calibrate); ``deactivate`` keeps the fingers where they are (never drops a part)."""

    def connect(self) -> None: ...

    def activate(self) -> None: ...

    def deactivate(self) -> None: ...

    def close(self) -> None: ...

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
    """A linear axis. ``activate`` enables the drive; ``deactivate`` stops and removes power."""

    def connect(self) -> None: ...

    def activate(self) -> None: ...

    def deactivate(self) -> None: ...

    def close(self) -> None: ...

    def state(self) -> TrackState: ...

    def move_velocity(self, velocity: float) -> None: ...

    def move_to(self, position: float, speed: float) -> None: ...

    def stop(self) -> None: ...
