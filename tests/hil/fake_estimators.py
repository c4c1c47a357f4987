"""Estimators for testing the harness itself: an oracle reading the simulator's ground truth."""

from __future__ import annotations

import time

import numpy as np

from estimators.frame import CameraInfo, Frame
from estimators.geometry import Pose
from estimators.measurement import Measurement
from estimators.target import TargetModel


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


def build_oracle(target, camera, **options):
    return Oracle(target, camera, **options)


def build_raising(target, camera, **options):
    class Raising:
        system = "raising"

        def estimate(self, frame, prior_X_CT=None):
            raise RuntimeError("boom")

    return Raising()


def build_blind(target, camera, **options):
    class Blind:
        system = "blind"

        def estimate(self, frame, prior_X_CT=None):
            return Measurement.lost(self.system, frame, "sees nothing")

    return Blind()


class Sleepy(Oracle):
    """The oracle, but it takes ``sleep_s`` over every frame (a slow or stuck estimator)."""

    system = "sleepy"

    def __init__(self, target: TargetModel, camera: CameraInfo, sleep_s: float = 0.2):
        super().__init__(target, camera)
        self.sleep_s = sleep_s

    def estimate(self, frame: Frame, prior_X_CT: Pose | None = None) -> Measurement:
        time.sleep(self.sleep_s)
        return super().estimate(frame, prior_X_CT)


def build_sleepy(target, camera, **options):
    return Sleepy(target, camera, **options)
