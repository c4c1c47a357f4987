"""The control loop: at the controller's rate, on a monotonic schedule, and never waiting for
vision.

One tick (docs/architecture.md):

1. read the arm, track and gripper states;
2. hand the arm/track state to the vision pipeline (for ``X_CM`` at each frame's capture) and
   take its newest fused state, predicted to this tick's time;
3. the sequencer proposes a camera twist, a track velocity and a gripper action;
4. the supervisor checks exactly what is about to be sent — any violation stops the arm and the
   track in this same tick;
5. command;
6. log the tick (and the vision results that came in since the last one).

``run`` sleeps until each next deadline (``t0 + k·period``, no drift) on the injected clock. With
``--clock wall`` that is the monotonic clock and the world runs on its own; with ``--clock sim``
sleeping steps the simulated world and the vision pipeline to the deadline
(``hil.runtime.stepped.SteppedClock``). The loop asks neither which it is: devices, vision link,
clock and the optional ground truth come from the composition root (``hil.runtime.compose``).

One difference it does see (``Clock.real_time``): only on real time does a tick's measured work
count against the supervisor's deadline. Under a simulated clock the work is logged and its
misses counted, but it cannot decide the trial: it is the host's timing, not the simulated
rig's, and a virtual machine's pause is counted as the thread's CPU time (a 2 ms piece of work
measured at 47–52 ms once a minute on this project's 2-core VM), which would make a run that is
deterministic for its seed abort at random. A simulated stall (the world advanced while the loop
waited) is lateness in simulated time and still trips it.
"""

from __future__ import annotations

import contextlib
import gc
import math
import time
import traceback
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from configuration.approach import ApproachConfig
from drivers.base import (
    Arm,
    ArmState,
    DeviceError,
    Gripper,
    GripperState,
    ServoCommand,
    Track,
    TrackState,
)
from drivers.clock import Clock
from estimators.fusion import TargetEstimate, estimate_from_state
from estimators.geometry import Pose
from hil.logs.records import (
    ArmRecord,
    CommandRecord,
    EstimateRecord,
    GripperRecord,
    TickRecord,
    TimingRecord,
    TrackRecord,
    TruthRecord,
    VisionCounters,
    VisionRecord,
)
from hil.runtime.history import StateSample
from hil.runtime.rig import RigGeometry
from hil.runtime.sequencer import TERMINAL, ApproachSequencer, SequencerInputs
from hil.runtime.servo import camera_twist_to_flange
from hil.runtime.supervisor import (
    ARM_ACCELERATION_BASELINE_S,
    TRACK_ACCELERATION_BASELINE_S,
    SafetySnapshot,
    Violation,
    acceleration_baseline,
    check,
    rate_exceeded_since,
)
from hil.runtime.vision import LoggedImage, VisionStatus

#: Camera images that may wait for a tick with room to log them (``ControlLoop._log_vision``).
MAX_WAITING_IMAGES = 4


class VisionLink(Protocol):
    """The control loop's view of the vision pipeline (in-process or in another process)."""

    def begin(self, t0: float) -> None: ...

    def publish_state(self, sample: StateSample) -> None: ...

    def latest(self) -> VisionStatus: ...

    def drain(self) -> list[VisionRecord | LoggedImage]: ...


class TrialRecorder(Protocol):
    """Where the loop's records go (``hil.logs.triallog.TrialLogWriter``). ``error``: why
    nothing more can be written (None while it can); the loop ends the trial when it is set."""

    error: str | None

    def write_tick(self, record: TickRecord) -> bool: ...

    def write_vision(self, record: VisionRecord) -> bool: ...

    def write_encoded_frame(self, t: float, data: bytes, *, encoding: str = ...) -> bool: ...

    def write_event(self, t: float, kind: str, message: str, /, **data: Any) -> bool: ...


class NullRecorder:
    error: str | None = None

    def write_tick(self, record: TickRecord) -> bool:
        return True

    def write_vision(self, record: VisionRecord) -> bool:
        return True

    def write_encoded_frame(self, t: float, data: bytes, *, encoding: str = "jpeg") -> bool:
        return True

    def write_event(self, t: float, kind: str, message: str, /, **data: Any) -> bool:
        return True


@dataclass(frozen=True, slots=True)
class TrialOutcome:
    """How the loop ended: final phase, why it aborted (if it did), duration, ticks, and the
    tick timing on the wall clock (``period_ms`` percentiles are simulated under --clock sim)."""

    phase: str
    completed: bool
    abort_reason: str
    duration_s: float
    ticks: int
    deadline_misses: int
    #: Devices whose final stop command failed, each with why (empty: arm and track stopped).
    stop_failures: tuple[str, ...] = ()


