"""Configuration of the real devices' drivers (addresses, streams, replays), and which backend
drives each device of a trial (``DevicesConfig``, the ``devices:`` section of a trial
configuration).

Every model is frozen and rejects unknown keys.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field, model_validator

from configuration.base import Positive, Strict
from configuration.rig import ModbusEndpoint
from drivers.threaded_io import TRACK_COMMAND_TIMEOUT_S
from drivers.ur_rtde import URArm, URArmOptions

if TYPE_CHECKING:
    from drivers.oak import OakCamera, OakReplay


# --- OAK camera (drivers/oak.py) ----------------------------------------------------------------


class OakReplayConfig(Strict):
    """A recorded video and its depthai calibration JSON replayed instead of a live camera
    (``satgrasp record`` writes both). ``realtime`` paces frames at ``fps`` (None: the video's
    own rate) and keeps only the newest, as a live camera does; false delivers every frame as
    fast as it is read. Relative paths are relative to the working directory."""

    video: Path
    calibration: Path
    realtime: bool = True
    fps: Annotated[float, Field(gt=0.0, le=1000.0)] | None = None


class OakCameraConfig(Strict):
    """An OAK camera: which socket, the output stream (size, rate, mono or colour), optional
    manual exposure (µs) with its ISO, which device (id, name or IP; None: the first found) —
    or, with ``replay``, a recording played through the same driver path."""

    socket: Literal["CAM_A", "CAM_B", "CAM_C", "CAM_D", "CAM_E", "CAM_F", "CAM_G", "CAM_H"] = (
        "CAM_A"
    )
    width: Annotated[int, Field(ge=16, le=8192)] = 1280
    height: Annotated[int, Field(ge=16, le=8192)] = 800
    fps: Annotated[Positive, Field(le=240.0)] = 30.0
    channels: Literal[1, 3] = 3
    exposure_us: Annotated[int, Field(ge=1, le=1_000_000)] | None = None
    iso: Annotated[int, Field(ge=100, le=1600)] = 400
    device: str | None = None
    replay: OakReplayConfig | None = None

    def build(self) -> OakCamera | OakReplay:
        """The driver this configuration describes (not yet connected)."""
        from drivers.oak import OakCamera, OakReplay  # depthai loads in ~1 s: only when used

        if self.replay is not None:
            return OakReplay(
                self.replay.video,
                self.replay.calibration,
                socket=self.socket,
                channels=self.channels,
                fps=self.replay.fps,
                realtime=self.replay.realtime,
            )
        return OakCamera(
            socket=self.socket,
            width=self.width,
            height=self.height,
            fps=self.fps,
            channels=self.channels,
            exposure_us=self.exposure_us,
            iso=self.iso,
            device=self.device,
        )


# --- UR arm (drivers/ur_rtde.py) ----------------------------------------------------------------

#: The driver's defaults, written once (in URArmOptions).
_UR = URArmOptions()


class URArmConfig(Strict):
    """A UR e-Series arm over ur-rtde: its address and the driver's time-outs and defaults.

    The controller's ports are fixed (dashboard 29999, script 30003, RTDE 30004); its TCP
    offset must be zero (the driver reports the flange tool0 as X_BE); remote control must be
    enabled on the teach pendant. See docs/rig_setup.md.
    """

    host: Annotated[str, Field(min_length=1)]
    #: Bound on each connection step (probe, dashboard, the ur-rtde constructors' handshake).
    connect_timeout_s: Positive = _UR.connect_timeout_s
    #: No new controller time stamp for this long → DeviceTimeout (link lost, controller hung).
    state_timeout_s: Positive = _UR.state_timeout_s
    #: Bound on a blocking control call (speedStop, stopScript, disconnect).
    command_timeout_s: Positive = _UR.command_timeout_s
    #: speedL's acceleration (m/s², and rad/s² for rotation) when a command gives none.
    speed_acceleration: Positive = _UR.speed_acceleration
    #: speedStop's deceleration (m/s²) for stop commands.
    stop_deceleration: Positive = _UR.stop_deceleration
    #: The controller stops the control script when commands stop coming at this rate (0: off).
    watchdog_min_frequency_hz: Annotated[float, Field(ge=0.0)] = _UR.watchdog_min_frequency_hz
    #: Rate of the state stream (None: the controller's own, 500 Hz on e-Series).
    receive_frequency_hz: Annotated[float, Field(gt=0.0, le=500.0)] | None = (
        _UR.receive_frequency_hz
    )
    #: Use RTDE registers 24–47 (when a fieldbus adapter already uses 0–23).
    upper_range_registers: bool = _UR.upper_range_registers
    reconnect_attempts: Annotated[int, Field(ge=1, le=100)] = _UR.reconnect_attempts
    reconnect_backoff_s: Positive = _UR.reconnect_backoff_s

    def options(self) -> URArmOptions:
        names = {f.name for f in dataclasses.fields(URArmOptions)}
        return URArmOptions(**self.model_dump(include=names))

    def driver(self) -> URArm:
        """The (unconnected) driver this configuration describes."""
        return URArm(self.host, self.options())


# --- which backend drives each device (the trial's ``devices:`` section) ------------------------


class SimDevice(Strict):
    """The simulated device of the simulated world (the default)."""

    backend: Literal["sim"] = "sim"


class URArmDevice(URArmConfig):
    """The arm on ur-rtde (``URArm``). ``emulate``: start the UR controller emulator on
    ``host`` (a 127.x.y.z address) in front of the simulated world's arm."""

    backend: Literal["ur_rtde"]
    emulate: bool = False


