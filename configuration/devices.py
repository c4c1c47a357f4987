"""Configuration of the real devices' drivers (addresses, streams, replays).

Every model is frozen and rejects unknown keys.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field

from configuration.base import Positive, Strict
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
        return URArmOptions(**self.model_dump(exclude={"host"}))

    def driver(self) -> URArm:
        """The (unconnected) driver this configuration describes."""
        return URArm(self.host, self.options())
