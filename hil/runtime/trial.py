"""Build and run one simulated trial from a ``SimulationConfig``: random start, world, estimators,
fusion, loop and trial log."""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from configuration.camera import load_camera
from configuration.mockup import MockupConfig, load_mockup
from configuration.rig import PoseConfig, RigConfig, load_rig
from configuration.simulation import SimulationConfig
from estimators.fusion import PoseFusion
from estimators.geometry import Pose
from estimators.registry import build_estimator
from estimators.target import facing_camera
from hil.logs.triallog import TrialLogWriter
from hil.runtime.loop import ApproachLoop, RigGeometry, TrialOutcome
from sim_backends.ur_kinematics import solve_ik, ur_model
from sim_backends.world import SimWorld


def rig_geometry(rig: RigConfig) -> RigGeometry:
    return RigGeometry(
        X_WB=rig.arm.X_WB.pose,
        X_EC=rig.arm.X_EC.pose,
        track_axis_W=rig.track.axis_unit_W,
        X_WM0=rig.track.X_WM0.pose,
        max_track_speed=rig.track.max_speed,
    )


def _pose_config(pose: Pose) -> PoseConfig:
    rpy = np.degrees(Rotation.from_matrix(pose.R).as_euler("xyz"))
    return PoseConfig(xyz=tuple(pose.p.tolist()), rpy_deg=tuple(rpy.tolist()))


@dataclass(frozen=True, slots=True)
class TrialStart:
    """A sampled start: the mock-up's mount on the carriage and the arm's joints."""

    rig: RigConfig  # with the sampled mount misalignment
    start_q: np.ndarray
    X_TC: Pose  # the camera's start pose relative to the target


def sample_start(sim: SimulationConfig, rig: RigConfig, rng: np.random.Generator) -> TrialStart:
    """The reference study's randomised start: camera ``distance_m`` from the face, off-centre
    by up to ``max_offset_m`` and turned by up to ``max_rotation_deg`` about each axis; the
    mock-up slightly misaligned on its carriage. The arm's joints come from inverse kinematics
    continued from the rig's start joints."""
    start = sim.start
    tilt = np.radians(rng.uniform(-start.mount_misalignment_deg, start.mount_misalignment_deg, 3))
    X_MT = rig.track.X_MT.pose @ Pose.from_rotvec(tilt, np.zeros(3))
    rig = rig.model_copy(
        update={"track": rig.track.model_copy(update={"X_MT": _pose_config(X_MT)})}
    )
    dx, dy = rng.uniform(-start.max_offset_m, start.max_offset_m, 2)
    rpy = np.radians(rng.uniform(-start.max_rotation_deg, start.max_rotation_deg, 3))
    X_TC = (
        Pose(np.eye(3), np.array([dx, dy, 0.0]))
        @ facing_camera(start.distance_m)
        @ Pose.from_rpy(*rpy, np.zeros(3))
    )
    geometry = rig_geometry(rig)
    X_WT = geometry.X_WM(rig.track.start_position) @ X_MT
    X_BE = geometry.X_WB.inverse() @ X_WT @ X_TC @ geometry.X_EC.inverse()
    q, converged = solve_ik(ur_model(rig.arm.model), X_BE, np.radians(rig.arm.q0_deg))
    if not converged:
        raise ValueError(f"start pose out of the arm's reach (offset {dx:.2f}, {dy:.2f} m)")
    return TrialStart(rig, q, X_TC)


@dataclass(frozen=True, slots=True)
class TrialResult:
    outcome: TrialOutcome
    log_path: Path
    start: TrialStart


