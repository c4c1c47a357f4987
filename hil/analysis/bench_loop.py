"""``satgrasp bench loop``: the two rates of the real-time loop, timed on this machine.

1. **The control tick without vision**: ``ControlLoop.tick`` on the simulated arm, track and
   gripper (no camera, no renderer), with a fused estimate already there, writing a real trial
   log — what must fit in the 8 ms period. Wall-clock time per tick, p50 / p99 / max.
2. **The vision pipeline**: the same pre-rendered frames (a stretch of the approach at camera
   rate, ``tracking_frames``) fed as fast as the pipeline takes them, through the real
   ``VisionPipeline`` and fusion, with the three systems run one after the other in one
   process (serial) or each in a process of its own (concurrent): frames fully processed per
   second, and latency from the frame's arrival to its fusion (p50 / p95).
"""

from __future__ import annotations

import math
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from multiprocessing.connection import wait
from pathlib import Path

import numpy as np

from configuration.camera import load_camera
from configuration.mockup import load_mockup
from configuration.render import NoiseConfig, RenderConfig
from configuration.rig import load_rig
from configuration.simulation import load_simulation
from configuration.vision import VisionConfig
from estimators.frame import Frame, GroundTruth
from estimators.fusion import PoseFusion
from estimators.geometry import Pose
from estimators.registry import build_estimator
from estimators.target import facing_camera
from hil.logs.records import VisionRecord
from hil.logs.triallog import TrialLogWriter
from hil.runtime.history import StateHistory, StateSample
from hil.runtime.loop import ControlLoop
from hil.runtime.rig import RigGeometry
from hil.runtime.vision import VisionPipeline, VisionStatus
from hil.runtime.workers import InlineWorkers, ProcessWorkers
from sim_backends.renderer import make_renderer
from sim_backends.scene import MockupScene
from sim_backends.sensor import expose, frame_rng
from sim_backends.start import sample_start
from sim_backends.world import SimRig


@dataclass(frozen=True, slots=True)
class TickTiming:
    ticks: int
    p50_ms: float
    p99_ms: float
    max_ms: float
    period_ms: float


@dataclass(frozen=True, slots=True)
class PipelineTiming:
    """One way of running the estimators: ``frames`` the camera delivered, ``frames_per_s`` the
    rate of the slowest system (every system has measured that many frames a second),
    ``latency`` arrival → fused over every result, per-system results a second."""

    mode: str
    frames: int
    seconds: float
    frames_per_s: float
    latency_p50_ms: float
    latency_p95_ms: float
    results_per_s: dict[str, float]


class _FixedVision:
    """A VisionLink that always reports the same fused estimate (the tick's own cost only)."""

    def __init__(self, status: VisionStatus):
        self._status = status

    def begin(self, t0: float) -> None:
        pass

    def publish_state(self, sample: StateSample) -> None:
        pass

    def latest(self) -> VisionStatus:
        return self._status

    def drain(self) -> list:
        return []


def control_tick_timing(config: str = "sim", *, ticks: int = 2000, seed: int = 1) -> TickTiming:
    """Wall time of ``ControlLoop.tick`` on the simulated devices during an approach."""
    sim = load_simulation(config)
    start = sample_start(sim.start, load_rig(sim.rig), np.random.default_rng(seed))
    geometry = RigGeometry.of(start.rig)
    target = load_mockup(sim.mockup).target_model()
    with (
        tempfile.TemporaryDirectory() as folder,
        SimRig(start.rig, grasp_X_TC=facing_camera(0.35), start_q=start.start_q) as world,
        TrialLogWriter(Path(folder) / "bench.mcap", {"config": {}, "seed": seed}) as log,
    ):
        world.start()
        # A confirmed fused estimate at the true pose, refreshed as the clock runs.
        fusion = PoseFusion(target, sim.fusion)
        X_WT, X_WC = world.track_model.X_WT(), world.arm.camera_pose_W()
        X_CM = geometry.X_CM(world.arm.state().X_BE, world.track.state().position)
        truth = _oracle_measurements(X_WC.inverse() @ X_WT, world.clock.now())
        for m in truth:
            fusion.update([m], X_CM, m.stamp)
        loop = ControlLoop(
            arm=world.arm,
            track=world.track,
            gripper=world.gripper,
            vision=_FixedVision(VisionStatus(fusion.state(), newest_frame_stamp=None)),
            geometry=geometry,
            config=sim.approach.model_copy(
                update={
                    "supervisor": sim.approach.supervisor.model_copy(
                        update={"max_estimate_age_s": 1e6, "max_frame_age_s": 1e6}
                    )
                }
            ),
            clock=world.clock,
            log=log,
        )
        loop.observers = []
        loop.start()
        period = loop.period_s
        times = []
        for _ in range(ticks):
            started = time.perf_counter()
            loop.tick()
            times.append(1000.0 * (time.perf_counter() - started))
            world.advance(period)
    values = np.array(times)
    return TickTiming(
        ticks,
        float(np.median(values)),
        float(np.percentile(values, 99)),
        float(values.max()),
        1000.0 * period,
    )


def _oracle_measurements(X_CT: Pose, stamp: float) -> list:
    from estimators.measurement import Measurement

    return [
        Measurement(
            system=s, status="acquired", stamp=stamp + 0.01 * i, seq=i, X_CT=X_CT,
            covariance=np.eye(6) * 1e-6,
        )
        for i, s in enumerate(("corners", "lines"))
    ]  # fmt: skip


