"""The safety supervisor: checks run every control tick (a pure function of a snapshot).

Any violation stops the arm and the track (ros2_control's error path: a failing read/write
deactivates the hardware). A *recoverable* violation — the estimate or the frames went away —
sends the sequencer back to ``acquire`` when the policy allows it; every other one aborts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from configuration.approach import ServoConfig, SupervisorConfig
from drivers.base import ArmState
from estimators.geometry import Pose

#: Phases in which something moves; outside them a missing estimate is not a fault.
MOVING_PHASES = frozenset({"approach", "standoff", "grasp", "retreat"})


@dataclass(frozen=True, slots=True)
class SafetySnapshot:
    """What the loop knows at one tick, just before it sends a command."""

    stamp: float
    phase: str
    arm: ArmState | None
    arm_error: str | None
    track_fault: str | None
    estimate_health: str
    estimate_age_s: float
    X_TC_est: Pose | None
    frame_age_s: float
    tick_s: float
    commanded_V_BE: np.ndarray
    commanded_track_velocity: float


@dataclass(frozen=True, slots=True)
class Violation:
    kind: str
    message: str
    recoverable: bool

    def __str__(self) -> str:
        return f"{self.kind}: {self.message}"


def check(
    snap: SafetySnapshot,
    config: SupervisorConfig,
    servo: ServoConfig,
    *,
    max_track_speed: float,
) -> list[Violation]:
    """Every violated rule at this tick (empty when all is well)."""
    found: list[Violation] = []

    def fail(kind: str, message: str, recoverable: bool = False) -> None:
        found.append(Violation(kind, message, recoverable))

    # Devices first: nothing else matters when the arm cannot be trusted.
    if snap.arm_error is not None:
        fail("arm_link", snap.arm_error)
    elif snap.arm is not None and snap.arm.fault_reason is not None:
        fail("arm_fault", snap.arm.fault_reason)
    if snap.track_fault is not None:
        fail("track_fault", snap.track_fault)
    if snap.tick_s > config.max_tick_s:
        fail(
            "deadline", f"tick took {1000 * snap.tick_s:.0f} ms > {1000 * config.max_tick_s:.0f} ms"
        )

    V = np.asarray(snap.commanded_V_BE, dtype=float)
    if not np.all(np.isfinite(V)) or not math.isfinite(snap.commanded_track_velocity):
        fail("command", "non-finite command")
    else:
        # The flange moves faster than the camera when turning (lever arm): margin, not equality.
        if np.linalg.norm(V[:3]) > servo.max_speed * config.speed_margin:
            fail("speed", f"commanded flange speed {np.linalg.norm(V[:3]):.3f} m/s over the limit")
        max_w = math.radians(servo.max_angular_speed_deg) * config.speed_margin
        if np.linalg.norm(V[3:]) > max_w:
            fail(
                "speed",
                f"commanded angular speed {math.degrees(np.linalg.norm(V[3:])):.1f}°/s over the limit",
            )
        if abs(snap.commanded_track_velocity) > max_track_speed * config.speed_margin:
            fail(
                "speed",
                f"commanded track speed {snap.commanded_track_velocity:.3f} m/s over the limit",
            )
    if snap.arm is not None:
        measured = float(np.linalg.norm(snap.arm.V_BE[:3]))
        if measured > servo.max_speed * config.speed_margin * 1.5:
            fail("speed", f"measured flange speed {measured:.3f} m/s over the limit")
        p = snap.arm.X_BE.p
        lo, hi = np.array(config.workspace_min_B), np.array(config.workspace_max_B)
        if np.any(p < lo) or np.any(p > hi):
            fail("workspace", f"flange at {np.round(p, 3).tolist()} m is outside the workspace box")

    if snap.phase in MOVING_PHASES:
        if snap.frame_age_s > config.max_frame_age_s:
            fail("frames", f"no usable frame for {snap.frame_age_s:.2f} s", recoverable=True)
        if snap.estimate_health != "ok":
            fail("estimate", f"estimate is {snap.estimate_health}", recoverable=True)
        elif snap.estimate_age_s > config.max_estimate_age_s:
            fail("estimate", f"estimate is {snap.estimate_age_s:.2f} s old", recoverable=True)
        X_TC = snap.X_TC_est
        if X_TC is None or not (np.all(np.isfinite(X_TC.p)) and np.all(np.isfinite(X_TC.R))):
            fail("estimate", "no finite pose estimate", recoverable=True)
        else:
            range_m = float(X_TC.p[2])
            off_axis = math.degrees(
                math.atan2(float(np.hypot(X_TC.p[0], X_TC.p[1])), max(range_m, 1e-9))
            )
            if range_m <= 0 or off_axis > config.approach_cone_deg:
                fail(
                    "cone",
                    f"camera {off_axis:.1f}° off the ring axis (limit {config.approach_cone_deg}°)",
                )
            if range_m < config.min_range_m:
                fail(
                    "too_close",
                    f"camera {range_m:.3f} m from the ring face (limit {config.min_range_m} m)",
                )
    return found
