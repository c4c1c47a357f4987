"""The approach sequencer: phases and the motion each phase asks for.

    idle → acquire → approach → standoff → grasp → retreat → done,   and abort from anywhere.

* acquire: hold still until the fused estimate has been healthy for ``lock_s``.
* approach: PBVS toward the stand-off pose; the along-track part of the closing motion goes to
  the linear track, alignment to the arm; speed scheduled down with range.
* standoff: track stopped, the arm refines; declared reached when the estimated error stays
  within tolerance for ``dwell_s``.
* grasp: guarded move of ``advance_m`` along the optical axis at ``grasp.speed``, close the
  gripper, expect an object; optionally hold and release (a HIL rig lets go of its mock-up).
* retreat: back to the stand-off pose, then done.

The sequencer proposes; the supervisor (``hil.runtime.supervisor``) vetoes. ``on_violations`` moves a
recoverable loss back to ``acquire`` and anything else to ``abort``; during the guarded move and
the retreat a recoverable loss *holds* the phase instead — the arm stands still until the
estimate has been healthy for ``lock_s`` again, then the move goes on from where it stopped
(abort if it does not come back within ``acquire_timeout_s``). Time comes in with the
inputs (an injected clock), so the same code runs faster than real time in simulation.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from configuration.approach import ApproachConfig
from drivers.base import GripperState
from estimators.geometry import Pose
from hil.runtime.servo import (
    PoseError,
    goal_keeping_roll,
    limit_command,
    pbvs_twist,
    pose_error,
    saturate,
    speed_limit,
    split_along_track,
)
from hil.runtime.supervisor import Violation


class Phase(StrEnum):
    IDLE = "idle"
    ACQUIRE = "acquire"
    APPROACH = "approach"
    STANDOFF = "standoff"
    GRASP = "grasp"
    RETREAT = "retreat"
    DONE = "done"
    ABORT = "abort"


TERMINAL = frozenset({Phase.DONE, Phase.ABORT})
#: Close enough to the stand-off pose to hand over from the approach to the fine alignment.
_HANDOVER_M = 0.03
_HANDOVER_RAD = math.radians(2.0)


@dataclass(frozen=True, slots=True)
class SequencerInputs:
    """What the sequencer needs at one tick. ``X_TC_est`` is the camera pose in T from the
    fused estimate (None when there is no healthy one); ``R_WC`` the camera's orientation in
    the world and ``track_axis_W`` the track's direction (for splitting the motion);
    ``roll_sigma_rad`` how well the estimate knows the target's roll (the grasp needs it)."""

    stamp: float
    X_TC_est: Pose | None
    estimate_ok: bool
    R_WC: np.ndarray
    track_axis_W: np.ndarray
    max_track_speed: float
    gripper: GripperState | None = None
    #: 1σ (rad) of the fused roll about the ring's axis (``TargetEstimate.roll_sigma_rad``);
    #: unknown until told.
    roll_sigma_rad: float = math.inf


@dataclass(frozen=True, slots=True)
class SequencerOutput:
    phase: Phase
    camera_twist_C: np.ndarray  # the arm's share, camera twist in C
    track_velocity: float
    gripper_command: str | None = None  # "grip" | "open"
    events: tuple[tuple[str, str], ...] = ()
    goal_error: PoseError | None = None


@dataclass
class _GraspState:
    step: str = "advance"  # advance → close → hold → release
    since: float = 0.0


