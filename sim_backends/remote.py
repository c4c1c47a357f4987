"""Device proxies for a simulated world that runs in another process (``--clock wall``).

``WorldLink`` keeps the newest ``WorldSnapshot`` the world process streamed (like the receive
side of RTDE: reading a state never waits for a round trip); ``RemoteArm``, ``RemoteTrack`` and
``RemoteGripper`` implement the device protocols on it and send commands without waiting. A
command the world refused comes back as an error that the device's next call raises. A link
that has gone quiet for ``timeout_s`` raises ``DeviceTimeout`` — as a dropped RTDE or Modbus
link would. ``RemoteCamera`` receives the camera process's frames.
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from collections.abc import Callable
from multiprocessing.connection import Connection

from drivers.base import (
    ArmState,
    DeviceError,
    DeviceFault,
    DeviceTimeout,
    GripperState,
    ServoCommand,
    TrackState,
)
from estimators.frame import CameraInfo, Frame
from sim_backends.world_server import WorldSnapshot


class WorldLink:
    """The control side of the world process's pipe."""

    def __init__(
        self,
        connection: Connection,
        *,
        timeout_s: float = 0.1,
        clock: Callable[[], float] = time.monotonic,
    ):
        self._connection = connection
        self._timeout_s = timeout_s
        self._clock = clock
        self._newest: WorldSnapshot | None = None
        self._errors: dict[str, str] = {}
        self.closed = False

    def snapshot(self, device: str) -> WorldSnapshot:
        """The newest snapshot; raises the device's pending error, or ``DeviceTimeout`` when
        nothing came for ``timeout_s``."""
        self._drain()
        error = self._errors.pop(device, None)
        if error is not None:
            raise DeviceFault(f"simulated {device} refused a command: {error}")
        newest = self._newest
        if newest is None or self._clock() - newest.stamp > self._timeout_s:
            age = "never" if newest is None else f"{self._clock() - newest.stamp:.3f} s ago"
            raise DeviceTimeout(f"simulated {device}: no state from the world process ({age})")
        return newest

    def newest(self) -> WorldSnapshot | None:
        self._drain()
        return self._newest

    def call(self, device: str, method: str, *args: object) -> None:
        self._send(("call", device, method, args))

    def inject(self, device: str, fault: str, *args: object) -> None:
        """A fault in the simulated device (tests, the fault suite)."""
        self._send(("fault", device, fault, args))

    def wait_for_state(self, timeout_s: float) -> WorldSnapshot:
        """Wait for a fresh state (one younger than the link's time-out)."""
        deadline = self._clock() + timeout_s
        while self._clock() < deadline:
            if self._connection.poll(0.01):
                self._drain()
                newest = self._newest
                if newest is not None and self._clock() - newest.stamp <= self._timeout_s:
                    return newest
        raise DeviceTimeout(f"the world process sent no fresh state within {timeout_s} s")

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            with contextlib.suppress(BrokenPipeError, OSError):
                self._connection.send(("stop",))

    def _send(self, message: tuple) -> None:
        try:
            self._connection.send(message)
        except (BrokenPipeError, OSError) as exc:
            raise DeviceTimeout(f"the world process is gone ({exc})") from None

    def _drain(self) -> None:
        try:
            while self._connection.poll(0):
                message = self._connection.recv()
                if isinstance(message, WorldSnapshot):
                    self._newest = message
                elif message[0] == "error":
                    _, device, method, text = message
                    self._errors[device] = f"{method}: {text}"
        except (EOFError, OSError):
            self._newest = None  # the process is gone: the next read times out


class _RemoteDevice:
    name = ""

    def __init__(self, link: WorldLink):
        self._link = link

    def connect(self) -> None:
        self._link.snapshot(self.name)

    def activate(self) -> None:
        self._link.call(self.name, "activate")

    def deactivate(self) -> None:
        self._link.call(self.name, "deactivate")

    def close(self) -> None:
        if not self._link.closed:
            self._link.call(self.name, "close")


class RemoteArm(_RemoteDevice):
    """``drivers.base.Arm`` of the simulated arm in the world process."""

    name = "arm"

    def state(self) -> ArmState:
        arm = self._link.snapshot("arm").arm
        if arm is None:
            raise DeviceTimeout("simulated arm: state unavailable")
        return arm

    def servo(self, command: ServoCommand) -> None:
        self._link.snapshot("arm")  # a refused earlier command raises here
        self._link.call("arm", "servo", command)

    def stop(self, deceleration: float = 2.0) -> None:
        self._link.call("arm", "stop", deceleration)


class RemoteTrack(_RemoteDevice):
    """``drivers.base.Track`` of the simulated track (driven over its register map in the
    world process)."""

    name = "track"

    def state(self) -> TrackState:
        track = self._link.snapshot("track").track
        if track is None:
            raise DeviceTimeout("simulated track: state unavailable")
        return track

    def move_velocity(self, velocity: float) -> None:
        self._link.snapshot("track")
        self._link.call("track", "move_velocity", velocity)

    def move_to(self, position: float, speed: float) -> None:
        self._link.snapshot("track")
        self._link.call("track", "move_to", position, speed)

    def stop(self) -> None:
        self._link.call("track", "stop")


class RemoteGripper(_RemoteDevice):
    """``drivers.base.Gripper`` of the simulated gripper in the world process."""

    name = "gripper"

    def state(self) -> GripperState:
        gripper = self._link.snapshot("gripper").gripper
        if gripper is None:
            raise DeviceTimeout("simulated gripper: state unavailable")
        return gripper

    def grip(self) -> None:
        self._link.call("gripper", "grip")

    def open(self) -> None:
        self._link.call("gripper", "open")


class RemoteCamera:
    """``drivers.base.Camera`` of the camera process: ``read`` returns the newest frame that has
    arrived (older ones are dropped and counted)."""

    def __init__(self, connection: Connection, info: CameraInfo):
        self._connection = connection
        self._info = info
        self._streaming = False
        self._ended = False  # the camera process said it stopped (after its last frame)
        self.frames_dropped = 0

    @property
    def info(self) -> CameraInfo:
        return self._info

    def connect(self) -> None:
        pass

    def activate(self) -> None:
        self._streaming = True

    def deactivate(self) -> None:
        self._streaming = False

    def close(self) -> None:
        self._streaming = False

    def read(self, timeout_s: float = 1.0) -> Frame:
        if not self._streaming:
            raise DeviceError("RemoteCamera.read: the camera is not streaming (call activate())")
        if self._ended:
            raise DeviceTimeout("the camera process stopped")
        frame = None
        try:
            if not self._connection.poll(timeout_s):
                raise DeviceTimeout(f"no frame within {timeout_s} s")
            while True:
                message = self._connection.recv()
                if message is None:  # the end: the frame before it is still handed over
                    self._ended = True
                    break
                if frame is not None:
                    self.frames_dropped += 1
                frame = message
                if not self._connection.poll(0):
                    break
        except (EOFError, OSError):
            if frame is None:
                raise DeviceTimeout("the camera process is gone") from None
        if frame is None:
            raise DeviceTimeout("the camera process stopped")
        # Arrival is when the host has it (as the OAK driver stamps it): the time the frame
        # spent in the pipe counts.
        return dataclasses.replace(frame, arrival_stamp=time.monotonic())
