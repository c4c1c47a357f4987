"""Simulation only: how close the camera really was to the stand-off when the sequencer declared
it reached — the success criterion of a simulated trial, judged against ground truth."""

from __future__ import annotations

import math
from collections.abc import Callable

from estimators.geometry import Pose, rotation_error_geodesic, translation_error
from hil.logs.records import TickRecord, TruthRecord


class StandoffJudge:
    """A tick observer: at the tick that leaves ``standoff`` for ``grasp``, the true camera pose
    error against ``X_TC_goal``; ``event(t, kind, message)`` reports it."""

    def __init__(self, X_TC_goal: Pose, event: Callable[[float, str, str], object]):
        self.X_TC_goal = X_TC_goal
        self._event = event
        self._previous_phase: str | None = None
        self.error_m: float | None = None
        self.error_rad: float | None = None

    def __call__(self, record: TickRecord) -> None:
        reached = self._previous_phase == "standoff" and record.phase == "grasp"
        self._previous_phase = record.phase
        if not reached or record.truth is None:
            return
        X_TC_true = record.truth.X_CT.inverse()
        self.error_m = translation_error(X_TC_true, self.X_TC_goal)
        self.error_rad = rotation_error_geodesic(X_TC_true, self.X_TC_goal)
        self._event(
            record.t,
            "info",
            f"stand-off reached; true error {1000 * self.error_m:.1f} mm, "
            f"{math.degrees(self.error_rad):.2f}°",
        )

    def success(self, position_m: float, angle_rad: float) -> bool:
        """Whether the stand-off was reached within the given true errors."""
        return (
            self.error_m is not None
            and self.error_m <= position_m
            and self.error_rad is not None
            and self.error_rad <= angle_rad
        )


def truth_record(truth: dict[str, Pose]) -> TruthRecord:
    """A tick's ground truth from a simulated world's ``X_WT`` and ``X_WC``."""
    X_WT, X_WC = truth["X_WT"], truth["X_WC"]
    return TruthRecord(X_CT=X_WC.inverse() @ X_WT, X_WT=X_WT, X_WC=X_WC)