class ModbusDevice(Strict):
    """A device on Modbus TCP at ``host``:``port``, ``device_id`` (unit id). ``timeout_s``
    bounds connecting and every reply: a silent device is reported within two time-outs and
    two ``io_period_s`` of its last reply (keep it well below a second). The device is read, and
    commanded, every ``io_period_s`` on an I/O thread of its own (``drivers.threaded_io``), so a
    control tick never waits on a round trip. ``emulate``: serve the simulated model there."""

    backend: Literal["modbus"]
    emulate: bool = False
    host: Annotated[str, Field(min_length=1)]
    port: Annotated[int, Field(ge=1, le=65535)] = 502
    device_id: Annotated[int, Field(ge=0, le=247)]
    timeout_s: Annotated[float, Field(gt=0.0, le=5.0)] = 0.1
    io_period_s: Annotated[float, Field(gt=0.0, le=0.5)] = 0.01

    def endpoint(self) -> ModbusEndpoint:
        return ModbusEndpoint(
            host=self.host, port=self.port, device_id=self.device_id, timeout_s=self.timeout_s
        )


class ModbusTrackDevice(ModbusDevice):
    """The track's axis controller on Modbus TCP (``ModbusTrack``, docs/track_modbus.md).
    ``command_timeout_s``: the host-side watchdog — a moving track the control loop has not
    commanded for this long is stopped by the I/O thread (``ThreadedTrack``)."""

    device_id: Annotated[int, Field(ge=0, le=247)] = 1
    command_timeout_s: Annotated[float, Field(gt=0.0, le=2.0)] = TRACK_COMMAND_TIMEOUT_S


class RobotiqGripperDevice(ModbusDevice):
    """A Robotiq 2F gripper on Modbus TCP (``RobotiqGripper``; RTU behind a gateway or the UR's
    tool-communication bridge). Its activation (the fingers calibrate) must finish within
    ``activation_timeout_s``."""

    device_id: Annotated[int, Field(ge=0, le=247)] = 9
    io_period_s: Annotated[float, Field(gt=0.0, le=0.5)] = 0.02  # its state changes slowly
    activation_timeout_s: Annotated[float, Field(gt=0.0, le=60.0)] = 10.0


class OakCameraDevice(OakCameraConfig):
    """An OAK camera (``oak``), or a recording replayed through the same driver (``replay``,
    with a ``replay:`` block)."""

    backend: Literal["oak", "replay"]

    @model_validator(mode="after")
    def _replay_block(self) -> OakCameraDevice:
        if self.backend == "replay" and self.replay is None:
            raise ValueError("backend replay needs a replay: block (video, calibration)")
        if self.backend == "oak" and self.replay is not None:
            raise ValueError("backend oak is the live camera: drop the replay: block")
        return self


ArmDevice = Annotated[SimDevice | URArmDevice, Field(discriminator="backend")]
CameraDevice = Annotated[SimDevice | OakCameraDevice, Field(discriminator="backend")]
TrackDevice = Annotated[SimDevice | ModbusTrackDevice, Field(discriminator="backend")]
GripperDevice = Annotated[SimDevice | RobotiqGripperDevice, Field(discriminator="backend")]


class DevicesConfig(Strict):
    """Which backend drives each device. Three coherent rigs:

    * ``sim`` — every device simulated (the default): the simulated world;
    * ``emulated`` — arm ``ur_rtde``, track and gripper ``modbus``, each with ``emulate: true``:
      the real drivers against loopback emulators in front of the simulated world; the camera
      ``sim`` renders what the emulated arm does (or ``replay``/``oak``);
    * ``real`` — arm ``ur_rtde``, track and gripper ``modbus`` without ``emulate``, camera
      ``oak`` (or ``replay``): the rig.

    A simulated device beside a real one, or an emulated one beside a real one, would not share
    one world (the camera would not see what the arm does), and is refused.
    """

    arm: ArmDevice = SimDevice()
    camera: CameraDevice = SimDevice()
    track: TrackDevice = SimDevice()
    gripper: GripperDevice = SimDevice()

    @property
    def kind(self) -> Literal["sim", "emulated", "real"]:
        if isinstance(self.arm, SimDevice):
            return "sim"
        return "emulated" if self.arm.emulate else "real"

    @model_validator(mode="after")
    def _one_rig(self) -> DevicesConfig:
        movers = {"arm": self.arm, "track": self.track, "gripper": self.gripper}
        simulated = [name for name, device in movers.items() if isinstance(device, SimDevice)]
        if simulated and len(simulated) < len(movers):
            real = next(name for name in movers if name not in simulated)
            raise ValueError(
                f"{simulated[0]} is simulated but {real} is {movers[real].backend}: either "
                "every device is sim or none of arm, track, gripper is (emulate: true runs the "
                "real drivers against the simulated world)"
            )
        if simulated:
            if not isinstance(self.camera, SimDevice):
                raise ValueError("camera: a real camera needs the real (or emulated) arm it rides")
            return self
        emulated = {name: device.emulate for name, device in movers.items()}
        if len(set(emulated.values())) > 1:
            on = [n for n, e in emulated.items() if e]
            off = [n for n, e in emulated.items() if not e]
            raise ValueError(
                f"{', '.join(on)} emulated but {', '.join(off)} not: the emulators share one "
                "simulated world, so emulate all of arm, track and gripper or none"
            )
        if isinstance(self.camera, SimDevice) and not self.arm.emulate:
            raise ValueError(
                "camera: sim renders the simulated world, which a real arm does not move: use "
                "backend oak (or replay)"
            )
        return self
