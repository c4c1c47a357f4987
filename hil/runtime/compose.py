"""The composition root: from configuration, build the devices, the vision pipeline, the clock
and the control loop of one trial — and tear them down, stopping the arm and the track, on
every way out.

Everything that differs between a simulation and a rig is decided here, once; the loop, the
sequencer and the supervisor see only the device protocols, a ``VisionLink`` and a ``Clock``.

* ``--clock sim``: the simulated world lives in this process and is stepped between control
  ticks as fast as the machine allows (``SteppedClock``); the vision pipeline runs inline and
  charges each system its modelled processing time. Deterministic for a seed.
* ``--clock wall``: the simulated world runs in real time in processes of its own and is reached
  only through device proxies; the vision pipeline runs in its own process with one worker
  process per system; the loop sleeps on the monotonic clock (``hil.runtime.wall``).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import get_args

import numpy as np

from configuration.camera import CameraConfig, load_camera
from configuration.mockup import MockupConfig, load_mockup
from configuration.rig import load_rig
from configuration.simulation import ClockKind, SimulationConfig
from estimators.fusion import PoseFusion
from estimators.geometry import Pose
from estimators.registry import build_estimator
from hil.logs.foxglove import FoxgloveRecorder
from hil.logs.records import TickRecord
from hil.logs.triallog import TrialLogError, TrialLogWriter
from hil.runtime.faults import FaultInjector
from hil.runtime.history import StateHistory
from hil.runtime.judge import StandoffJudge, truth_record
from hil.runtime.loop import ControlLoop, TrialOutcome, describe_exception
from hil.runtime.rig import RigGeometry
from hil.runtime.signals import StopSignals
from hil.runtime.stepped import SteppedClock
from hil.runtime.vision import VisionPipeline
from hil.runtime.workers import InlineWorkers
from sim_backends.start import TrialStart, sample_start
from sim_backends.world import SimWorld


@dataclass(frozen=True, slots=True)
class TrialResult:
    """How a trial ended. ``standoff_error_*``: the true camera pose error when the stand-off was
    declared reached (simulation only; None on a rig or if it was never reached).
    ``log_error``: why the log stopped being written (None when it holds the whole trial)."""

    outcome: TrialOutcome
    success: bool
    standoff_error_m: float | None
    standoff_error_rad: float | None
    log_path: Path
    start: TrialStart
    clock: str
    log_error: str | None = None


def grasp_pose(config: SimulationConfig) -> Pose:
    """Where the camera is when the fingers straddle the ring lip: the stand-off advanced."""
    approach = config.approach
    advance = Pose(np.eye(3), np.array([0.0, 0.0, approach.grasp.advance_m]))
    return approach.standoff.X_TC_goal() @ advance


def header(
    config: SimulationConfig,
    mockup: MockupConfig,
    camera: CameraConfig,
    start: TrialStart,
    seed: int,
    clock: str,
) -> dict:
    """The trial log's header: the full resolved configuration, seed, start and clock."""
    return {
        "config": {
            "simulation": config.model_dump(mode="json"),
            "mockup": mockup.model_dump(mode="json"),
            "camera": camera.model_dump(mode="json"),
            "rig": start.rig.model_dump(mode="json"),
        },
        "seed": seed,
        "clock": clock,
        "notes": f"{config.devices.kind} approach, clock {clock}, noise {config.noise.preset}, "
        f"systems {', '.join(config.systems)}",
        "start": {"X_TC": start.X_TC.to_list(), "q": start.start_q.tolist()},
    }


