"""The devices of a trial from its configuration (``devices:``, ``configuration.devices``).

Which backend drives each device is decided here and in ``hil.runtime.wall`` (which starts the
trial's processes), once; the loop, the sequencer and the supervisor see only the device
protocols.

* ``emulated_endpoints``: where the emulators of an emulated rig listen
  (``sim_backends.emulated_world``).
* ``RealDevices``: the arm, track and gripper drivers — ``URArm`` on ur-rtde, ``ModbusTrack`` and
  ``RobotiqGripper`` on pymodbus, each on an I/O thread of its own (``drivers.threaded_io``) —
  built from configuration, brought up (connect, then activate,
  then the gripper's own activation) within bounded times, and closed on every way out.
* ``device_camera_main``: the camera process of a real OAK (or a replayed recording): it reads
  the camera and hands the newest frame to the vision process, like the rendering camera
  process of a simulated rig.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection

import numpy as np

from configuration.devices import (
    DevicesConfig,
    ModbusDevice,
    OakCameraDevice,
    RobotiqGripperDevice,
    URArmDevice,
)
from configuration.rig import RigConfig
from drivers.base import DeviceError, DeviceTimeout, ServoCommand
from drivers.gripper_robotiq import RobotiqGripper
from drivers.threaded_io import ThreadedGripper, ThreadedTrack, stale_after
from drivers.track_modbus import ModbusTrack
from drivers.ur_rtde import URArm
from sim_backends.emulated_world import EmulatedEndpoints
from sim_backends.world_server import LatestSender

log = logging.getLogger(__name__)

#: How often the gripper's activation is polled (s).
_POLL_S = 0.02


def _drivers_of(
    devices: DevicesConfig,
) -> tuple[URArmDevice, ModbusDevice, RobotiqGripperDevice]:
    arm, track, gripper = devices.arm, devices.track, devices.gripper
    if not (
        isinstance(arm, URArmDevice)
        and isinstance(track, ModbusDevice)
        and isinstance(gripper, RobotiqGripperDevice)
    ):
        raise ValueError("real devices need arm ur_rtde, track modbus and gripper modbus")
    return arm, track, gripper


def emulated_endpoints(devices: DevicesConfig) -> EmulatedEndpoints:
    """Where the emulators of ``devices`` (an emulated rig) listen; ``ValueError`` when an
    address is not a loopback address."""
    arm, track, gripper = _drivers_of(devices)
    return EmulatedEndpoints(arm.host, track.endpoint(), gripper.endpoint())


@dataclass(eq=False)
class RealDevices:
    """The real drivers of arm, track and gripper (``drivers.base`` protocols)."""

    arm: URArm
    track: ThreadedTrack
    gripper: ThreadedGripper
    gripper_activation_s: float = 10.0

    @staticmethod
    def from_config(devices: DevicesConfig, rig: RigConfig) -> RealDevices:
        """The drivers ``devices`` describe (not yet connected). ``rig`` gives the gripper's
        speed and force."""
        arm, track, gripper = _drivers_of(devices)
        return RealDevices(
            arm=arm.driver(),
            track=ThreadedTrack(
                ModbusTrack.over_tcp(
                    track.host, track.port, track.device_id, timeout_s=track.timeout_s
                ),
                period_s=track.io_period_s,
                stale_after_s=stale_after(track.timeout_s, track.io_period_s),
                command_timeout_s=track.command_timeout_s,
            ),
            gripper=ThreadedGripper(
                RobotiqGripper.over_tcp(
                    gripper.host,
                    gripper.port,
                    gripper.device_id,
                    timeout_s=gripper.timeout_s,
                    speed=rig.gripper.grip_speed,
                    force=rig.gripper.grip_force,
                ),
                period_s=gripper.io_period_s,
                stale_after_s=stale_after(gripper.timeout_s, gripper.io_period_s),
            ),
            gripper_activation_s=gripper.activation_timeout_s,
        )

    def named(self) -> dict[str, URArm | ThreadedTrack | ThreadedGripper]:
        return {"arm": self.arm, "track": self.track, "gripper": self.gripper}

    def start(self, *, clock: Callable[[], float] = time.monotonic) -> None:
        """Connect every device; activate the gripper and wait for its activation (the fingers
        calibrate, which takes a while), then the track, and the arm last: once its control
        script runs, the controller's watchdog wants a command every 1/watchdog_min_frequency_hz
        seconds, which only the control loop, started right after, sends. Raises
        ``DeviceError`` naming the device."""
        for name, device in self.named().items():
            _named(name, device.connect)
        _named("gripper", self.gripper.activate)
        deadline = clock() + self.gripper_activation_s
        while not _named("gripper", self.gripper.state).activated:
            if clock() > deadline:
                raise DeviceTimeout(
                    f"gripper: not activated within {self.gripper_activation_s:g} s "
                    "(devices.gripper.activation_timeout_s)"
                )
            time.sleep(_POLL_S)
        _named("track", self.track.activate)
        _named("arm", self.arm.activate)
        # A zero twist: the arm's first command arms the controller's watchdog and is the
        # slowest (setWatchdog, then ur-rtde waits for the script: 20–60 ms measured), better here
        # than in the loop's first tick, whose deadline the supervisor checks.
        _named("arm", lambda: self.arm.servo(ServoCommand(clock(), np.zeros(6))))

    def close(self) -> list[str]:
        """Close every device (each attempted whatever the others do; the arm first: it stops
        and ends its control script); returns what failed."""
        failures = []
        for name in ("arm", "track", "gripper"):
            try:
                self.named()[name].close()
            except Exception as exc:  # closing must go on to the next device
                failures.append(f"{name}: {exc}")
                log.warning("closing the %s failed: %s", name, exc)
        return failures


def _named(name: str, call: Callable):
    try:
        return call()
    except DeviceError as exc:
        raise type(exc)(f"{name}: {exc}") from None


def device_camera_main(config: OakCameraDevice, frames: Connection, control: Connection) -> None:
    """The camera process of a real camera (or a replay): build and start it, report
    ``("ready", CameraInfo)`` (or ``("failed", reason)``) on ``control``, then hand every new
    frame to ``frames`` — the newest only: a reader that fell behind gets the present — until
    ``control`` says stop or closes, or a replay ends."""
    from drivers.oak import ReplayFinished  # depthai loads in ~1 s: only in this process

    with contextlib.suppress(KeyboardInterrupt):  # Ctrl-C is the control process's business
        camera = config.build()
        try:
            camera.connect()
            camera.activate()
        except (DeviceError, OSError) as exc:
            camera.close()
            with contextlib.suppress(OSError):
                control.send(("failed", str(exc)))
            return
        outgoing = LatestSender(frames)
        try:
            control.send(("ready", camera.info))
            while not outgoing.broken:
                if control.poll(0):
                    break  # "stop", or the control side went away
                try:
                    outgoing.put(camera.read(timeout_s=0.2))
                except ReplayFinished:
                    break
                except DeviceTimeout:
                    continue
        except (EOFError, OSError):
            pass
        finally:
            outgoing.close(drain=True)  # the newest frame still goes out
            with contextlib.suppress(OSError):
                frames.send(None)  # the vision side's camera reports it stopped
            camera.close()
