"""The closed loop: one control tick reads the devices, runs vision when a frame is due, fuses,
lets the sequencer propose and the supervisor dispose, commands, and logs.

The loop sees devices only through their protocols (``drivers.base``); simulation differs only
in the clock (``SimClock``) and a ``World`` that advances the simulated devices between ticks.
Order within a tick (DESIGN.md's data flow):

1. arm, track and gripper state; 2. a frame if one is due → each estimator with the fused prior
→ fusion update (with the camera-to-carriage pose at the frame's stamp); 3. fused estimate now;
4. sequencer step → proposed camera twist, track velocity, gripper action; 5. supervisor check of
exactly what is about to be sent — any violation stops arm and track in this same tick;
6. command; 7. log the tick; 8. wait for the next tick (or advance the simulated world).
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from configuration.approach import ApproachConfig
from drivers.base import (
    Arm,
    ArmState,
    Camera,
    DeviceError,
    Gripper,
    GripperState,
    ServoCommand,
    Track,
    TrackState,
)
from drivers.clock import Clock
from estimators.frame import Frame, frame_problem
from estimators.geometry import Pose
from estimators.measurement import Estimator, Measurement
from hil.runtime.history import PoseHistory
from hil.runtime.sequencer import TERMINAL, ApproachSequencer, Phase, SequencerInputs
from hil.runtime.servo import camera_twist_to_flange, pose_error
from hil.runtime.supervisor import SafetySnapshot, Violation, check


@dataclass(frozen=True, slots=True)
class RigGeometry:
    """Fixed geometry of the rig: arm base ``X_WB``, hand-eye ``X_EC``, and the track (its unit
    axis in W, the carriage pose ``X_WM0`` at position 0, its speed limit)."""

    X_WB: Pose
    X_EC: Pose
    track_axis_W: np.ndarray
    X_WM0: Pose
    max_track_speed: float

    def X_WM(self, track_position: float) -> Pose:
        return Pose(self.X_WM0.R, self.X_WM0.p + track_position * self.track_axis_W)

    def X_WC(self, X_BE: Pose) -> Pose:
        return self.X_WB @ X_BE @ self.X_EC

    def X_CM(self, X_BE: Pose, track_position: float) -> Pose:
        """Pose of the carriage in the camera — what fusion needs to map X_MT to X_CT."""
        return self.X_WC(X_BE).inverse() @ self.X_WM(track_position)


class World(Protocol):
    """A simulation the loop advances between ticks (absent on hardware)."""

    def advance(self, dt: float) -> None: ...

    def truth(self) -> Mapping[str, Pose]: ...


class TickLog(Protocol):
    def write_tick(self, record: dict) -> None: ...

    def write_event(self, t: float, kind: str, message: str, **data: Any) -> None: ...


class NullLog:
    def write_tick(self, record: dict) -> None:
        pass

    def write_event(self, t: float, kind: str, message: str, **data: Any) -> None:
        pass


@dataclass(frozen=True, slots=True)
class TrialOutcome:
    """How a trial ended. ``standoff_error_*`` is the true camera pose error when the
    stand-off was declared reached (simulation only; None on hardware or if never reached)."""

    phase: str
    success: bool
    abort_reason: str
    duration_s: float
    ticks: int
    standoff_error_m: float | None
    standoff_error_rad: float | None


def _measurement_problem(m: Measurement) -> str | None:
    """Why a measurement must not be trusted (non-finite numbers), or None."""
    for name in ("covariance", "center_C", "normal_C", "covariance_5dof"):
        value = getattr(m, name)
        if value is not None and not np.all(np.isfinite(value)):
            return f"{m.system} returned non-finite {name}"
    if m.X_CT is not None and not (np.all(np.isfinite(m.X_CT.R)) and np.all(np.isfinite(m.X_CT.p))):
        return f"{m.system} returned a non-finite pose"
    return None


@dataclass
class ApproachLoop:
    arm: Arm
    track: Track
    gripper: Gripper
    camera: Camera
    estimators: Mapping[str, Estimator]
    fusion: Any  # estimators.fusion.PoseFusion
    geometry: RigGeometry
    config: ApproachConfig
    clock: Clock
    log: TickLog = field(default_factory=NullLog)
    world: World | None = None
    camera_fps: float = 30.0
    frame_log_period_s: float = 1.0
    frame_logger: Any = None  # callable(t, image) for decimated frames, optional

    def __post_init__(self) -> None:
        self.sequencer = ApproachSequencer(self.config)
        self._X_BE_history = PoseHistory()
        self._track_history: list[tuple[float, float]] = []
        self._next_frame_t = -math.inf
        self._last_frame_t: float | None = None
        self._last_logged_frame_t = -math.inf
        self._tick = 0
        self._start_t = 0.0
        self._standoff_error: tuple[float, float] | None = None
        self._read_ms = 0.0
        self._gated = None  # the fusion update of this tick's frame, if any

    # --- helpers ------------------------------------------------------------------------
    def _event(self, t: float, kind: str, message: str, **data: Any) -> None:
        self.log.write_event(t - self._start_t, kind, message, **data)

    def _track_position_at(self, stamp: float, fallback: float) -> float:
        for t, position in reversed(self._track_history):
            if t <= stamp:
                return position
        return fallback

    def _stop_devices(self, t: float) -> None:
        decel = self.config.supervisor.stop_deceleration
        for name, action in (("arm", lambda: self.arm.stop(decel)), ("track", self.track.stop)):
            try:
                action()
            except DeviceError as exc:
                self._event(t, "fault", f"{name} stop failed: {exc}")

    # --- vision ---------------------------------------------------------------------------
    def _vision(
        self, t: float, arm: ArmState | None, track: TrackState | None, problems: list[Violation]
    ) -> tuple[list[Measurement], dict[str, float], float]:
        """Read a frame, run every estimator with the fused prior, update fusion. Returns the
        measurements, per-estimator times and the fusion time (ms); the time spent waiting for
        the camera is kept in ``self._read_ms`` (on hardware the camera runs on its own)."""
        read_start = time.perf_counter()
        try:
            frame: Frame = self.camera.read(timeout_s=max(0.05, 2.0 / self.camera_fps))
        except DeviceError as exc:
            problems.append(Violation("frames", f"camera read failed: {exc}", True))
            return [], {}, 0.0
        finally:
            self._read_ms = 1000.0 * (time.perf_counter() - read_start)
        problem = frame_problem(frame)
        if problem is not None:
            problems.append(Violation("frames", f"corrupt frame: {problem}", True))
            return [], {}, 0.0
        self._last_frame_t = t
        if (
            self.frame_logger is not None
            and t - self._last_logged_frame_t >= self.frame_log_period_s
        ):
            self.frame_logger(t - self._start_t, frame.image)
            self._last_logged_frame_t = t
        X_BE = self._X_BE_history.at(frame.stamp)
        if X_BE is None or track is None:
            problems.append(Violation("frames", "no arm/track state for the frame's stamp", True))
            return [], {}, 0.0
        X_CM = self.geometry.X_CM(X_BE, self._track_position_at(frame.stamp, track.position))
        prior = self.fusion.prior_X_CT(X_CM, frame.stamp)
        measurements, timings = [], {}
        for system, estimator in self.estimators.items():
            start = time.perf_counter()
            try:
                m = estimator.estimate(frame, prior)
            except Exception as exc:  # a bug in vision must stop the arm, not the program
                problems.append(
                    Violation("estimator", f"{system} raised {type(exc).__name__}: {exc}", True)
                )
                m = Measurement.lost(system, frame, f"raised {type(exc).__name__}")
            bad = _measurement_problem(m)
            if bad is not None:
                problems.append(Violation("estimator", bad, True))
                m = Measurement.lost(system, frame, bad)
            timings[system] = 1000.0 * (time.perf_counter() - start)
            measurements.append(m)
        start = time.perf_counter()
        # What fusion made of this frame's measurements (accepted, rejected and why) is only in
        # the update's answer; a later prediction no longer lists them.
        self._gated = self.fusion.update(measurements, X_CM, frame.stamp)
        return measurements, timings, 1000.0 * (time.perf_counter() - start)

    # --- one tick -------------------------------------------------------------------------
    def tick(self) -> None:
        wall_start = time.perf_counter()
        t = self.clock.now()
        dt = 1.0 / self.config.servo.control_rate_hz
        problems: list[Violation] = []
        arm_error = None
        arm: ArmState | None = None
        try:
            arm = self.arm.state()
            self._X_BE_history.add(arm.stamp, arm.X_BE)
        except DeviceError as exc:
            arm_error = f"arm state unavailable: {exc}"
        track: TrackState | None = None
        track_fault = None
        try:
            track = self.track.state()
            self._track_history.append((track.stamp, track.position))
            del self._track_history[:-500]
            track_fault = track.fault
        except DeviceError as exc:
            track_fault = f"track state unavailable: {exc}"
        gripper: GripperState | None = None
        try:
            gripper = self.gripper.state()
        except DeviceError as exc:
            self._event(t, "fault", f"gripper state unavailable: {exc}")

        measurements: list[Measurement] = []
        timings: dict[str, float] = {}
        fusion_ms = 0.0
        self._read_ms = 0.0
        self._gated = None
        if t >= self._next_frame_t and self.sequencer.phase not in TERMINAL:
            self._next_frame_t = t + 1.0 / self.camera_fps - 1e-9
            measurements, timings, fusion_ms = self._vision(t, arm, track, problems)

        estimate = self.fusion.estimate(t)
        X_CT_est = X_TC_est = None
        if arm is not None and track is not None and estimate.health == "ok":
            X_CT_est = estimate.X_CT(self.geometry.X_CM(arm.X_BE, track.position))
            X_TC_est = X_CT_est.inverse()

        phase_before = self.sequencer.phase
        X_WC = self.geometry.X_WC(arm.X_BE) if arm is not None else None
        output = self.sequencer.step(
            SequencerInputs(
                stamp=t,
                X_TC_est=X_TC_est,
                estimate_ok=estimate.health == "ok" and not problems,
                R_WC=X_WC.R if X_WC is not None else np.eye(3),
                track_axis_W=self.geometry.track_axis_W,
                max_track_speed=self.geometry.max_track_speed,
                gripper=gripper,
            ),
            dt,
        )
        V_BE = np.zeros(6)
        if arm is not None:
            V_BE = camera_twist_to_flange(output.camera_twist_C, arm.X_BE, self.geometry.X_EC)
        frame_age = math.inf if self._last_frame_t is None else t - self._last_frame_t
        snapshot = SafetySnapshot(
            stamp=t,
            phase=str(self.sequencer.phase),
            arm=arm,
            arm_error=arm_error,
            track_fault=track_fault,
            estimate_health=estimate.health,
            estimate_age_s=estimate.age_s if estimate.age_s is not None else math.inf,
            X_TC_est=X_TC_est,
            frame_age_s=frame_age,
            tick_s=0.0
            if self.world is not None
            else time.perf_counter() - wall_start - self._read_ms / 1000,
            commanded_V_BE=V_BE,
            commanded_track_velocity=output.track_velocity,
        )
        violations = problems + check(
            snapshot,
            self.config.supervisor,
            self.config.servo,
            max_track_speed=self.geometry.max_track_speed,
        )
        events = list(output.events)
        if (
            self.world is not None
            and phase_before == Phase.STANDOFF
            and self.sequencer.phase == Phase.GRASP
        ):
            truth = self.world.truth()
            error = pose_error(truth["X_WT"].inverse() @ truth["X_WC"], self.sequencer.X_TC_goal)
            self._standoff_error = (error.distance_m, error.angle_rad)
            events.append(
                (
                    "info",
                    f"stand-off reached; true error {1000 * error.distance_m:.1f} mm, "
                    f"{math.degrees(error.angle_rad):.2f}°",
                )
            )

        command: ServoCommand
        if violations and self.sequencer.phase not in TERMINAL:
            self._stop_devices(t)
            events.extend(self.sequencer.on_violations(violations, t))
            command = ServoCommand.halt(t, "; ".join(str(v) for v in violations))
            track_velocity = 0.0
        elif self.sequencer.phase in TERMINAL:
            if phase_before not in TERMINAL:
                self._stop_devices(t)
            command = ServoCommand.halt(t, self.sequencer.abort_reason or str(self.sequencer.phase))
            track_velocity = 0.0
        else:
            command = ServoCommand(t, V_BE)
            track_velocity = output.track_velocity
            try:
                self.arm.servo(command)
                self.track.move_velocity(track_velocity)
                if output.gripper_command == "grip":
                    self.gripper.grip()
                elif output.gripper_command == "open":
                    self.gripper.open()
            except DeviceError as exc:
                self._stop_devices(t)
                events.extend(
                    self.sequencer.on_violations([Violation("command", str(exc), False)], t)
                )
                command = ServoCommand.halt(t, f"command failed: {exc}")
                track_velocity = 0.0
        for kind, message in events:
            self._event(t, kind, message)

        self.log.write_tick(
            self._record(
                t,
                measurements,
                estimate,
                X_CT_est,
                X_TC_est,
                command,
                track_velocity,
                arm,
                track,
                gripper,
                timings,
                fusion_ms,
                1000.0 * (time.perf_counter() - wall_start) - self._read_ms,
            )
        )
        self._tick += 1

    def _record(
        self,
        t,
        measurements,
        estimate,
        X_CT_est,
        X_TC_est,
        command,
        track_velocity,
        arm,
        track,
        gripper,
        timings,
        fusion_ms,
        tick_ms,
    ) -> dict:
        truth = None
        if self.world is not None:
            poses = self.world.truth()
            truth = {name: pose.to_list() for name, pose in poses.items()}
            truth["X_CT"] = (poses["X_WC"].inverse() @ poses["X_WT"]).to_list()
        return {
            "t": t - self._start_t,
            "tick": self._tick,
            "phase": str(self.sequencer.phase),
            "range_m": float(X_TC_est.p[2]) if X_TC_est is not None else None,
            "measurements": [m.to_dict() for m in measurements],
            "estimate": {
                "health": estimate.health,
                "X_CT": X_CT_est.to_list() if X_CT_est is not None else None,
                "X_MT": estimate.X_MT.to_list()
                if getattr(estimate, "X_MT", None) is not None
                else None,
                "covariance": np.asarray(estimate.covariance)[:6, :6].tolist()
                if getattr(estimate, "covariance", None) is not None
                else None,
                "accepted": list(self._gated.accepted) if self._gated is not None else [],
                "rejected": [{"system": s, "reason": r} for s, r in self._gated.rejected]
                if self._gated is not None
                else [],
                "age_s": estimate.age_s,
            },
            "command": {
                "V_BE": command.V_BE.tolist(),
                "stop": command.stop,
                "reason": command.reason,
                "track_velocity": track_velocity,
            },
            "arm": None
            if arm is None
            else {
                "q": arm.q.tolist(),
                "X_BE": arm.X_BE.to_list(),
                "V_BE": arm.V_BE.tolist(),
                "protective_stop": arm.protective_stop,
                "fault": arm.fault_reason,
            },
            "track": None
            if track is None
            else {
                "position": track.position,
                "velocity": track.velocity,
                "fault": track.fault,
            },
            "gripper": None
            if gripper is None
            else {
                "position": gripper.position,
                "object_detected": gripper.object_detected,
            },
            "truth": truth,
            # "tick": everything this tick did except waiting for the camera ("camera_read");
            # in simulation the read includes rendering the frame.
            "timing_ms": {
                "estimators": timings,
                "fusion": fusion_ms,
                "tick": tick_ms,
                "camera_read": self._read_ms,
            },
        }

    # --- the run --------------------------------------------------------------------------
    def run(self, max_duration_s: float = 180.0) -> TrialOutcome:
        dt = 1.0 / self.config.servo.control_rate_hz
        self._start_t = self.clock.now()
        self.sequencer.start(self._start_t)
        self._event(self._start_t, "phase", "trial started")
        next_t = self._start_t
        while self.sequencer.phase not in TERMINAL:
            if self.clock.now() - self._start_t > max_duration_s:
                self._stop_devices(self.clock.now())
                self.sequencer.abort(self.clock.now(), f"trial exceeded {max_duration_s:.0f} s")
                self._event(self.clock.now(), "abort", self.sequencer.abort_reason)
                break
            self.tick()
            next_t += dt
            if self.world is not None:
                self.world.advance(dt)
            else:
                self.clock.sleep_until(next_t)
        # One more tick records the terminal state (and makes sure everything is stopped).
        self.tick()
        duration = self.clock.now() - self._start_t
        success = self.sequencer.phase == Phase.DONE
        if self._standoff_error is not None:
            standoff = self.config.standoff
            success = (
                success
                and self._standoff_error[0] <= standoff.success_position_m
                and self._standoff_error[1] <= math.radians(standoff.success_angle_deg)
            )
        return TrialOutcome(
            phase=str(self.sequencer.phase),
            success=success,
            abort_reason=self.sequencer.abort_reason,
            duration_s=duration,
            ticks=self._tick,
            standoff_error_m=None if self._standoff_error is None else self._standoff_error[0],
            standoff_error_rad=None if self._standoff_error is None else self._standoff_error[1],
        )
