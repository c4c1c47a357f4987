"""Estimators for testing the harness itself: the oracle reading the simulator's ground truth
(``sim_backends.oracle``), and ones that raise, see nothing or take their time."""

from __future__ import annotations

import time

from estimators.frame import CameraInfo, Frame
from estimators.geometry import Pose
from estimators.measurement import Measurement
from estimators.target import TargetModel
from sim_backends.oracle import Oracle


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