@dataclass
class ApproachSequencer:
    """Stateful phase logic; feed it one ``SequencerInputs`` per control tick."""

    config: ApproachConfig
    phase: Phase = Phase.IDLE
    abort_reason: str = ""
    _phase_since: float = 0.0
    _healthy_since: float | None = None
    _within_since: float | None = None
    _previous_twist: np.ndarray = field(default_factory=lambda: np.zeros(6))
    _previous_track: float = 0.0
    _grasp: _GraspState = field(default_factory=_GraspState)
    _events: list[tuple[str, str]] = field(default_factory=list)
    #: The kinds of recoverable violation holding the acquisition (logged once, not per tick).
    _holding: frozenset[str] = frozenset()
    #: Since when the guarded move or the retreat has been held for the estimate (None: not).
    _held_since: float | None = None
    #: Since when the stand-off, reached, has waited for the roll to be measured (None: not).
    _roll_wait_since: float | None = None

    @property
    def X_TC_goal(self) -> Pose:
        return self.config.standoff.X_TC_goal()

    @property
    def X_TC_grasp(self) -> Pose:
        """The goal of the guarded move: the stand-off pose advanced along the optical axis."""
        return self.X_TC_goal @ Pose(np.eye(3), np.array([0.0, 0.0, self.config.grasp.advance_m]))

    # --- phase bookkeeping --------------------------------------------------------------
    def _enter(self, phase: Phase, stamp: float, why: str) -> None:
        if phase == self.phase:
            return
        self._events.append(("phase", f"{self.phase} → {phase}: {why}"))
        self.phase = phase
        self._phase_since = stamp
        self._within_since = self._roll_wait_since = None
        if phase != Phase.ACQUIRE:
            self._holding = frozenset()
        if phase == Phase.GRASP:
            self._grasp = _GraspState(since=stamp)
        self._held_since = None

    @property
    def guided(self) -> bool:
        """Whether the estimate steers the motion now: in the moving phases, except while the
        gripper closes, holds or opens at the grasp pose (the arm stands still then)."""
        if self._held_since is not None:
            return False
        if self.phase == Phase.GRASP:
            return self._grasp.step == "advance"
        return self.phase in (Phase.APPROACH, Phase.STANDOFF, Phase.RETREAT)

    @property
    def _holdable(self) -> bool:
        """Whether a recoverable loss holds the phase (the guarded move, the retreat)."""
        return self.phase == Phase.RETREAT or (
            self.phase == Phase.GRASP and self._grasp.step == "advance"
        )

    def start(self, stamp: float) -> None:
        self._enter(Phase.ACQUIRE, stamp, "started")

    def abort(self, stamp: float, reason: str) -> None:
        if self.phase not in TERMINAL:
            self.abort_reason = reason
            self._events.append(("abort", reason))
            self._enter(Phase.ABORT, stamp, reason)

    def on_violations(
        self, violations: Sequence[Violation], stamp: float
    ) -> tuple[tuple[str, str], ...]:
        """React to the supervisor's findings (the loop has already stopped the arm)."""
        if not violations or self.phase in TERMINAL:
            return ()
        self._previous_twist = np.zeros(6)
        self._previous_track = 0.0
        text = "; ".join(str(v) for v in violations)
        recoverable = all(v.recoverable for v in violations)
        can_reacquire = self.phase in (Phase.APPROACH, Phase.STANDOFF, Phase.ACQUIRE)
        if recoverable and self.config.supervisor.reacquire and self._holdable:
            if self._held_since is None:
                self._held_since = stamp
                self._events.append(("fault", f"holding the {self.phase}: {text}"))
            self._healthy_since = None
        elif recoverable and self.config.supervisor.reacquire and can_reacquire:
            kinds = frozenset(v.kind for v in violations)
            if self.phase != Phase.ACQUIRE or kinds != self._holding:
                self._events.append(("fault", text))
            self._holding = kinds
            self._healthy_since = None
            self._enter(Phase.ACQUIRE, stamp, f"stopped: {text}")
        else:
            self.abort(stamp, text)
        return self._drain()

    def _drain(self) -> tuple[tuple[str, str], ...]:
        events, self._events = tuple(self._events), []
        return events

    # --- the tick -----------------------------------------------------------------------
    def step(self, inputs: SequencerInputs, dt: float) -> SequencerOutput:
        t = inputs.stamp
        zero = np.zeros(6)
        gripper_command = None
        twist, track = zero, 0.0
        error: PoseError | None = None
        goal = self._goal(inputs, self.X_TC_goal)
        if inputs.X_TC_est is not None:
            error = pose_error(inputs.X_TC_est, goal)

        if self._held_since is not None:
            self._hold(inputs, t)
        elif self.phase == Phase.ACQUIRE:
            self._healthy_since = (self._healthy_since or t) if inputs.estimate_ok else None
            if (
                self._healthy_since is not None
                and t - self._healthy_since >= self.config.supervisor.lock_s
            ):
                self._enter(Phase.APPROACH, t, "estimate locked")
            elif t - self._phase_since > self.config.supervisor.acquire_timeout_s:
                self.abort(t, f"no lock within {self.config.supervisor.acquire_timeout_s:.0f} s")
        elif (
            self.phase in (Phase.APPROACH, Phase.STANDOFF, Phase.RETREAT)
            and inputs.X_TC_est is not None
        ):
            twist, track = self._servo(inputs, goal, use_track=self.phase == Phase.APPROACH)
            assert error is not None
            if (
                self.phase == Phase.APPROACH
                and error.distance_m < _HANDOVER_M
                and error.angle_rad < _HANDOVER_RAD
            ):
                self._enter(
                    Phase.STANDOFF, t, f"within {100 * error.distance_m:.1f} cm of the stand-off"
                )
            elif self.phase == Phase.STANDOFF and self._dwelled(error, t):
                if self._roll_known(inputs.roll_sigma_rad, t):
                    self._enter(Phase.GRASP, t, "stand-off reached")
            elif (
                self.phase == Phase.RETREAT
                and error.distance_m < 2 * self.config.standoff.position_tolerance_m
            ):
                self._enter(Phase.DONE, t, "retreated to the stand-off")
        elif self.phase == Phase.GRASP and inputs.X_TC_est is not None:
            twist, gripper_command = self._grasp_step(inputs, t)
        twist, track = self._limit(twist, track, dt)
        events = self._drain()
        return SequencerOutput(self.phase, twist, track, gripper_command, events, error)

    def _hold(self, inputs: SequencerInputs, t: float) -> None:
        """Stand still until the estimate has been healthy for ``lock_s``, then go on."""
        supervisor = self.config.supervisor
        self._healthy_since = (self._healthy_since or t) if inputs.estimate_ok else None
        assert self._held_since is not None
        if self._healthy_since is not None and t - self._healthy_since >= supervisor.lock_s:
            self._events.append(("info", f"estimate back: the {self.phase} goes on"))
            self._held_since = self._healthy_since = None
        elif t - self._held_since > supervisor.acquire_timeout_s:
            self.abort(
                t, f"estimate not back within {supervisor.acquire_timeout_s:.0f} s in {self.phase}"
            )

    def _dwelled(self, error: PoseError, t: float) -> bool:
        standoff = self.config.standoff
        within = (
            error.distance_m <= standoff.position_tolerance_m
            and error.angle_rad <= math.radians(standoff.angle_tolerance_deg)
        )
        if not within:
            self._within_since = None
            return False
        self._within_since = self._within_since if self._within_since is not None else t
        return t - self._within_since >= standoff.dwell_s

    def _goal(self, inputs: SequencerInputs, goal: Pose) -> Pose:
        """``goal``, or — while the target's roll is not measured — ``goal`` turned about the
        ring's axis to the camera's present roll: the arm never chases a guessed roll."""
        if self._roll_measured(inputs.roll_sigma_rad) or inputs.X_TC_est is None:
            return goal
        return goal_keeping_roll(inputs.X_TC_est, goal)

    def _roll_measured(self, roll_sigma_rad: float) -> bool:
        return math.degrees(roll_sigma_rad) <= self.config.grasp.max_roll_sigma_deg

    def _roll_known(self, roll_sigma_rad: float, t: float) -> bool:
        """Whether the grasp may start: the target's roll is measured. A roll that only a guess
        holds (a ring seen alone, a symmetric panel) refuses the grasp, after waiting up to
        ``acquire_timeout_s`` for a frame that decides it (issue 13)."""
        limit_deg = self.config.grasp.max_roll_sigma_deg
        sigma_deg = math.degrees(roll_sigma_rad)
        if self._roll_measured(roll_sigma_rad):
            if self._roll_wait_since is not None:
                self._events.append(("info", f"roll measured (σ {sigma_deg:.2f}°)"))
            self._roll_wait_since = None
            return True
        timeout = self.config.supervisor.acquire_timeout_s
        if self._roll_wait_since is None:
            self._roll_wait_since = t
            self._events.append(
                (
                    "warning",
                    f"roll not measured (σ {sigma_deg:.1f}° > {limit_deg:g}°): the grasp waits "
                    f"up to {timeout:.0f} s for a view that decides it",
                )
            )
        elif t - self._roll_wait_since > timeout:
            self.abort(t, f"roll not measured (σ {sigma_deg:.1f}° > {limit_deg:g}°): grasp refused")
        return False

    def _servo(
        self, inputs: SequencerInputs, goal: Pose, *, use_track: bool, speed: float | None = None
    ):
        servo = self.config.servo
        X_TC = inputs.X_TC_est
        assert X_TC is not None
        range_m = float(X_TC.p[2])
        max_speed = speed if speed is not None else speed_limit(range_m, servo)
        twist = saturate(
            pbvs_twist(X_TC, goal, servo.gain), max_speed, math.radians(servo.max_angular_speed_deg)
        )
        if not use_track:
            return twist, 0.0
        split = split_along_track(twist, inputs.R_WC, inputs.track_axis_W, inputs.max_track_speed)
        return split.camera_twist_C, split.track_velocity

    def _grasp_step(self, inputs: SequencerInputs, t: float) -> tuple[np.ndarray, str | None]:
        grasp, g = self.config.grasp, self._grasp
        gripper = inputs.gripper
        zero = np.zeros(6)
        if g.step == "advance":
            goal = self._goal(inputs, self.X_TC_grasp)
            twist, _ = self._servo(inputs, goal, use_track=False, speed=grasp.speed)
            assert inputs.X_TC_est is not None
            reached = pose_error(inputs.X_TC_est, goal)
            if reached.distance_m <= 2 * self.config.standoff.position_tolerance_m:
                g.step, g.since = "close", t
                self._events.append(("info", "guarded move done; closing the gripper"))
                return zero, "grip"
            return twist, None
        if g.step == "close":
            if gripper is not None and gripper.object_detected:
                g.step, g.since = "hold", t
                self._events.append(("grasp", "object detected between the fingers"))
            elif gripper is not None and gripper.fault:
                self.abort(t, f"gripper fault: {gripper.fault}")
            elif t - g.since > grasp.close_timeout_s or (
                gripper is not None and not gripper.moving and gripper.position > 0.95
            ):
                self.abort(t, "grasp failed: the gripper closed without an object")
            return zero, None
        if g.step == "hold":
            if t - g.since >= grasp.hold_s:
                if grasp.release_after_grasp:
                    g.step, g.since = "release", t
                    return zero, "open"
                self._enter(Phase.DONE, t, "grasped (holding)")
            return zero, None
        # release: wait for the fingers to open, then retreat
        opened = gripper is None or (not gripper.moving and gripper.position < 0.1)
        if opened or t - g.since > grasp.close_timeout_s:
            self._enter(Phase.RETREAT, t, "released")
        return zero, None

    def _limit(self, twist: np.ndarray, track: float, dt: float) -> tuple[np.ndarray, float]:
        """Acceleration limits on what is actually commanded (also when stopping)."""
        if self.phase in TERMINAL:
            self._previous_twist, self._previous_track = np.zeros(6), 0.0
            return np.zeros(6), 0.0
        limited, track = limit_command(
            twist, track, self._previous_twist, self._previous_track, dt, self.config.servo
        )
        self._previous_twist, self._previous_track = limited, track
        return limited, track