@contextlib.contextmanager
def young_collections_only() -> Iterator[None]:
    """No full garbage collection while the loop runs: a collection of the oldest generation
    scans every object the process holds and can stall a tick for tens of milliseconds. What
    exists when the loop starts is frozen out of collection; the loop collects the young
    generations itself between ticks (``collect_young``), which costs a fraction of a
    millisecond."""
    was_enabled = gc.isenabled()
    gc.freeze()
    gc.disable()
    try:
        yield
    finally:
        gc.unfreeze()
        if was_enabled:
            gc.enable()


def collect_young(threshold: int = 2000) -> None:
    """Collect the youngest generation when it has grown, the middle one every tenth time."""
    young, middle, _ = gc.get_count()
    if young > threshold:
        gc.collect(1 if middle >= 10 else 0)


def uninitialized(stamp: float) -> TargetEstimate:
    return TargetEstimate(stamp, None, None, None, "uninitialized")


@dataclass
class ControlLoop:
    arm: Arm
    track: Track
    gripper: Gripper
    vision: VisionLink
    geometry: RigGeometry
    config: ApproachConfig
    clock: Clock
    log: TrialRecorder = field(default_factory=NullRecorder)
    #: Simulator ground truth at the current time (absent on a rig).
    truth: Callable[[], TruthRecord | None] | None = None
    observers: Sequence[Callable[[TickRecord], None]] = ()

    def __post_init__(self) -> None:
        self.sequencer = ApproachSequencer(self.config)
        self.period_s = 1.0 / self.config.servo.control_rate_hz
        self._tick = 0
        self._t0 = 0.0
        self._previous_start: float | None = None
        self._last_work_s = 0.0
        self._deadline_misses = 0
        self._faults_seen = 0
        #: (reason, clock time it was asked) of a pending ``request_stop``.
        self._stop_request: tuple[str, float] | None = None
        self._stop_failures: tuple[str, ...] = ()
        #: The exception that ended ``run``, once it is in the log (so no one logs it twice).
        self.ended_by: BaseException | None = None
        #: Why the loop ended before the sequencer did, and whether the stop worked: "interrupted
        #: by SIGINT in phase approach; arm and track stopped" (None when it ran to its end).
        self.ending: str | None = None
        # What the supervisor compares against: the previous tick's sent command and states,
        # the flange's orientation at the start, since when the target turns too fast.
        self._sent: tuple[np.ndarray, float] | None = None
        self._arm_states: deque[ArmState] = deque(maxlen=32)
        self._track_states: deque[TrackState] = deque(maxlen=32)
        self._R_BE_start: np.ndarray | None = None
        self._rate_since: float | None = None
        #: Camera images for the log, waiting for a tick with room to write them.
        self._pending_images: deque[LoggedImage] = deque()

    # --- helpers ------------------------------------------------------------------------
    def _event(self, t: float, kind: str, message: str, **data: Any) -> None:
        self.log.write_event(t - self._t0, kind, message, **data)

    def stop_devices(self, t: float) -> tuple[str, ...]:
        """Stop the arm and the track, each attempted whatever the other did (any exception,
        not only a ``DeviceError``); returns the failures, each naming its device."""
        decel = self.config.supervisor.stop_deceleration
        failures = []
        for name, action in (("arm", lambda: self.arm.stop(decel)), ("track", self.track.stop)):
            try:
                action()
            except Exception as exc:
                failures.append(f"{name} stop failed: {describe_exception(exc)}")
                self._event(t, "fault", failures[-1])
        self._stop_failures = tuple(failures)
        return self._stop_failures

    def request_stop(self, reason: str) -> None:
        """Ask the loop to stop the arm and the track and end the trial with ``reason`` (e.g.
        "interrupted by SIGINT"). Safe from a signal handler or another thread: it only records
        the request; ``run`` acts on it before its next tick, within one control period."""
        if self._stop_request is None:
            self._stop_request = (reason, self.clock.now())

    # --- one tick -----------------------------------------------------------------------
    def tick(self, late_s: float = 0.0) -> TickRecord:
        """One control tick; ``late_s``: how late it started after its deadline."""
        work_start = self.clock.work_time()
        cpu_start = time.thread_time()
        t = self.clock.now()
        problems: list[Violation] = []
        arm, arm_error = self._read(self.arm.state, "arm")
        track, track_error = self._read(self.track.state, "track")
        gripper, gripper_error = self._read(self.gripper.state, "gripper")
        if gripper_error is not None:
            self._event(t, "fault", gripper_error)
        if arm is not None and track is not None:
            self.vision.publish_state(StateSample(arm.stamp, arm.X_BE, track.stamp, track.position))

        status = self.vision.latest()
        estimate = (
            uninitialized(t) if status.fusion is None else estimate_from_state(status.fusion, t)
        )
        if status.frame_problem is not None:
            problems.append(Violation("frames", status.frame_problem, True))
        if status.camera_fault is not None:
            problems.append(Violation("camera", status.camera_fault, False))
        if status.estimator_faults > self._faults_seen:
            self._faults_seen = status.estimator_faults
            problems.append(Violation("estimator", status.estimator_fault or "malfunction", False))

        X_CT_est = X_TC_est = None
        if arm is not None and track is not None and estimate.health == "ok":
            X_CT_est = estimate.X_CT(self.geometry.X_CM(arm.X_BE, track.position))
            X_TC_est = X_CT_est.inverse()

        X_WC = self.geometry.X_WC(arm.X_BE) if arm is not None else None
        phase_before = self.sequencer.phase
        output = self.sequencer.step(
            SequencerInputs(
                stamp=t,
                X_TC_est=X_TC_est,
                estimate_ok=estimate.health == "ok" and not problems,
                R_WC=X_WC.R if X_WC is not None else np.eye(3),
                track_axis_W=self.geometry.track_axis_W,
                max_track_speed=self.geometry.max_track_speed,
                gripper=gripper,
                roll_sigma_rad=estimate.roll_sigma_rad(),
            ),
            self.period_s,
        )
        V_BE = np.zeros(6)
        if arm is not None:
            V_BE = camera_twist_to_flange(output.camera_twist_C, arm.X_BE, self.geometry.X_EC)
        newest_frame = status.newest_frame_stamp
        if self._R_BE_start is None and arm is not None:
            self._R_BE_start = arm.X_BE.R
        rate = None
        if estimate.health == "ok" and estimate.V_MT is not None:
            rate = float(np.linalg.norm(estimate.V_MT[:3]))
        self._rate_since = rate_exceeded_since(self._rate_since, rate, t, self.config.supervisor)
        snapshot = SafetySnapshot(
            stamp=t,
            phase=str(self.sequencer.phase),
            arm=arm,
            arm_error=arm_error,
            track_fault=track_error if track_error is not None else track and track.fault,
            estimate_health=estimate.health,
            estimate_age_s=estimate.age_s if estimate.age_s is not None else math.inf,
            X_TC_est=X_TC_est,
            frame_age_s=math.inf if newest_frame is None else t - newest_frame,
            tick_s=max(late_s, self._last_work_s if self.clock.real_time else 0.0),
            commanded_V_BE=V_BE,
            commanded_track_velocity=output.track_velocity,
            period_s=self.period_s,
            previous_V_BE=None if self._sent is None else self._sent[0],
            previous_track_velocity=None if self._sent is None else self._sent[1],
            previous_arm=acceleration_baseline(self._arm_states, arm, ARM_ACCELERATION_BASELINE_S),
            track=track,
            previous_track=acceleration_baseline(
                self._track_states, track, TRACK_ACCELERATION_BASELINE_S
            ),
            R_BE_start=self._R_BE_start,
            target_rate=rate,
            target_rate_since=self._rate_since,
            guided=self.sequencer.guided,
        )
        violations = problems + check(
            snapshot, self.config.supervisor, self.config.servo, self.geometry
        )
        events = list(output.events)
        command, track_velocity, gripper_command, more = self._command(
            t, violations, output, V_BE, phase_before
        )
        events.extend(more)
        self._sent = (command.V_BE, track_velocity)
        if arm is not None:
            self._arm_states.append(arm)
        if track is not None:
            self._track_states.append(track)
        for kind, message in events:
            self._event(t, kind, message)
        self._log_vision(work_start)
        work_s = self.clock.work_time() - work_start
        cpu_s = time.thread_time() - cpu_start
        record = self._record(
            t, estimate, X_CT_est, X_TC_est, command, track_velocity, gripper_command,
            arm, track, gripper, status, late_s, work_s, cpu_s,
        )  # fmt: skip
        self.log.write_tick(record)
        for observer in self.observers:
            observer(record)
        self._last_work_s = work_s
        self._tick += 1
        return record

    def _read(self, read: Callable[[], Any], name: str) -> tuple[Any, str | None]:
        try:
            return read(), None
        except DeviceError as exc:
            return None, f"{name} state unavailable: {exc}"

    def _command(
        self,
        t: float,
        violations: list[Violation],
        output: Any,
        V_BE: np.ndarray,
        phase_before: str,
    ) -> tuple[ServoCommand, float, str | None, list[tuple[str, str]]]:
        """Send what the sequencer proposed, or stop: (command, track velocity, gripper
        command, events)."""
        events: list[tuple[str, str]] = []
        if violations and self.sequencer.phase not in TERMINAL:
            self.stop_devices(t)
            events.extend(self.sequencer.on_violations(violations, t))
            return ServoCommand.halt(t, "; ".join(map(str, violations))), 0.0, None, events
        if self.sequencer.phase in TERMINAL:
            if phase_before not in TERMINAL or self._tick == 0:
                self.stop_devices(t)
            reason = self.sequencer.abort_reason or str(self.sequencer.phase)
            return ServoCommand.halt(t, reason), 0.0, None, events
        command = ServoCommand(t, V_BE)
        try:
            self.arm.servo(command)
            self.track.move_velocity(output.track_velocity)
            if output.gripper_command == "grip":
                self.gripper.grip()
            elif output.gripper_command == "open":
                self.gripper.open()
        except DeviceError as exc:
            self.stop_devices(t)
            events.extend(self.sequencer.on_violations([Violation("command", str(exc), False)], t))
            return ServoCommand.halt(t, f"command failed: {exc}"), 0.0, None, events
        return command, output.track_velocity, output.gripper_command, events

    def _log_vision(self, work_start: float | None = None) -> None:
        """Log the vision records since the last tick, and a camera image if this tick has
        room for it (``work_start`` None: all of them now). Writing one (~200 kB of JPEG,
        base64 in JSON, once a second) took a tick past its 8 ms under load; it waits a few
        ticks instead — its log time is its capture stamp either way."""
        for item in self.vision.drain():
            if isinstance(item, LoggedImage):
                self._pending_images.append(item)
            else:
                self.log.write_vision(item)
        room = work_start is None or self.clock.work_time() - work_start < 0.5 * self.period_s
        # One a tick when there is room; all that wait at the end; and never more than a few
        # waiting (a loop that never has room writes them as it did before).
        while self._pending_images and (room or len(self._pending_images) > MAX_WAITING_IMAGES):
            image = self._pending_images.popleft()
            self.log.write_encoded_frame(image.stamp - self._t0, image.jpeg, encoding="jpeg")
            room = work_start is None

    def _record(
        self,
        t: float,
        estimate: TargetEstimate,
        X_CT_est: Pose | None,
        X_TC_est: Pose | None,
        command: ServoCommand,
        track_velocity: float,
        gripper_command: str | None,
        arm: ArmState | None,
        track: TrackState | None,
        gripper: GripperState | None,
        status: VisionStatus,
        late_s: float,
        work_s: float,
        cpu_s: float,
    ) -> TickRecord:
        period = None if self._previous_start is None else t - self._previous_start
        self._previous_start = t
        miss = late_s >= 0.5 * self.period_s or work_s > self.period_s
        self._deadline_misses += miss
        covariance = estimate.covariance
        return TickRecord(
            t=t - self._t0,
            tick=self._tick,
            phase=str(self.sequencer.phase),
            range_m=float(X_TC_est.p[2]) if X_TC_est is not None else None,
            estimate=EstimateRecord(
                health=estimate.health,
                X_CT=X_CT_est,
                X_MT=estimate.X_MT,
                V_MT=estimate.V_MT,
                covariance=None if covariance is None else np.asarray(covariance)[:6, :6],
                age_s=estimate.age_s if math.isfinite(estimate.age_s) else None,
                updated_t=None
                if status.fusion is None or not math.isfinite(status.fusion.stamp)
                else status.fusion.stamp - self._t0,
            ),
            command=CommandRecord(
                V_BE=command.V_BE,
                stop=command.stop,
                reason=command.reason,
                track_velocity=track_velocity,
                gripper=gripper_command,
            ),
            timing=TimingRecord(
                period_ms=None if period is None else 1000.0 * period,
                late_ms=1000.0 * late_s,
                work_ms=1000.0 * work_s,
                deadline_miss=bool(miss),
                cpu_ms=1000.0 * cpu_s,
            ),
            vision=VisionCounters(
                frames_received=status.frames_received,
                frames_processed=status.frames_processed,
                frames_dropped=status.frames_dropped,
                results_stale=status.results_stale,
                newest_frame_t=None
                if status.newest_frame_stamp is None
                else status.newest_frame_stamp - self._t0,
            ),
            arm=None
            if arm is None
            else ArmRecord(
                q=arm.q,
                X_BE=arm.X_BE,
                V_BE=arm.V_BE,
                protective_stop=arm.protective_stop,
                emergency_stop=arm.emergency_stop,
                fault=arm.fault,
                wrench_B=arm.wrench_B,
            ),
            track=None
            if track is None
            else TrackRecord(track.position, track.velocity, track.moving, track.fault),
            gripper=None
            if gripper is None
            else GripperRecord(
                gripper.position,
                gripper.object_detected,
                gripper.activated,
                gripper.moving,
                gripper.fault,
            ),
            truth=None if self.truth is None else self.truth(),
        )

    # --- the run ------------------------------------------------------------------------
    def start(self) -> None:
        """The trial starts now: times are counted from here, the sequencer begins to acquire."""
        self._t0 = self.clock.now()
        self.vision.begin(self._t0)
        self.sequencer.start(self._t0)
        self._event(self._t0, "phase", "trial started")

    def run(self, max_duration_s: float = 180.0) -> TrialOutcome:
        """Tick at the control rate until the sequencer ends (or the time limit, a stop request,
        a log that cannot be written), then one more tick that records the final state and
        makes sure everything is stopped.

        Any exception — in a tick, a driver call, an observer — stops the arm and the track
        before it leaves: the abort is logged with the exception and its traceback, then the
        exception propagates."""
        with young_collections_only():
            try:
                return self._run(max_duration_s)
            except BaseException as exc:
                self._end_by_exception(exc)
                raise

    def _run(self, max_duration_s: float) -> TrialOutcome:
        period = self.period_s
        self.start()
        deadline = self._t0
        while self.sequencer.phase not in TERMINAL:
            now = self.clock.now()
            if self._must_end(now, max_duration_s):
                break
            late = max(0.0, now - deadline)
            if late >= period:  # a whole period lost: re-phase rather than burst to catch up
                deadline = now
            self.tick(late)
            collect_young()
            deadline += period
            if self._stop_request is None and self._log_error() is None:
                self.clock.sleep_until(deadline)  # else act on it now, not a period later
        self.tick()
        self._log_vision()  # the images still waiting for room
        return TrialOutcome(
            phase=str(self.sequencer.phase),
            completed=str(self.sequencer.phase) == "done",
            abort_reason=self.sequencer.abort_reason,
            duration_s=self.clock.now() - self._t0,
            ticks=self._tick,
            deadline_misses=self._deadline_misses,
            stop_failures=self._stop_failures,
        )

    def _must_end(self, now: float, max_duration_s: float) -> bool:
        """End the trial here, for a stop request, a log that can no longer be written (a trial
        that cannot be recorded must not go on moving) or the time limit: stop the arm and the
        track now, abort the sequencer, and say why (the final tick records the stop)."""
        phase, data = str(self.sequencer.phase), {}
        if self._stop_request is not None:
            reason, asked = self._stop_request
            reason = f"{reason} in phase {phase}"
            data = {"asked_t": asked - self._t0, "reaction_s": now - asked}
        elif (error := self._log_error()) is not None:
            reason = f"trial log cannot be written ({error}) in phase {phase}"
        elif now - self._t0 > max_duration_s:
            reason = f"trial exceeded {max_duration_s:.0f} s"
        else:
            return False
        failures = self.stop_devices(now)
        self.sequencer.abort(now, reason)
        self.ending = f"{reason}; {_stopped(failures)}"
        self._event(now, "stop", self.ending, stop_failures=list(failures), **data)
        return True

    def _log_error(self) -> str | None:
        return getattr(self.log, "error", None)

    def _end_by_exception(self, exc: BaseException) -> None:
        now = self.clock.now()
        failures = self.stop_devices(now)
        self.ending = (
            f"trial ended by {describe_exception(exc)} in phase {self.sequencer.phase}; "
            f"{_stopped(failures)}"
        )
        self._event(
            now,
            "abort",
            self.ending,
            exception=type(exc).__name__,
            traceback="".join(traceback.format_exception(exc)),
            stop_failures=list(failures),
        )
        self.ended_by = exc

    @property
    def t0(self) -> float:
        return self._t0


def describe_exception(exc: BaseException) -> str:
    """``ValueError: what it says`` (just the type when it says nothing)."""
    text = str(exc)
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _stopped(failures: Sequence[str]) -> str:
    return "; ".join(failures) if failures else "arm and track stopped"
