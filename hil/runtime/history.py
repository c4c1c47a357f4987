"""A short history of stamped poses, interpolated at a past stamp.

A frame shows the world as it was when it was exposed, not when the loop gets it (a real OAK
delivers frames ~100 ms late), so the camera pose that goes with a measurement is the arm's
pose at the frame's stamp: linear in position, slerp in rotation between the two nearest
samples.
"""

from __future__ import annotations

from collections import deque

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from estimators.geometry import Pose


class PoseHistory:
    def __init__(self, horizon_s: float = 2.0):
        self.horizon_s = horizon_s
        self._samples: deque[tuple[float, Pose]] = deque()

    def add(self, stamp: float, pose: Pose) -> None:
        if self._samples and stamp <= self._samples[-1][0]:
            if stamp == self._samples[-1][0]:
                self._samples[-1] = (stamp, pose)
                return
            raise ValueError(
                f"PoseHistory stamps must increase ({stamp} after {self._samples[-1][0]})"
            )
        self._samples.append((stamp, pose))
        while self._samples and self._samples[0][0] < stamp - self.horizon_s:
            self._samples.popleft()

    def at(self, stamp: float) -> Pose | None:
        """The pose at ``stamp`` (clamped to the newest sample if later; None if older than
        the history or empty)."""
        if not self._samples:
            return None
        if stamp >= self._samples[-1][0]:
            return self._samples[-1][1]
        if stamp < self._samples[0][0]:
            return None
        for (t0, X0), (t1, X1) in zip(self._samples, list(self._samples)[1:], strict=False):
            if t0 <= stamp <= t1:
                s = (stamp - t0) / (t1 - t0)
                rotations = Rotation.from_matrix(np.stack([X0.R, X1.R]))
                R = Slerp([0.0, 1.0], rotations)([s]).as_matrix()[0]
                return Pose(R, (1 - s) * X0.p + s * X1.p)
        return self._samples[-1][1]
