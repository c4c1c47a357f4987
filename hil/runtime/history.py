"""Where the camera was when a frame was taken: a short history of the arm's flange pose and
the track's position, interpolated at a past stamp.

A frame shows the world as it was when it was exposed, not when the pipeline gets it (a real
OAK delivers frames 100–130 ms late, and processing adds tens of milliseconds), so the
camera-to-carriage pose that goes with a measurement is the one at the frame's capture stamp:
flange position linear and rotation slerped between the two nearest samples, track position
linear. Without this, the arm's and the track's own motion since the exposure would look like
target motion to fusion.
"""

from __future__ import annotations

import bisect
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np

from estimators.geometry import Pose
from estimators.so3 import exp_so3, log_so3
from hil.runtime.rig import RigGeometry

T = TypeVar("T")


@dataclass(frozen=True, slots=True, eq=False)
class StateSample:
    """The arm's flange pose and the track's position, each at its own device stamp: what the
    control loop hands the vision pipeline every tick."""

    arm_stamp: float
    X_BE: Pose
    track_stamp: float
    track_position: float


class StampedSeries(Generic[T]):
    """Values with increasing stamps over the last ``horizon_s`` seconds, interpolated at any
    stamp inside by ``interpolate(earlier, later, fraction)``."""

    def __init__(self, interpolate: Callable[[T, T, float], T], horizon_s: float = 2.0):
        self._interpolate = interpolate
        self.horizon_s = horizon_s
        self._stamps: list[float] = []
        self._values: list[T] = []

    def add(self, stamp: float, value: T) -> None:
        if self._stamps and stamp <= self._stamps[-1]:
            if stamp == self._stamps[-1]:
                self._values[-1] = value
                return
            raise ValueError(f"stamps must increase ({stamp} after {self._stamps[-1]})")
        self._stamps.append(stamp)
        self._values.append(value)
        old = bisect.bisect_left(self._stamps, stamp - self.horizon_s)
        if old > 0:
            del self._stamps[:old], self._values[:old]

    def at(self, stamp: float, *, extrapolate_s: float = 0.05) -> T | None:
        """The value at ``stamp``: interpolated inside the history, the newest one up to
        ``extrapolate_s`` after it; None when older than the history or further ahead."""
        if not self._stamps or stamp < self._stamps[0]:
            return None
        if stamp >= self._stamps[-1]:
            return self._values[-1] if stamp - self._stamps[-1] <= extrapolate_s else None
        i = bisect.bisect_right(self._stamps, stamp)
        t0, t1 = self._stamps[i - 1], self._stamps[i]
        return self._interpolate(self._values[i - 1], self._values[i], (stamp - t0) / (t1 - t0))


def interpolate_pose(X0: Pose, X1: Pose, s: float) -> Pose:
    """The pose a fraction ``s`` of the way from ``X0`` to ``X1``: position linear, rotation
    slerped."""
    R = X0.R @ exp_so3(s * log_so3(X0.R.T @ X1.R))
    return Pose(R, (1.0 - s) * X0.p + s * X1.p)


def interpolate_linear(x0: float, x1: float, s: float) -> float:
    return (1.0 - s) * x0 + s * x1


class StateHistory:
    """The camera-to-carriage pose ``X_CM`` at any recent stamp, from the samples the control
    loop publishes."""

    def __init__(self, geometry: RigGeometry, horizon_s: float = 2.0):
        self.geometry = geometry
        self._X_BE = StampedSeries(interpolate_pose, horizon_s)
        self._track = StampedSeries(interpolate_linear, horizon_s)

    def add(self, sample: StateSample) -> None:
        self._X_BE.add(sample.arm_stamp, sample.X_BE)
        self._track.add(sample.track_stamp, sample.track_position)

    def X_CM_at(self, stamp: float) -> Pose | None:
        """``X_CM`` at ``stamp``, or None when the history does not cover it."""
        X_BE = self._X_BE.at(stamp)
        position = self._track.at(stamp)
        if X_BE is None or position is None:
            return None
        return self.geometry.X_CM(X_BE, position)


class StateRing:
    """``StateSample``s from the control process to the vision process through shared memory:
    the control loop writes without a system call and can never be held up by a reader that
    falls behind (a pipe would block the loop once its buffer filled).

    A ring of ``capacity`` slots of 16 float64 (arm stamp, X_BE as 12 numbers, track stamp,
    track position, spare) after a header holding the count of samples written. The writer
    fills a slot, then bumps the count; a reader takes the slots between its own count and the
    writer's (only the newest ``capacity`` if it fell further behind). One writer, any readers.
    """

    _FIELDS = 16

    def __init__(self, name: str | None = None, capacity: int = 1024):
        from multiprocessing import shared_memory

        size = 8 * (1 + capacity * self._FIELDS)
        if name is None:
            self._shm = shared_memory.SharedMemory(create=True, size=size)
            self._owner = True
        else:
            self._shm = shared_memory.SharedMemory(name=name)
            self._owner = False
        self.capacity = capacity
        self._count = np.ndarray((1,), dtype=np.int64, buffer=self._shm.buf)
        self._slots = np.ndarray(
            (capacity, self._FIELDS), dtype=np.float64, buffer=self._shm.buf, offset=8
        )
        if self._owner:
            self._count[0] = 0
        self._read = 0

    @property
    def name(self) -> str:
        return self._shm.name

    def write(self, sample: StateSample) -> None:
        count = int(self._count[0])
        slot = self._slots[count % self.capacity]
        slot[0] = sample.arm_stamp
        slot[1:10] = sample.X_BE.R.reshape(-1)
        slot[10:13] = sample.X_BE.p
        slot[13] = sample.track_stamp
        slot[14] = sample.track_position
        self._count[0] = count + 1  # published only once the slot is complete

    def read_new(self) -> list[StateSample]:
        """The samples written since this reader's last call, oldest first."""
        count = int(self._count[0])
        start = max(self._read, count - self.capacity + 1)
        samples = []
        for i in range(start, count):
            slot = self._slots[i % self.capacity].copy()
            X_BE = Pose.unchecked(slot[1:10].reshape(3, 3), slot[10:13])
            samples.append(StateSample(float(slot[0]), X_BE, float(slot[13]), float(slot[14])))
        self._read = count
        return samples

    def close(self) -> None:
        self._count = self._slots = None  # release the views before the mapping
        self._shm.close()
        if self._owner:
            self._shm.unlink()
