"""Fast stand-ins for the devices, the world and the estimators, to test the loop's logic and
fault paths without rendering. The real simulated rig is tested in its own modules and end to
end."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from drivers.base import (
    ArmState,
    DeviceFault,
    DeviceTimeout,
    GripperState,
    ServoCommand,
    TrackState,
)
from drivers.clock import SimClock
from estimators.frame import CameraInfo, Frame, GroundTruth
from estimators.geometry import Pose, intrinsics_from_fov
from estimators.measurement import Measurement
from estimators.target import facing_camera
from hil.runtime.rig import RigGeometry
from sim_backends.camera import StreamingSimCamera

INFO = CameraInfo(64, 48, intrinsics_from_fov(64, 48, 70.0), np.zeros(0), "tiny")
AXIS_W = np.array([1.0, 0.0, 0.0])


def rig_geometry() -> RigGeometry:
    # Target T faces −x_W (its z axis along −x); carriage frame M = T at track position 0.
    X_WM0 = Pose.from_rpy(0.0, -math.pi / 2, 0.0, np.array([3.0, 0.0, 1.0]))
    X_EC = Pose.from_rpy(0.0, 0.0, math.pi / 2, np.array([0.0, 0.05, 0.08]))
    return RigGeometry(
        X_WB=Pose.identity(), X_EC=X_EC, track_axis_W=AXIS_W, X_WM0=X_WM0, max_track_speed=0.3
    )


@dataclass
class FakeArm:
    """Integrates the commanded flange twist exactly, brakes to rest at the stop's deceleration
    (both parts reaching zero together, like ``SimArm``); faults on demand."""

    clock: SimClock
    X_BE: Pose
    V_BE: np.ndarray = field(default_factory=lambda: np.zeros(6))
    protective_stop: bool = False
    link_down: bool = False
    stops: list = field(default_factory=list)
    braking: float | None = None  # the deceleration of a stop in progress

    def connect(self):
        pass

    def activate(self):
        pass

    def deactivate(self):
        pass

    def close(self):
        pass

    def state(self) -> ArmState:
        if self.link_down:
            raise DeviceTimeout("arm link down")
        return ArmState(
            self.clock.now(),
            np.zeros(6),
            self.X_BE,
            self.V_BE,
            protective_stop=self.protective_stop,
        )

    def servo(self, command: ServoCommand) -> None:
        if self.protective_stop:
            raise DeviceFault("protective stop")
        self.V_BE = command.V_BE.copy()
        self.braking = None

    def stop(self, deceleration: float = 2.0) -> None:
        self.braking = deceleration
        self.stops.append(self.clock.now())

    def advance(self, dt: float) -> None:
        if self.braking is not None:
            largest = max(np.linalg.norm(self.V_BE[:3]), np.linalg.norm(self.V_BE[3:]))
            slower = max(0.0, largest - self.braking * dt)
            self.V_BE = self.V_BE * (slower / largest) if largest > 0 else self.V_BE
        w, v = self.V_BE[3:], self.V_BE[:3]
        self.X_BE = Pose(
            Pose.from_rotvec(w * dt, np.zeros(3)).R @ self.X_BE.R, self.X_BE.p + v * dt
        )


@dataclass
class FakeTrack:
    clock: SimClock
    position: float = 0.0
    velocity: float = 0.0
    fault: str | None = None

    def connect(self):
        pass

    def activate(self):
        pass

    def deactivate(self):
        pass

    def close(self):
        pass

    def state(self) -> TrackState:
        return TrackState(
            self.clock.now(), self.position, self.velocity, self.velocity != 0, self.fault
        )

    def move_velocity(self, velocity: float) -> None:
        self.velocity = velocity

    def move_to(self, position: float, speed: float) -> None:
        raise NotImplementedError

    def stop(self) -> None:
        self.velocity = 0.0

    def advance(self, dt: float) -> None:
        self.position += self.velocity * dt


@dataclass
class FakeGripper:
    clock: SimClock
    closing_since: float | None = None
    opening_since: float | None = None
    object_present: bool = True

    def connect(self):
        pass

    def activate(self):
        pass

    def deactivate(self):
        pass

    def close(self):
        pass

    def grip(self):
        self.closing_since, self.opening_since = self.clock.now(), None

    def open(self):
        self.opening_since, self.closing_since = self.clock.now(), None

    def state(self) -> GripperState:
        t = self.clock.now()
        if self.closing_since is not None:
            moving = t - self.closing_since < 0.3
            return GripperState(
                t,
                True,
                0.5 if self.object_present else 1.0,
                moving,
                self.object_present and not moving,
            )
        if self.opening_since is not None:
            return GripperState(t, True, 0.0, t - self.opening_since < 0.3, False)
        return GripperState(t, True, 0.0, False, False)


class FakeStillCamera:
    """Draws a blank frame carrying the truth of the moment (what ``StreamingSimCamera`` wraps);
    its frame number is written into the first pixels, as a live sensor's noise makes every
    frame differ. ``frozen``: the image stops changing (a stuck driver), stamps go on."""

    def __init__(self, world: FakeWorld):
        self.world = world
        self.seq = 0
        self.streaming = False
        self.corrupt_next = False
        self.frozen = False
        self._last_image: np.ndarray | None = None

    @property
    def info(self) -> CameraInfo:
        return INFO

    def connect(self):
        pass

    def activate(self):
        self.streaming = True

    def deactivate(self):
        self.streaming = False

    def close(self):
        self.streaming = False

    def render_frame(self) -> Frame:
        truth = self.world.truth()
        X_CT = truth["X_WC"].inverse() @ truth["X_WT"]
        image = np.zeros((48, 64), np.uint8)
        image[0, :4] = np.frombuffer(np.uint32(self.seq).tobytes(), np.uint8)
        if self.frozen and self._last_image is not None:
            image = self._last_image
        self._last_image = image
        if self.corrupt_next:
            self.corrupt_next = False
            image = np.zeros((10, 10), np.uint8)
        frame = Frame(
            image, self.world.clock.now(), INFO, self.seq, GroundTruth(X_CT, truth["X_WC"])
        )
        self.seq += 1
        return frame


class FakeWorld:
    """Advances the fakes and the clock, captures frames at ``fps`` that arrive ``latency_s``
    later; knows the truth."""

    def __init__(
        self, clock, arm, track, geometry, X_MT: Pose | None = None, fps=15.0, latency_s=0.12
    ):
        self.clock, self.arm, self.track, self.geometry = clock, arm, track, geometry
        self.X_MT = X_MT or Pose.identity()
        self.still = FakeStillCamera(self)
        self.camera = StreamingSimCamera(
            self.still, latency_s=latency_s, jitter_s=0.0, seed=0, clock=clock.now
        )
        self.camera.connect()
        self.camera.activate()
        self.frames_stopped = False
        self._period = 1.0 / fps
        self._next_capture = clock.now()

    def advance(self, dt: float) -> None:
        end = self.clock.now() + dt
        while (now := self.clock.now()) < end - 1e-12:
            step = min(end, self._next_capture) - now
            if step > 0:
                self.arm.advance(step)
                self.track.advance(step)
                self.clock.advance(step)
            if self.clock.now() >= self._next_capture - 1e-12:
                if not self.frames_stopped:
                    self.camera.capture()
                self._next_capture += self._period

    def truth(self) -> dict[str, Pose]:
        return {
            "X_WT": self.geometry.X_WM(self.track.position) @ self.X_MT,
            "X_WC": self.geometry.X_WC(self.arm.X_BE),
        }


class TruthEstimator:
    """Returns the true pose with small seeded noise; can be blinded, made to raise or to
    return NaN."""

    def __init__(self, system: str, seed: int = 0):
        self.system = system
        self.rng = np.random.default_rng(seed)
        self.blind = False
        self.raise_error = False
        self.nan = False

    def estimate(self, frame: Frame, prior_X_CT=None) -> Measurement:
        if self.raise_error:
            raise RuntimeError("injected estimator failure")
        if self.blind:
            return Measurement.lost(self.system, frame, "blinded")
        X = frame.truth.X_CT
        noisy = Pose.from_rotvec(self.rng.normal(0, 1e-4, 3), np.zeros(3)) @ X
        noisy = Pose(noisy.R, X.p + self.rng.normal(0, 2e-4, 3))
        m = Measurement(
            system=self.system,
            status="tracking" if prior_X_CT is not None else "acquired",
            stamp=frame.stamp,
            seq=frame.seq,
            X_CT=noisy,
            covariance=np.eye(6) * 1e-7,
        )
        if self.nan:
            object.__setattr__(
                m.X_CT, "p", np.array([np.nan, 0.0, 1.0])
            )  # bypass validation on purpose
        return m


def start_X_BE(
    geometry: RigGeometry, distance: float = 2.5, offset=(0.2, -0.15), tilt_deg=6.0
) -> Pose:
    """Flange pose putting the camera ``distance`` in front of the target, off-centre and tilted
    by ``tilt_deg`` about its optical axis (and half that about the other two) from the
    stand-off's orientation — within the flange's rotation envelope, as a rig's start is."""
    X_WT = geometry.X_WM(0.0)
    tilt = math.radians(tilt_deg)
    X_TC = (
        Pose(np.eye(3), np.array([offset[0], offset[1], 0.0]))
        @ facing_camera(distance)
        @ Pose.from_rpy(tilt / 2, -tilt / 2, tilt, np.zeros(3))
    )
    return geometry.X_WB.inverse() @ X_WT @ X_TC @ geometry.X_EC.inverse()