class SimTrial:
    """A simulated trial, built and torn down as a context manager: ``world``, ``log`` and
    ``loop`` are available inside, so tests can step it and inject faults; ``run()`` runs it to
    the end and records the outcome in the log."""

    def __init__(
        self,
        sim: SimulationConfig,
        *,
        seed: int,
        log_path: Path,
        on_tick: Callable[[dict], None] | None = None,
        mockup: MockupConfig | None = None,
    ):
        self.sim, self.seed, self.log_path, self._on_tick = sim, seed, Path(log_path), on_tick
        self.mockup = mockup or load_mockup(sim.mockup)
        self.camera = load_camera(sim.camera)
        self.start = sample_start(sim, load_rig(sim.rig), np.random.default_rng(seed))
        self._stack = contextlib.ExitStack()

    def _header(self) -> dict:
        sim, start = self.sim, self.start
        return {
            "config": {
                "simulation": sim.model_dump(mode="json"),
                "mockup": self.mockup.model_dump(mode="json"),
                "camera": self.camera.model_dump(mode="json"),
                "rig": start.rig.model_dump(mode="json"),
            },
            "seed": self.seed,
            "notes": f"simulated approach, noise {sim.noise.preset}, systems {', '.join(sim.systems)}",
            "start": {"X_TC": start.X_TC.to_list(), "q": start.start_q.tolist()},
        }

    def __enter__(self) -> SimTrial:
        sim, start = self.sim, self.start
        target = self.mockup.target_model()
        info = self.camera.camera_info()
        grasp_X_TC = sim.approach.standoff.X_TC_goal() @ Pose(
            np.eye(3), np.array([0.0, 0.0, sim.approach.grasp.advance_m])
        )
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self.world = self._stack.enter_context(
                SimWorld(
                    start.rig,
                    self.mockup,
                    self.camera,
                    noise=sim.noise,
                    render=sim.render,
                    seed=self.seed,
                    grasp_X_TC=grasp_X_TC,
                    start_q=start.start_q,
                    links=sim.links,
                    capture_position_m=sim.grasp_capture_m,
                    capture_angle_deg=sim.grasp_capture_deg,
                    object_width=sim.grasp_object_width_m,
                )
            )
            self.log = self._stack.enter_context(TrialLogWriter(self.log_path, self._header()))
            self.world.start()
            estimators = {s: build_estimator(s, target, info) for s in sim.systems}
            frame_logger = None
            if sim.log_frames_every_s > 0:
                log = self.log

                def frame_logger(t: float, image: np.ndarray) -> None:
                    log.write_frame(t, image, encoding="jpeg")

            self.loop = ApproachLoop(
                arm=self.world.arm,
                track=self.world.track,
                gripper=self.world.gripper,
                camera=self.world.camera,
                estimators=estimators,
                fusion=PoseFusion(target, sim.fusion),
                geometry=rig_geometry(start.rig),
                config=sim.approach,
                clock=self.world.clock,
                log=_TeeLog(self.log, self._on_tick),
                world=self.world,
                camera_fps=sim.camera_fps,
                frame_log_period_s=sim.log_frames_every_s or math.inf,
                frame_logger=frame_logger,
            )
        except BaseException:
            self._stack.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self._stack.close()

    def run(self) -> TrialResult:
        outcome = self.loop.run(max_duration_s=self.sim.max_duration_s)
        self.log.write_event(
            outcome.duration_s,
            "outcome",
            "success" if outcome.success else "failure",
            phase=outcome.phase,
            abort_reason=outcome.abort_reason,
            standoff_error_m=outcome.standoff_error_m,
            standoff_error_rad=outcome.standoff_error_rad,
        )
        return TrialResult(outcome, self.log_path, self.start)


def run_sim_trial(
    sim: SimulationConfig,
    *,
    seed: int,
    log_path: Path,
    on_tick: Callable[[dict], None] | None = None,
    mockup: MockupConfig | None = None,
) -> TrialResult:
    """Run one simulated approach and write its trial log to ``log_path``."""
    with SimTrial(sim, seed=seed, log_path=log_path, on_tick=on_tick, mockup=mockup) as trial:
        return trial.run()


class _TeeLog:
    """The trial log, plus a live view of each tick (progress output)."""

    def __init__(self, log: TrialLogWriter, on_tick: Callable[[dict], None] | None):
        self._log = log
        self._on_tick = on_tick

    def write_tick(self, record: dict) -> None:
        self._log.write_tick(record)
        if self._on_tick is not None:
            self._on_tick(record)

    def write_event(self, t: float, kind: str, message: str, **data) -> None:
        self._log.write_event(t, kind, message, **data)


def with_overrides(sim: SimulationConfig, **changes) -> SimulationConfig:
    """``sim`` with top-level fields replaced, validated again (e.g. ``systems``)."""
    data = sim.model_dump(mode="json")
    data.update({k: v for k, v in changes.items() if v is not None})
    return SimulationConfig.model_validate(data)