#: The stretch of the approach the pipeline benchmarks replay: 2.0 → 1.5 m at the servo's top
#: speed (0.25 m/s) seen at 30 fps, 8.5 mm per frame — the motion tracking sees on a rig.
TRACKING_STRETCH_M = (2.0, 1.5)
TRACKING_STRETCH_FRAMES = 60


def tracking_frames(camera: str, mockup: str, *, noise: str = "low") -> list[Frame]:
    """``approach_frames`` over ``TRACKING_STRETCH_M``, played forward and back (a replay that
    cycles them never jumps, so every system tracks as it would on a rig)."""
    start, end = TRACKING_STRETCH_M
    forward = approach_frames(
        camera, mockup, frames=TRACKING_STRETCH_FRAMES, noise=noise, start_m=start, end_m=end
    )
    return forward + forward[-2:0:-1]


def approach_frames(
    camera: str,
    mockup: str,
    *,
    frames: int,
    noise: str = "low",
    seed: int = 0,
    start_m: float = 3.0,
    end_m: float = 0.5,
) -> list[Frame]:
    """Rendered frames along a straight approach from ``start_m`` to ``end_m``, with ground
    truth."""
    info = load_camera(camera).camera_info()
    out = []
    noise_config = NoiseConfig(preset=noise)
    with MockupScene(load_mockup(mockup)) as scene:
        renderer = make_renderer(scene, info, RenderConfig())
        for i, distance in enumerate(np.linspace(start_m, end_m, frames)):
            X_TC = Pose.from_rpy(0.02, -0.03, 0.05, np.array([0.02, -0.01, 0.0])) @ facing_camera(
                float(distance)
            )
            X_WC = X_TC  # the target at the world origin
            rendering = renderer.render(X_WC)
            image = expose(
                rendering.image, rendering.depth_m, info.K, noise_config, frame_rng(seed, i)
            )
            out.append(Frame(image, 0.0, info, i, GroundTruth(rendering.X_CT, rendering.X_WC)))
    return out


def arm_state(frame: Frame, stamp: float) -> StateSample:
    """The state a rig reports while its camera takes ``frame``: the arm at the camera's pose
    (``pipeline_timing``'s rig has base, flange and camera frames all one), the track at 0.

    The arm's motion is measured on a rig, so fusion predicts each frame's pose from it; a
    bench that held the arm still while its frames moved would hand every system a prior
    lagging the motion by several frames, and time a harder search than a rig ever asks
    for."""
    if frame.truth is None:
        raise ValueError("arm_state needs a rendered frame (with its ground truth)")
    return StateSample(stamp, frame.truth.X_WC, stamp, 0.0)


def pipeline_timing(
    mode: str,
    frames: Sequence[Frame],
    systems: Sequence[str],
    *,
    mockup: str = "default",
    fps: float = 30.0,
    seconds: float = 20.0,
    progress: Callable[[str], None] | None = None,
) -> PipelineTiming:
    """A camera delivering ``frames`` (cycled) at ``fps`` for ``seconds`` into a
    ``VisionPipeline`` on the wall clock, the arm reporting each frame's camera pose
    (``arm_state``): each system takes the newest frame whenever it is free. ``serial``: the
    systems one after the other in this process; ``concurrent``: a process each.
    """
    target = load_mockup(mockup).target_model()
    info = frames[0].info
    if mode == "concurrent":
        workers: InlineWorkers | ProcessWorkers = ProcessWorkers(systems, target, info)
    elif mode == "serial":
        estimators = {s: build_estimator(s, target, info) for s in systems}
        workers = InlineWorkers(estimators, None)
    else:
        raise ValueError(f"mode must be serial or concurrent; got {mode!r}")
    # Base, flange and camera frames are one, the carriage is at the world's origin with the
    # target: X_WC = X_BE, so the arm's state is the camera's pose (``arm_state``).
    geometry = RigGeometry(
        Pose.identity(), Pose.identity(), np.array([1.0, 0.0, 0.0]), Pose.identity(), 1.0
    )
    pipeline = VisionPipeline(
        systems=systems,
        fusion=PoseFusion(target),
        history=StateHistory(geometry),
        workers=workers,
        config=VisionConfig(max_frame_age_s=5.0, log_frames_every_s=0.0),
    )
    records: list[VisionRecord] = []
    try:
        t0 = time.monotonic()
        pipeline.begin(t0)
        seq, next_frame = 0, t0
        source = frames[0]
        while (now := time.monotonic()) < t0 + seconds:
            due = now >= next_frame
            if due:
                source = frames[seq % len(frames)]
            pipeline.publish_state(arm_state(source, now))
            if due:
                frame = Frame(source.image, now, info, seq, source.truth, arrival_stamp=now)
                pipeline.on_frame(frame, now)
                seq += 1
                next_frame += 1.0 / fps
            pipeline.step(time.monotonic())
            records.extend(r for r in pipeline.drain() if isinstance(r, VisionRecord))
            remaining = max(0.0, next_frame - time.monotonic())
            if isinstance(workers, ProcessWorkers) and workers.connections():
                wait(workers.connections(), timeout=remaining)
            else:
                time.sleep(remaining)
        elapsed = time.monotonic() - t0
    finally:
        pipeline.close()
    latency = np.array([r.t - r.arrival_t for r in records]) * 1000.0
    rates = {s: sum(r.system == s for r in records) / elapsed for s in systems}
    if progress is not None:
        progress(f"  {mode}: {len(records)} results in {elapsed:.1f} s")
    return PipelineTiming(
        mode,
        seq,
        elapsed,
        min(rates.values()),
        float(np.median(latency)) if latency.size else math.nan,
        float(np.percentile(latency, 95)) if latency.size else math.nan,
        rates,
    )
