"""Simulated cameras implementing ``drivers.base.Camera``.

``SimCamera`` renders the scene from a viewpoint source whenever it is read (a still camera for
one-off renders and open-loop evaluations). ``StreamingSimCamera`` behaves like a real one: the
simulated world triggers a capture at the frame rate, and each frame reaches the host ``latency``
± ``jitter`` after its mid-exposure; ``read`` returns the newest frame that has arrived, and a
frame superseded before anyone read it is dropped (counted), as with a newest-only device queue.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from configuration.render import NoiseConfig
from drivers.base import DeviceError, DeviceTimeout
from estimators.frame import CameraInfo, Frame, GroundTruth
from estimators.geometry import Pose
from sim_backends.renderer import Renderer
from sim_backends.sensor import NoisePool, expose, frame_rng


@dataclass(frozen=True, slots=True, eq=False)
class Viewpoint:
    """Where the camera is: ``X_WC``, and its twist [v, ω] relative to the target, in C
    (used for motion blur)."""

    X_WC: Pose
    twist_C: np.ndarray = field(default_factory=lambda: np.zeros(6))


class SimCamera:
    """Renders a frame on every ``read``; frame ``seq`` of seed ``s`` is always the same image
    (unless its noise comes from a ``NoisePool``)."""

    def __init__(
        self,
        renderer: Renderer,
        viewpoint: Callable[[], Viewpoint],
        noise: NoiseConfig | None = None,
        *,
        seed: int = 0,
        clock: Callable[[], float] = time.monotonic,
        noise_draws: NoisePool | None = None,
    ):
        """``noise_draws``: where the sensor noise comes from — by default frame ``seq``'s own
        generator (``frame_rng``), so that a frame is the same image for a seed; a
        ``NoisePool`` for a camera that must keep its frame rate."""
        self._renderer = renderer
        self._viewpoint = viewpoint
        self._noise = noise or NoiseConfig()
        self._seed = seed
        self._noise_draws = noise_draws
        self._clock = clock
        self._seq = 0
        self._connected = False
        self._streaming = False

    @property
    def info(self) -> CameraInfo:
        return self._renderer.info

    @property
    def streaming(self) -> bool:
        return self._streaming

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
        return self.render_frame()

    def render_frame(self, *, stamp: float | None = None, seq: int | None = None) -> Frame:
        """A frame of the scene as it is now, stamped with the clock (the capture instant) —
        or with ``stamp`` and ``seq`` given by whoever triggered the capture."""
        seq = self._seq if seq is None else seq
        view = self._viewpoint()
        rendering = self._renderer.render(view.X_WC)
        image = expose(
            rendering.image,
            rendering.depth_m,
            self.info.K,
            self._noise,
            frame_rng(self._seed, seq) if self._noise_draws is None else self._noise_draws,
            view.twist_C,
        )
        frame = Frame(
            image=image,
            stamp=self._clock() if stamp is None else stamp,
            info=self.info,
            seq=seq,
            truth=GroundTruth(X_CT=rendering.X_CT, X_WC=rendering.X_WC),
            exposure_s=self._noise.exposure_s,
        )
        self._seq = seq + 1
        return frame


class StreamingSimCamera:
    """A camera that streams: ``capture`` (called by the simulated world at the frame rate)
    renders the scene as it is at that instant; the frame arrives ``latency_s`` ± ``jitter_s``
    (uniform, seeded) later on ``clock``. ``read`` returns the newest arrived frame not read
    before, or raises ``DeviceTimeout`` — it cannot block: simulated time only moves between
    reads.

    Fault injection (``inject_*``): the camera stops delivering (dropout), keeps delivering the
    last image with new stamps (a frozen driver), or delivers one truncated image (corrupt).
    """

    def __init__(
        self,
        camera: SimCamera,
        *,
        latency_s: float,
        jitter_s: float,
        seed: int,
        clock: Callable[[], float],
    ):
        if latency_s < 0 or jitter_s < 0 or jitter_s > latency_s:
            raise ValueError(
                f"camera latency {latency_s} s ± {jitter_s} s: both ≥ 0 and jitter ≤ latency"
            )
        self._camera = camera
        self._latency_s, self._jitter_s = latency_s, jitter_s
        self._rng = np.random.default_rng([seed, 0x1A7E])  # its own stream, apart from noise
        self._clock = clock
        self._in_flight: list[Frame] = []
        self._last_read_seq = -1
        self.frames_dropped = 0
        self._dropout = False
        self._frozen_image: np.ndarray | None = None
        self._freeze = False
        self._corrupt_next = False
        #: (seq, capture stamp, arrival stamp) of the frames a fault affected, in order.
        self.faulty_frames: list[tuple[int, float, float]] = []

    @property
    def info(self) -> CameraInfo:
        return self._camera.info

    def connect(self) -> None:
        self._camera.connect()

    def activate(self) -> None:
        self._camera.activate()

    def deactivate(self) -> None:
        self._camera.deactivate()
        self._in_flight.clear()

    def close(self) -> None:
        self._camera.close()
        self._in_flight.clear()

    def capture(self) -> None:
        """Expose a frame now; it reaches the host after the latency."""
        if not self._camera.streaming or self._dropout:
            return
        frame = self._camera.render_frame()
        jitter = self._rng.uniform(-self._jitter_s, self._jitter_s) if self._jitter_s else 0.0
        arrival = frame.stamp + self._latency_s + jitter
        faulty = self._freeze and self._frozen_image is not None
        if faulty:
            frame = dataclasses.replace(frame, image=self._frozen_image)
        self._frozen_image = frame.image
        if self._corrupt_next:
            self._corrupt_next, faulty = False, True
            frame = dataclasses.replace(frame, image=frame.image[:10, :10])
        if faulty:
            self.faulty_frames.append((frame.seq, frame.stamp, arrival))
        self._in_flight.append(dataclasses.replace(frame, arrival_stamp=arrival))

    def inject_dropout(self) -> None:
        """No frame is captured from now on (frames already in flight still arrive)."""
        self._dropout = True

    def inject_freeze(self) -> None:
        """Every frame from now on repeats the last captured image, with new stamps."""
        self._freeze = True

    def inject_corrupt_frame(self) -> None:
        """The next frame's image is truncated (10×10 pixels)."""
        self._corrupt_next = True

    def read(self, timeout_s: float = 1.0) -> Frame:
        if not self._camera.streaming:
            raise DeviceError(
                "StreamingSimCamera.read: the camera is not streaming (call activate())"
            )
        now = self._clock()
        arrived = [f for f in self._in_flight if f.arrival_stamp <= now]
        if not arrived:
            raise DeviceTimeout("no new frame has arrived")
        newest = max(arrived, key=lambda f: f.seq)
        self._in_flight = [f for f in self._in_flight if f.arrival_stamp > now]
        self.frames_dropped += sum(f.seq > self._last_read_seq for f in arrived) - 1
        self._last_read_seq = newest.seq
        return newest
