"""The safety supervisor: checks run every control tick (a pure function of a snapshot).

It sees exactly what is about to be commanded (the flange twist, the track velocity) and what
was measured (arm, track, the fused estimate), with the previous tick's command and states for
accelerations. Any violation stops the arm and the track in that same tick (ros2_control's
error path: a failing read/write deactivates the hardware). A *recoverable* violation — the
estimate or the frames went away, the target turns too fast to follow — sends the sequencer
back to ``acquire`` (holding still) when the policy allows it; every other one aborts.

Every message names the measured value and its limit. The rules, by group:

* devices: arm link and faults, track faults, the tick's deadline;
* command: finite; nothing moves outside a moving phase; flange and track speeds under their
  maxima; accelerations of the flange (linear, angular) and the track against the previous
  command over one period;
* measured motion: flange speed, flange and track accelerations against states a little older
  (``acceleration_baseline``);
* range: the camera's speed and the track's under the range schedule
  (``hil.runtime.servo.speed_limit``, ``slow_speed`` inside the slow-down distance), and the
  combined closing speed of camera and target along the line of sight (arm + track);
* track travel: the carriage braking at its maximum acceleration from the measured or the
  commanded velocity must stop inside its soft limits (v·T + v²/2a);
* arm envelope: workspace box, the keep-out around the arm's own base, the flange's rotation
  from its start orientation, joint-range margins, the Jacobian's smallest singular value;
* contact: the force and torque the arm reports at the TCP;
* estimate (in moving phases, while it steers the arm or anything moves): frames and estimate
  fresh and healthy, approach cone, keep-out distance; the target's angular rate (also while
  acquiring): hold, then abort.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TypeVar

import numpy as np

from configuration.approach import ServoConfig, SupervisorConfig
from configuration.rig import UR_JOINT_RANGE_DEG
from drivers.base import ArmState, TrackState
from drivers.ur_kinematics import jacobian, ur_model
from estimators.geometry import Pose
from estimators.so3 import log_so3
from hil.runtime.rig import RigGeometry
from hil.runtime.servo import speed_limit

#: Phases in which something moves; outside them a missing estimate is not a fault.
MOVING_PHASES = frozenset({"approach", "standoff", "grasp", "retreat"})
#: Phases in which a turning target must not be locked onto or followed.
WATCHING_PHASES = MOVING_PHASES | {"acquire"}
#: Changes smaller than this (m/s, rad/s) are no motion (a stopped command is exactly zero).
_STILL = 1e-9


@dataclass(frozen=True, slots=True, eq=False)
class SafetySnapshot:
    """What the loop knows at one tick, just before it sends a command.

    ``commanded_*`` is what is about to be sent; ``previous_*`` what was sent (or measured) at
    the tick before (None at the first tick). ``X_TC_est``: the camera in the target frame from
    the fused estimate. ``R_BE_start``: the flange's orientation when the trial started.
    ``target_rate``: the angular rate of the target in the fused estimate (rad/s), and
    ``target_rate_since`` the stamp since which it has stayed above the limit
    (``rate_exceeded_since``)."""

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
    period_s: float = 0.008
    previous_V_BE: np.ndarray | None = None
    previous_track_velocity: float | None = None
    #: Earlier arm and track states to difference measured accelerations against (the loop
    #: passes ones about ``*_ACCELERATION_BASELINE_S`` old, not the previous tick's).
    previous_arm: ArmState | None = None
    track: TrackState | None = None
    previous_track: TrackState | None = None
    R_BE_start: np.ndarray | None = None
    target_rate: float | None = None
    target_rate_since: float | None = None
    #: Whether the estimate steers the arm at this tick (``ApproachSequencer.guided``): not
    #: while the gripper closes, holds or opens at the grasp pose.
    guided: bool = True


@dataclass(frozen=True, slots=True)
class Violation:
    kind: str
    message: str
    recoverable: bool

    def __str__(self) -> str:
        return f"{self.kind}: {self.message}"


def rate_exceeded_since(
    since: float | None, target_rate: float | None, stamp: float, config: SupervisorConfig
) -> float | None:
    """The stamp since which the target's rate has stayed above ``max_target_rate_deg_s``
    (``since`` from the previous tick), or None when it is not above it now."""
    if target_rate is None or target_rate <= math.radians(config.max_target_rate_deg_s):
        return None
    return stamp if since is None else since


#: Measured accelerations are differenced against a state at least this much older than the
#: newest, not the previous tick's: when a device sampled its state is known only to within its
#: update cadence and the host's scheduling, and that jitter over one 8 ms period reads as
#: acceleration. The arm streams its state at 500 Hz (RTDE): 32 ms. The track is polled over
#: Modbus and its drive refreshes its registers at its own pace: 0.1 s, which tolerates a sample
#: up to 50 ms older than its stamp inside the 1.5 acceleration margin (over 32 ms, CI saw the
#: emulated track accelerating at its 0.5 m/s² read 0.81 m/s² against its 0.75 m/s² limit).
#: The arm keeps the shorter one: a sudden stop of the flange must show within a few ticks.
ARM_ACCELERATION_BASELINE_S = 0.032
TRACK_ACCELERATION_BASELINE_S = 0.1

_State = TypeVar("_State", ArmState, TrackState)


def acceleration_baseline(
    states: Sequence[_State], now: _State | None, baseline_s: float
) -> _State | None:
    """The newest of ``states`` (oldest first) at least ``baseline_s`` older than ``now``: the
    state to difference ``now`` against (the oldest one while none is that old yet)."""
    if now is None or not states:
        return None
    for state in reversed(states):
        if now.stamp - state.stamp >= baseline_s:
            return state
    return states[0]


def check(
    snap: SafetySnapshot,
    config: SupervisorConfig,
    servo: ServoConfig,
    rig: RigGeometry,
) -> list[Violation]:
    """Every violated rule at this tick (empty when all is well)."""
    found: list[Violation] = []

    def fail(kind: str, message: str, recoverable: bool = False) -> None:
        found.append(Violation(kind, message, recoverable))

    _devices(snap, config, fail)
    V = np.asarray(snap.commanded_V_BE, dtype=float)
    u = float(snap.commanded_track_velocity)
    if not np.all(np.isfinite(V)) or not math.isfinite(u):
        fail("command", "non-finite command")
    else:
        _command(snap, V, u, config, servo, rig, fail)
        if snap.arm is not None and snap.X_TC_est is not None and snap.phase in MOVING_PHASES:
            _range(snap, V, u, config, servo, rig, fail)
    if snap.arm is not None:
        _measured_arm(snap, snap.arm, config, servo, fail)
        _envelope(snap, snap.arm, config, rig, fail)
    if snap.track is not None:
        _track(snap, snap.track, u if math.isfinite(u) else 0.0, config, rig, fail)
    moving = bool(np.any(np.abs(np.nan_to_num(V, nan=1.0)) > _STILL)) or not abs(u) <= _STILL
    if snap.phase in MOVING_PHASES and (snap.guided or moving):
        # An arm that stands still at the grasp pose whatever the estimate says does not need
        # a fresh one; anything that moves, or is steered by it, does.
        _estimate(snap, config, fail)
    if snap.phase in WATCHING_PHASES:
        _target_rate(snap, config, fail)
    return found


# --- rule groups ----------------------------------------------------------------------------


def _devices(snap: SafetySnapshot, config: SupervisorConfig, fail) -> None:
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


def _command(
    snap: SafetySnapshot,
    V: np.ndarray,
    u: float,
    config: SupervisorConfig,
    servo: ServoConfig,
    rig: RigGeometry,
    fail,
) -> None:
    """The command about to be sent: motion only where motion belongs, speeds, accelerations."""
    moving = np.linalg.norm(V) > _STILL or abs(u) > _STILL
    if moving and snap.phase not in MOVING_PHASES:
        fail("command", f"motion commanded in phase {snap.phase}")
    speed, angular = float(np.linalg.norm(V[:3])), float(np.linalg.norm(V[3:]))
    # The flange moves faster than the camera when turning (lever arm): margin, not equality.
    max_v = servo.max_speed * config.speed_margin
    if speed > max_v:
        fail("speed", f"commanded flange speed {speed:.3f} m/s, limit {max_v:.3f} m/s")
    max_w = math.radians(servo.max_angular_speed_deg) * config.speed_margin
    if angular > max_w:
        fail(
            "speed",
            f"commanded angular speed {math.degrees(angular):.1f}°/s, "
            f"limit {math.degrees(max_w):.1f}°/s",
        )
    max_u = rig.max_track_speed * config.speed_margin
    if abs(u) > max_u:
        fail("speed", f"commanded track speed {u:.3f} m/s, limit ±{max_u:.3f} m/s")

    # Accelerations against what was sent one period before (without the arm's state the
    # loop has no twist to send: the arm rule stops it).
    dt = snap.period_s
    max_a = servo.max_acceleration * config.acceleration_margin
    if snap.previous_V_BE is not None and snap.arm is not None:
        dV = (V - np.asarray(snap.previous_V_BE, dtype=float)) / dt
        a, alpha = float(np.linalg.norm(dV[:3])), float(np.linalg.norm(dV[3:]))
        if a > max_a:
            fail(
                "acceleration",
                f"commanded flange acceleration {a:.2f} m/s², limit {max_a:.2f} m/s²",
            )
        max_alpha = math.radians(servo.max_angular_acceleration_deg) * config.acceleration_margin
        if alpha > max_alpha:
            fail(
                "acceleration",
                f"commanded angular acceleration {math.degrees(alpha):.0f}°/s², "
                f"limit {math.degrees(max_alpha):.0f}°/s²",
            )
    if snap.previous_track_velocity is not None:
        a_track = abs(u - snap.previous_track_velocity) / dt
        if a_track > max_a:
            fail(
                "acceleration",
                f"commanded track acceleration {a_track:.2f} m/s², limit {max_a:.2f} m/s²",
            )


def camera_velocity_B(V_BE: np.ndarray, X_BE: Pose, X_EC: Pose) -> np.ndarray:
    """Velocity (m/s, in B) of the camera's origin for the flange twist ``V_BE`` = [v, ω] in B:
    v + ω × (p_BC − p_BE)."""
    lever_B = X_BE.R @ X_EC.p
    return np.asarray(V_BE[:3], dtype=float) + np.cross(V_BE[3:], lever_B)


def _range(
    snap: SafetySnapshot,
    V: np.ndarray,
    u: float,
    config: SupervisorConfig,
    servo: ServoConfig,
    rig: RigGeometry,
    fail,
) -> None:
    """Speeds against the range schedule: each device's share, and together along the line of
    sight (the camera moving toward the target and the track bringing the target closer add)."""
    assert snap.arm is not None and snap.X_TC_est is not None
    X_TC = snap.X_TC_est
    if not (np.all(np.isfinite(X_TC.p)) and np.all(np.isfinite(X_TC.R))):
        return  # the estimate rules name it
    range_m = float(X_TC.p[2])
    limit = speed_limit(range_m, servo) * config.speed_margin
    X_BE = snap.arm.X_BE
    v_camera_B = camera_velocity_B(V, X_BE, rig.X_EC)
    camera_speed = float(np.linalg.norm(v_camera_B))
    if camera_speed > limit:
        fail(
            "range_speed",
            f"commanded camera speed {camera_speed:.3f} m/s at {range_m:.2f} m range, "
            f"limit {limit:.3f} m/s",
        )
    if abs(u) > limit:
        fail(
            "range_speed",
            f"commanded track speed {abs(u):.3f} m/s at {range_m:.2f} m range, "
            f"limit {limit:.3f} m/s",
        )
    # The carriage carries the target along the track axis (W), seen in B.
    target_v_B = u * (rig.X_WB.R.T @ rig.track_axis_W)
    X_BC = X_BE @ rig.X_EC
    p_CT = X_TC.inverse().p
    distance = float(np.linalg.norm(p_CT))
    if distance <= 0:
        return
    line_of_sight_B = X_BC.R @ (p_CT / distance)
    closing = float((v_camera_B - target_v_B) @ line_of_sight_B)
    if closing > limit:
        fail(
            "closing",
            f"camera and target closing at {closing:.3f} m/s (arm + track) at {range_m:.2f} m "
            f"range, limit {limit:.3f} m/s",
        )


def _measured_arm(
    snap: SafetySnapshot, arm: ArmState, config: SupervisorConfig, servo: ServoConfig, fail
) -> None:
    measured = float(np.linalg.norm(arm.V_BE[:3]))
    max_v = servo.max_speed * config.speed_margin * 1.5
    if measured > max_v:
        fail("speed", f"measured flange speed {measured:.3f} m/s, limit {max_v:.3f} m/s")
    previous = snap.previous_arm
    if previous is None:
        return
    dt = arm.stamp - previous.stamp
    if dt < 0.5 * snap.period_s:
        return  # the same state read twice (or clocks that disagree): nothing to differentiate
    dV = (np.asarray(arm.V_BE) - np.asarray(previous.V_BE)) / dt
    a, alpha = float(np.linalg.norm(dV[:3])), float(np.linalg.norm(dV[3:]))
    if a > config.max_measured_acceleration:
        fail(
            "acceleration",
            f"measured flange acceleration {a:.2f} m/s², "
            f"limit {config.max_measured_acceleration:.2f} m/s²",
        )
    max_alpha = math.radians(config.max_measured_angular_acceleration_deg)
    if alpha > max_alpha:
        fail(
            "acceleration",
            f"measured angular acceleration {math.degrees(alpha):.0f}°/s², "
            f"limit {config.max_measured_angular_acceleration_deg:.0f}°/s²",
        )


def _envelope(
    snap: SafetySnapshot, arm: ArmState, config: SupervisorConfig, rig: RigGeometry, fail
) -> None:
    """Where the arm is: workspace box, base keep-out, flange rotation, joints, singularity."""
    p = arm.X_BE.p
    lo, hi = np.array(config.workspace_min_B), np.array(config.workspace_max_B)
    if np.any(p < lo) or np.any(p > hi):
        fail(
            "workspace",
            f"flange at {np.round(p, 3).tolist()} m is outside the workspace box "
            f"{list(config.workspace_min_B)}…{list(config.workspace_max_B)} m",
        )
    radial = float(np.hypot(p[0], p[1]))
    if radial < config.base_keepout_radius_m and p[2] < config.base_keepout_height_m:
        fail(
            "workspace",
            f"flange {radial:.3f} m from the base axis at {p[2]:.3f} m height, inside the base "
            f"keep-out (radius {config.base_keepout_radius_m} m, up to "
            f"{config.base_keepout_height_m} m)",
        )
    if snap.R_BE_start is not None:
        # Rotation vector of R_E0ᵀ·R_E: about the start flange's own axes.
        turned = np.degrees(log_so3(snap.R_BE_start.T @ arm.X_BE.R))
        axis = int(np.argmax(np.abs(turned)))
        if abs(turned[axis]) > config.max_flange_rotation_deg:
            fail(
                "orientation",
                f"flange turned {turned[axis]:+.1f}° about its start {'xyz'[axis]} axis, "
                f"limit ±{config.max_flange_rotation_deg}°",
            )
    q_deg = np.degrees(np.asarray(arm.q, dtype=float))
    for i, (q, half_range) in enumerate(zip(q_deg, UR_JOINT_RANGE_DEG, strict=True)):
        allowed = half_range - config.joint_margin_deg
        if abs(q) > allowed:
            fail(
                "joint_limit",
                f"joint {i + 1} at {q:+.1f}°, limit ±{allowed:.0f}° "
                f"(range ±{half_range:.0f}° less {config.joint_margin_deg}°)",
            )
    if rig.arm_model is not None and config.min_singular_value > 0:
        sigma_min = float(np.linalg.svd(jacobian(ur_model(rig.arm_model), arm.q))[1][-1])
        if sigma_min < config.min_singular_value:
            fail(
                "singularity",
                f"smallest singular value of the arm's Jacobian {sigma_min:.3f}, "
                f"limit {config.min_singular_value}",
            )
    if arm.wrench_B is not None:
        force = float(np.linalg.norm(arm.wrench_B[:3]))
        torque = float(np.linalg.norm(arm.wrench_B[3:]))
        if force > config.max_contact_force:
            fail("contact", f"force {force:.1f} N at the tool, limit {config.max_contact_force} N")
        if torque > config.max_contact_torque:
            fail(
                "contact",
                f"torque {torque:.2f} N·m at the tool, limit {config.max_contact_torque} N·m",
            )


def stopping_position(position: float, velocity: float, deceleration: float, dt: float) -> float:
    """Where a carriage at ``position`` moving at ``velocity`` comes to rest if it keeps going
    for ``dt`` and then brakes at ``deceleration``: x + v·dt + v·|v|/2a."""
    return position + velocity * dt + velocity * abs(velocity) / (2.0 * deceleration)


def _track(
    snap: SafetySnapshot,
    track: TrackState,
    u: float,
    config: SupervisorConfig,
    rig: RigGeometry,
    fail,
) -> None:
    """Travel with braking distance, and the measured acceleration."""
    a = rig.max_track_acceleration
    if math.isfinite(a):
        low = rig.travel_min + config.track_limit_margin_m
        high = rig.travel_max - config.track_limit_margin_m
        for what, v in (("measured", track.velocity), ("commanded", u)):
            stop = stopping_position(track.position, v, a, snap.period_s)
            if (v > 0 and stop > high) or (v < 0 and stop < low):
                limit = rig.travel_max if v > 0 else rig.travel_min
                fail(
                    "track_travel",
                    f"track at {track.position:.3f} m, {what} {v:+.3f} m/s, would stop at "
                    f"{stop:.3f} m: beyond its soft limit {limit:.3f} m less "
                    f"{config.track_limit_margin_m} m",
                )
                break
    previous = snap.previous_track
    if previous is not None and math.isfinite(a):
        dt = track.stamp - previous.stamp
        if dt >= 0.5 * snap.period_s:
            measured = abs(track.velocity - previous.velocity) / dt
            limit = a * config.acceleration_margin
            if measured > limit:
                fail(
                    "acceleration",
                    f"measured track acceleration {measured:.2f} m/s², limit {limit:.2f} m/s²",
                )


def _estimate(snap: SafetySnapshot, config: SupervisorConfig, fail) -> None:
    if snap.frame_age_s > config.max_frame_age_s:
        fail(
            "frames",
            f"no usable frame for {snap.frame_age_s:.2f} s, limit {config.max_frame_age_s} s",
            recoverable=True,
        )
    if snap.estimate_health != "ok":
        # The loop hands no pose on from an estimate that is not ok: the checks below would
        # only add "no finite pose estimate" to the reason.
        fail("estimate", f"estimate is {snap.estimate_health}", recoverable=True)
        return
    if snap.estimate_age_s > config.max_estimate_age_s:
        fail(
            "estimate",
            f"estimate is {snap.estimate_age_s:.2f} s old, limit {config.max_estimate_age_s} s",
            recoverable=True,
        )
    X_TC = snap.X_TC_est
    if X_TC is None or not (np.all(np.isfinite(X_TC.p)) and np.all(np.isfinite(X_TC.R))):
        fail("estimate", "no finite pose estimate", recoverable=True)
        return
    range_m = float(X_TC.p[2])
    off_axis = math.degrees(math.atan2(float(np.hypot(X_TC.p[0], X_TC.p[1])), max(range_m, 1e-9)))
    if range_m <= 0 or off_axis > config.approach_cone_deg:
        fail(
            "cone",
            f"camera {off_axis:.1f}° off the ring axis, limit {config.approach_cone_deg}°",
        )
    if range_m < config.min_range_m:
        fail(
            "too_close",
            f"camera {range_m:.3f} m from the ring face, limit {config.min_range_m} m",
        )


def _target_rate(snap: SafetySnapshot, config: SupervisorConfig, fail) -> None:
    """A target turning faster than the limit is never followed: hold (recoverable: back to
    acquire, which does not lock while it turns), abort once it has lasted the abort time."""
    if snap.target_rate is None or not math.isfinite(snap.target_rate):
        return
    rate_deg = math.degrees(snap.target_rate)
    if rate_deg <= config.max_target_rate_deg_s:
        return
    lasted = 0.0 if snap.target_rate_since is None else snap.stamp - snap.target_rate_since
    message = f"target rotating at {rate_deg:.1f}°/s, limit {config.max_target_rate_deg_s}°/s"
    if lasted >= config.target_rate_abort_s:
        fail("target_rate", f"{message} (held {lasted:.1f} s)")
    else:
        fail("target_rate", f"{message}: holding", recoverable=True)
