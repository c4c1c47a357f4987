"""A simulated camera implementing ``drivers.base.Camera``: renders the scene from a viewpoint
source, applies the sensor model and stamps frames with an injected clock."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from configuration.render import NoiseConfig
from drivers.base import DeviceError
from estimators.frame import CameraInfo, Frame, GroundTruth
from estimators.geometry import Pose
from sim_backends.renderer import PybulletRenderer
from sim_backends.sensor import expose, frame_rng


@dataclass(frozen=True, slots=True, eq=False)
class Viewpoint:
    """Where the camera is: ``X_WC``, and its twist [v, ω] relative to the target, in C
    (used for motion blur)."""

    X_WC: Pose
    twist_C: np.ndarray = field(default_factory=lambda: np.zeros(6))


class SimCamera:
    """Renders a frame on every ``read``; frame ``seq`` of seed ``s`` is always the same image."""

    def __init__(
        self,
        renderer: PybulletRenderer,
        viewpoint: Callable[[], Viewpoint],
        noise: NoiseConfig | None = None,
        *,
        seed: int = 0,
        clock: Callable[[], float] = time.monotonic,
    ):
        self._renderer = renderer
        self._viewpoint = viewpoint
        self._noise = noise or NoiseConfig()
        self._seed = seed
        self._clock = clock
        self._seq = 0
        self._connected = False
        self._streaming = False

    @property
    def info(self) -> CameraInfo:
        return self._renderer.info

    def connect(self) -> None:
        self._connected = True

    def activate(self) -> None:
        if not self._connected:
            raise DeviceError("SimCamera.activate: the camera is not connected (call connect())")
        self._streaming = True

    def deactivate(self) -> None:
        self._streaming = False

    def close(self) -> None:
        self._streaming = False
        self._connected = False

    def read(self, timeout_s: float = 1.0) -> Frame:
        if not self._streaming:
            raise DeviceError("SimCamera.read: the camera is not streaming (call activate())")
        view = self._viewpoint()
        rendering = self._renderer.render(view.X_WC)
        image = expose(
            rendering.image,
            rendering.depth_m,
            self.info.K,
            self._noise,
            frame_rng(self._seed, self._seq),
            view.twist_C,
        )
        frame = Frame(
            image=image,
            stamp=self._clock(),
            info=self.info,
            seq=self._seq,
            truth=GroundTruth(X_CT=rendering.X_CT, X_WC=rendering.X_WC),
        )
        self._seq += 1
        return frame
