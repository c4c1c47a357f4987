"""The fused system as a fourth in the open-loop test matrix: the three systems' measurements
of each frame go through the same fusion filter the closed loop uses (``PoseFusion``), and the
filter's estimate at the frame's capture stamp is judged like any system's answer.

In the matrix the camera stands still while the target maneuvers about its nominal pose, so the
carriage frame M is that nominal pose and ``X_CM`` is fixed for the whole case (the maneuver is
target motion the filter has to follow, as in the reference study). Each system keeps its own tracker
(its own prior), so the single-system rows of a case are unchanged by the fused one.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

from configuration.simulation import load_simulation
from estimators.frame import Frame
from estimators.fusion import FusionParams, PoseFusion
from estimators.geometry import Pose
from estimators.measurement import Measurement
from estimators.target import TargetModel

FUSED = "fused"


#: White-acceleration spectral densities for the matrix's maneuvers: a 10° or 10 cm sine over
#: one second peaks at 6.9 rad/s² and 3.9 m/s²; q ≈ a²·0.2 s lets the filter follow that within
#: a few frames. The closed loop's mock-up sits still (1e-5, 1e-6), and with those settings
#: the filter gates every measurement of a maneuvering target out (fused error = the maneuver's
#: amplitude: 10.1° on 10° about y at 2 m, low noise; 0.08° with these).
MANEUVER_ANGULAR_ACCEL_PSD = 10.0
MANEUVER_LINEAR_ACCEL_PSD = 2.0


def default_fusion_params() -> FusionParams:
    """The closed loop's fusion settings (``configs/sim.yaml``: calibrated covariances) with
    process noise for the matrix's maneuvering target."""
    return dataclasses.replace(
        load_simulation("sim").fusion,
        angular_accel_psd=MANEUVER_ANGULAR_ACCEL_PSD,
        linear_accel_psd=MANEUVER_LINEAR_ACCEL_PSD,
    )


class OpenLoopFusion:
    """Fuses each frame's measurements of a static camera (``X_CM``: the carriage in the camera,
    fixed for the case) and answers as a ``Measurement`` of system ``fused``."""

    def __init__(self, target: TargetModel, X_CM: Pose, params: FusionParams | None = None):
        self.X_CM = X_CM
        self.fusion = PoseFusion(target, params if params is not None else default_fusion_params())

    def update(self, frame: Frame, measurements: Sequence[Measurement]) -> Measurement:
        """The fused estimate at ``frame.stamp`` after this frame's measurements: ``tracking``
        with the pose and its 6×6 covariance in C while the track is ``ok`` or ``coasting``,
        else ``lost`` with the filter's health as the reason."""
        estimate = self.fusion.update(list(measurements), self.X_CM, frame.stamp)
        if estimate.health not in ("ok", "coasting") or estimate.X_MT is None:
            return Measurement.lost(FUSED, frame, f"fusion {estimate.health}")
        return Measurement(
            FUSED,
            "tracking",
            frame.stamp,
            frame.seq,
            X_CT=estimate.X_CT(self.X_CM),
            covariance=estimate.pose_covariance_C(self.X_CM),
        )
