"""An estimator that reads the simulator's ground truth: for testing the harness (loop,
supervisor, fault handling) and for fault trials where vision is not the point.

It returns the true ``X_CT`` of the frame's capture instant (``Frame.truth``), optionally
offset, and is lost on every ``lose_every``-th frame. Build it by path like any experimental
estimator: ``systems: ["sim_backends.oracle:build_oracle"]``.
"""

from __future__ import annotations

import numpy as np

from estimators.frame import CameraInfo, Frame
from estimators.geometry import Pose
from estimators.measurement import Measurement
from estimators.target import TargetModel

#: The oracle's systems entry in a simulation config.
ORACLE_SYSTEM = "sim_backends.oracle:build_oracle"


class Oracle:
    """Returns the true pose (plus a fixed offset), lost on every ``lose_every``-th frame."""

    system = "oracle"

    def __init__(
        self, target: TargetModel, camera: CameraInfo, offset_m: float = 0.0, lose_every: int = 0
    ):
        self.offset = np.array([offset_m, 0.0, 0.0])
        self.lose_every = lose_every

    def estimate(self, frame: Frame, prior_X_CT: Pose | None = None) -> Measurement:
        if self.lose_every and frame.seq % self.lose_every == self.lose_every - 1:
            return Measurement.lost(self.system, frame, "forced loss")
        if frame.truth is None:
            return Measurement.lost(self.system, frame, "no ground truth (not a simulated frame)")
        X = frame.truth.X_CT
        return Measurement(
            system=self.system,
            status="tracking" if prior_X_CT is not None else "acquired",
            stamp=frame.stamp,
            seq=frame.seq,
            X_CT=Pose(X.R, X.p + self.offset),
            covariance=np.eye(6) * 1e-6,
            residual_px=0.1,
        )


def build_oracle(target: TargetModel, camera: CameraInfo, **options) -> Oracle:
    return Oracle(target, camera, **options)