class Trial:
    """One trial, built and torn down as a context manager. Inside, ``loop``, ``log``,
    ``vision`` and (``--clock sim``) ``world`` are available, so tests can step it and inject
    faults; ``run()`` runs it to the end and records the outcome in the log.

    Whatever ends the trial — its own end, an exception, Ctrl-C — ``__exit__`` stops the arm and
    the track, writes why into the log and closes it. With ``signals`` (``StopSignals``, entered
    by the caller), SIGINT and SIGTERM are routed to the loop's ``request_stop`` from the moment
    the loop exists until the trial is torn down: the loop stops the devices itself and the log
    gets its footer; during start-up they raise ``Interrupted`` as before.
    """

    def __init__(
        self,
        config: SimulationConfig,
        *,
        seed: int,
        log_path: Path,
        on_tick: Callable[[TickRecord], None] | None = None,
        mockup: MockupConfig | None = None,
        clock: str | None = None,
        signals: StopSignals | None = None,
    ):
        self.config, self.seed, self.log_path = config, seed, Path(log_path)
        self._signals = signals
        self.clock_kind = clock or config.clock
        if self.clock_kind not in get_args(ClockKind):
            raise ValueError(f"clock must be 'sim' or 'wall'; got {self.clock_kind!r}")
        if self.clock_kind == "sim" and config.devices.kind != "sim":
            raise ValueError(
                f"--clock sim steps a simulated world; {config.devices.kind} devices run on the "
                "wall clock (use --clock wall)"
            )
        self._on_tick = on_tick
        self.mockup = mockup or load_mockup(config.mockup)
        self.camera = load_camera(config.camera)
        self.start = sample_start(config.start, load_rig(config.rig), np.random.default_rng(seed))
        self.geometry = RigGeometry.of(self.start.rig)
        self._stack = contextlib.ExitStack()
        #: What the trial's processes used (wall clock), reported with the outcome.
        self.resources: Callable[[], dict] | None = None
        #: The configured faults' injector (``--clock sim`` with ``faults:``), an observer.
        self.injector: FaultInjector | None = None

    def __enter__(self) -> Trial:
        try:
            self.log_path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise TrialLogError(
                f"cannot create the log directory {self.log_path.parent}: {exc.strerror}"
            ) from None
        try:
            self.log = self._stack.enter_context(
                TrialLogWriter(
                    self.log_path,
                    header(
                        self.config, self.mockup, self.camera, self.start, self.seed,
                        self.clock_kind,
                    ),
                )
            )  # fmt: skip
            self.log = FoxgloveRecorder(
                self.log,
                X_WB=self.geometry.X_WB,
                X_EC=self.geometry.X_EC,
                X_WM=self.geometry.X_WM,
                camera=self.camera.camera_info(),
                target=self.mockup.target_model(),
            )
            if self.clock_kind == "sim":
                self._build_stepped()
            else:
                from hil.runtime.wall import build_wall

                build_wall(self)
        except BaseException as exc:
            log = getattr(self, "log", None)
            if log is not None:
                log.write_event(
                    0.0, "abort", f"trial ended during start-up by {describe_exception(exc)}"
                )
            self._stack.close()
            raise
        if self._signals is not None:
            self._signals.route_to = self.loop.request_stop
        return self

    def _observers(self) -> list[Callable[[TickRecord], None]]:
        self.judge = StandoffJudge(self.config.approach.standoff.X_TC_goal(), self.log.write_event)
        injector = [self.injector] if self.injector is not None else []
        return [self.judge, *injector] + ([self._on_tick] if self._on_tick is not None else [])

    def _build_stepped(self) -> None:
        """``--clock sim``: world, pipeline and loop in this process, one simulated clock."""
        config, start = self.config, self.start
        self.world = world = self._stack.enter_context(
            SimWorld(
                start.rig,
                self.mockup,
                self.camera,
                noise=config.noise,
                render=config.render.for_noise(config.noise),
                seed=self.seed,
                **rig_options(config, start),
            )
        )
        world.start()
        target, info = self.mockup.target_model(), self.camera.camera_info()
        estimators = {s: build_estimator(s, target, info) for s in config.systems}
        self.vision = VisionPipeline(
            systems=config.systems,
            fusion=PoseFusion(target, config.fusion),
            history=StateHistory(self.geometry),
            workers=InlineWorkers(estimators, config.vision.processing_s),
            config=config.vision,
        )
        self._stack.callback(self.vision.close)
        period = 1.0 / config.approach.servo.control_rate_hz
        clock = SteppedClock(world, world.camera, self.vision, step_s=period)
        if config.faults:
            self.injector = FaultInjector(
                config.faults, world=world, workers=self.vision.workers, log=self.log,
                t0=lambda: self.loop.t0,
            )  # fmt: skip
        self.loop = ControlLoop(
            arm=world.arm,
            track=world.track,
            gripper=world.gripper,
            vision=self.vision,
            geometry=self.geometry,
            config=config.approach,
            clock=clock,
            log=self.log,
            truth=lambda: truth_record(world.truth()),
            observers=self._observers(),
        )

    def run(self) -> TrialResult:
        outcome = self.loop.run(max_duration_s=self.config.max_duration_s)
        resources = self.resources() if self.resources is not None else {}
        standoff = self.config.approach.standoff
        # With ground truth (simulation) success is judged on it; a rig has only completion.
        success = outcome.completed and (
            self.loop.truth is None
            or self.judge.success(
                standoff.success_position_m, math.radians(standoff.success_angle_deg)
            )
        )
        self.log.write_event(
            outcome.duration_s,
            "outcome",
            "success" if success else "failure",
            phase=outcome.phase,
            abort_reason=outcome.abort_reason,
            success=success,
            standoff_error_m=self.judge.error_m,
            standoff_error_rad=self.judge.error_rad,
            deadline_misses=outcome.deadline_misses,
            clock=self.clock_kind,
            control_period_s=self.loop.period_s,
            **resources,
        )
        return TrialResult(
            outcome,
            success,
            self.judge.error_m,
            self.judge.error_rad,
            self.log_path,
            self.start,
            self.clock_kind,
            self.log.error,
        )

    def __exit__(self, exc_type, exc, traceback) -> None:
        try:
            loop = getattr(self, "loop", None)
            if loop is not None:
                now = loop.clock.now()
                loop.stop_devices(now)
                if exc_type is not None and exc is not loop.ended_by:  # else the loop said it
                    self.log.write_event(
                        now - loop.t0, "abort", f"trial ended by {exc_type.__name__}: {exc}"
                    )
        finally:
            try:
                self._stack.close()
            finally:
                if self._signals is not None:
                    self._signals.route_to = None


def run_trial(
    config: SimulationConfig,
    *,
    seed: int,
    log_path: Path,
    on_tick: Callable[[TickRecord], None] | None = None,
    mockup: MockupConfig | None = None,
    clock: str | None = None,
    signals: StopSignals | None = None,
) -> TrialResult:
    """Run one approach and write its trial log to ``log_path``."""
    with Trial(
        config,
        seed=seed,
        log_path=log_path,
        on_tick=on_tick,
        mockup=mockup,
        clock=clock,
        signals=signals,
    ) as trial:
        return trial.run()


def rig_options(config: SimulationConfig, start: TrialStart) -> dict:
    """How the simulated rig of ``config`` starts (from ``start``) and judges a grasp:
    ``SimRig``'s keyword arguments, the same for both clocks and the emulated rig."""
    return {
        "grasp_X_TC": grasp_pose(config),
        "start_q": start.start_q,
        "links": config.links,
        "capture_position_m": config.grasp_capture_m,
        "capture_angle_deg": config.grasp_capture_deg,
        "object_width": config.grasp_object_width_m,
        "tool_reach_m": config.tool_reach_m,
        "contact_stiffness": config.contact_stiffness,
        "timing": config.camera_timing,
    }
