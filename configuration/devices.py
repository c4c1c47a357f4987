"""Configuration of the real devices' drivers (addresses, streams, replays).

Every model is frozen and rejects unknown keys.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field

from configuration.base import Positive, Strict

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
