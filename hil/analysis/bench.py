"""Timing benchmarks (not tests): numbers for notes and READMEs, measured on this machine.

``render_timings``: the renderer's time per frame. ``comparison_timings`` (``satgrasp bench
estimate``, issue 12): on the same rendered frames, each system's tracking (given a prior 1 cm /
1° off the truth) and acquisition (no prior) time and accuracy, and the plain OpenCV pipeline
of ``hil.evaluation.opencv_pipeline`` given the same prior, timed in the same run, one thread.
``full_frame_timings``: the three systems plus fusion on every frame, serial and concurrent,
through ``hil.analysis.bench_loop.pipeline_timing`` (the real ``VisionPipeline``).
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass

import numpy as np
from rich.console import Console

from configuration.camera import load_camera
from configuration.mockup import load_mockup
from configuration.render import NoiseConfig, RenderConfig
from estimators.frame import CameraInfo, Frame, GroundTruth
from estimators.geometry import Pose
from estimators.measurement import Measurement
from estimators.registry import build_estimator
from estimators.target import TargetModel
from hil.analysis.bench_loop import PipelineTiming, pipeline_timing, tracking_frames
from hil.evaluation.errors import measurement_error
from hil.evaluation.opencv_pipeline import (
    NO_ERROR,
    OPENCV_SYSTEMS,
    EstimateError,
    opencv_error,
    opencv_pipeline,
)
from hil.evaluation.scenarios import MANEUVERS, camera_pose_for, target_offset
from sim_backends.renderer import Renderer, make_renderer
from sim_backends.scene import MockupScene
from sim_backends.sensor import expose, frame_rng


@dataclass(frozen=True, slots=True)
class RenderTiming:
    engine: str
    distance_m: float
    supersample: int
    median_ms: float
    p95_ms: float


def render_timings(
    camera: str,
    mockup: str,
    *,
    distances_m: tuple[float, ...] = (3.0, 2.0, 1.2, 0.5),
    supersamples: tuple[int, ...] = (1, 2),
    engines: tuple[str, ...] = ("pybullet", "raster"),
    repeats: int = 9,
    progress: Console | None = None,
) -> list[RenderTiming]:
    """Time render + low-noise exposure of one frame per case; the pose is a generic one
    (small offset and tilt) so no edge sits on the pixel grid."""
    info = load_camera(camera).camera_info()
    noise = NoiseConfig(preset="low")
    rows = []
    offset = target_offset(0.02, -0.015, 0.0, np.radians(3.0), np.radians(-4.0), np.radians(7.0))
    with MockupScene(load_mockup(mockup)) as scene:
        for engine, supersample in itertools.product(engines, supersamples):
            config = RenderConfig(engine=engine, supersample=supersample)
            renderer = make_renderer(scene, info, config)
            for distance in distances_m:
                X_WC, _ = camera_pose_for(distance, offset)
                renderer.render(X_WC)  # warm-up
                times = []
                for i in range(repeats):
                    start = time.perf_counter()
                    rendering = renderer.render(X_WC)
                    expose(rendering.image, rendering.depth_m, info.K, noise, frame_rng(0, i))
                    times.append(1000.0 * (time.perf_counter() - start))
                row = RenderTiming(
                    engine,
                    distance,
                    supersample,
                    float(np.median(times)),
                    float(np.percentile(times, 95)),
                )
                if progress is not None:
                    progress.print(
                        f"  {engine}, {distance:.1f} m, supersample {supersample}: "
                        f"{row.median_ms:.1f} ms"
                    )
                rows.append(row)
    return rows


#: The prior the tracking runs and the OpenCV pipelines get: the truth moved by this much in a
#: random direction (the issue's "same 1 cm / 1° prior").
PRIOR_OFFSET_M = 0.01
PRIOR_OFFSET_RAD = math.radians(1.0)
DISTANCES_M: tuple[float, ...] = (3.0, 2.0, 1.2, 0.5)
SYSTEMS: tuple[str, ...] = ("corners", "lines", "ellipses")


@dataclass(frozen=True, slots=True, eq=False)
class BenchFrame:
    """A rendered frame (with its truth) and the prior every method is given for it."""

    frame: Frame
    X_CT_true: Pose
    prior_X_CT: Pose


def offset_prior(X_CT: Pose, rng: np.random.Generator) -> Pose:
    """``X_CT`` moved by ``PRIOR_OFFSET_M`` and turned by ``PRIOR_OFFSET_RAD`` (on the left, in
    C, as the measurement covariances are) about random directions."""
    axis = rng.normal(size=3)
    shift = rng.normal(size=3)
    turn = Pose.from_rotvec(PRIOR_OFFSET_RAD * axis / np.linalg.norm(axis), np.zeros(3))
    return Pose(turn.R @ X_CT.R, X_CT.p + PRIOR_OFFSET_M * shift / np.linalg.norm(shift))


def render_bench_frames(
    renderer: Renderer,
    info: CameraInfo,
    distance_m: float,
    noises: Sequence[str],
    *,
    frames: int,
    seed: int = 0,
) -> dict[str, list[BenchFrame]]:
    """``frames`` frames per noise level at ``distance_m`` along the reference's
    turn-about-y maneuver; each pose is rendered once and exposed at every noise level; the
    priors are seeded per frame (the same for every noise level)."""
    maneuver = next(m for m in MANEUVERS if m.name == "turn_y_10deg")
    out: dict[str, list[BenchFrame]] = {noise: [] for noise in noises}
    for i in range(frames):
        X_WC, _ = camera_pose_for(distance_m, maneuver.offset(i / max(frames, 1)))
        rendering = renderer.render(X_WC)
        prior = offset_prior(
            rendering.X_CT, np.random.default_rng([seed, i, round(100 * distance_m)])
        )
        for noise in noises:
            image = expose(
                rendering.image, rendering.depth_m, info.K, NoiseConfig(preset=noise),
                frame_rng(seed, i),
            )  # fmt: skip
            truth = GroundTruth(rendering.X_CT, rendering.X_WC)
            frame = Frame(image, i / 30.0, info, i, truth)
            out[noise].append(BenchFrame(frame, rendering.X_CT, prior))
    return out


def satgrasp_error(m: Measurement, X_CT_true: Pose, target: TargetModel) -> EstimateError:
    """Position and attitude error of a measurement, on the OpenCV pipeline's terms: for the
    ellipses the circle's centre and normal (no roll), else the pose (or, when only 5 DOF were
    measured, the circle)."""
    if not m.valid:
        return NO_ERROR
    error = measurement_error(m, X_CT_true, target)
    if m.system == "ellipses" and not math.isnan(error.center_m):
        return EstimateError(error.center_m, error.normal_rad)
    return EstimateError(error.position_m, error.attitude_rad)


@dataclass(frozen=True, slots=True)
class ComparisonRow:
    """One system on one set of frames (camera, distance, noise): satgrasp's tracking and
    acquisition and the OpenCV pipeline, each time per frame (ms, median and p95) and frames
    valid; accuracy as median position (m) and attitude (rad) errors over the valid frames of
    satgrasp's tracking and of the OpenCV pipeline. NaN where a method has no value (no OpenCV
    pipeline for a plugged-in system, nothing valid)."""

    system: str
    camera: str
    width: int
    height: int
    distance_m: float
    noise: str
    frames: int
    tracking_median_ms: float
    tracking_p95_ms: float
    tracking_valid: int
    acquisition_median_ms: float
    acquisition_p95_ms: float
    acquisition_valid: int
    opencv_median_ms: float
    opencv_p95_ms: float
    opencv_valid: int
    tracking_position_error_m: float
    tracking_attitude_error_rad: float
    opencv_position_error_m: float
    opencv_attitude_error_rad: float

    @property
    def time_ratio(self) -> float:
        """satgrasp tracking median / OpenCV median (≤ 1: satgrasp no slower)."""
        return _ratio(self.tracking_median_ms, self.opencv_median_ms)

    @property
    def position_accuracy_ratio(self) -> float:
        """OpenCV position error / satgrasp's (> 1: satgrasp more accurate)."""
        return _ratio(self.opencv_position_error_m, self.tracking_position_error_m)

    @property
    def attitude_accuracy_ratio(self) -> float:
        """OpenCV attitude error / satgrasp's (> 1: satgrasp more accurate)."""
        return _ratio(self.opencv_attitude_error_rad, self.tracking_attitude_error_rad)

    def to_dict(self) -> dict:
        """JSON-ready: the fields and the three ratios, NaN as None."""
        values = asdict(self) | {
            "time_ratio": self.time_ratio,
            "position_accuracy_ratio": self.position_accuracy_ratio,
            "attitude_accuracy_ratio": self.attitude_accuracy_ratio,
        }
        return {k: None if isinstance(v, float) and math.isnan(v) else v for k, v in values.items()}


def _ratio(a: float, b: float) -> float:
    return a / b if b > 0 and math.isfinite(a) and math.isfinite(b) else math.nan


def _stats(times_ms: Sequence[float]) -> tuple[float, float]:
    if not times_ms:
        return math.nan, math.nan
    return float(np.median(times_ms)), float(np.percentile(times_ms, 95))


def _median(values: Sequence[float]) -> float:
    finite = [v for v in values if math.isfinite(v)]
    return float(np.median(finite)) if finite else math.nan


def _timed(call: Callable[[], object]) -> tuple[object, float]:
    start = time.perf_counter()
    result = call()
    return result, 1000.0 * (time.perf_counter() - start)


def compare_system(
    system: str,
    frames: Sequence[BenchFrame],
    target: TargetModel,
    *,
    camera: str,
    distance_m: float,
    noise: str,
) -> ComparisonRow:
    """Time and judge ``system`` on ``frames``: satgrasp tracking (the frame's prior), satgrasp
    acquisition (no prior, a fresh estimator) and the OpenCV pipeline (the same prior), each
    over all frames in turn; one warm-up call of each on the first frame is not counted."""
    info = frames[0].frame.info
    first = frames[0]
    tracker = build_estimator(system, target, info)
    tracker.estimate(first.frame, first.prior_X_CT)
    tracking, tracking_errors, tracking_valid = [], [], 0
    for f in frames:
        m, ms = _timed(lambda f=f: tracker.estimate(f.frame, f.prior_X_CT))
        tracking.append(ms)
        tracking_valid += m.valid
        tracking_errors.append(satgrasp_error(m, f.X_CT_true, target))
    # A fresh estimator: nothing the tracking runs left behind can help acquisition.
    acquirer = build_estimator(system, target, info)
    acquirer.estimate(first.frame, None)
    acquisition, acquisition_valid = [], 0
    for f in frames:
        m, ms = _timed(lambda f=f: acquirer.estimate(f.frame, None))
        acquisition.append(ms)
        acquisition_valid += m.valid
    opencv, opencv_errors, opencv_valid = [], [], 0
    if system in OPENCV_SYSTEMS:
        pipeline = opencv_pipeline(system, target, info)
        pipeline(first.frame, first.prior_X_CT)
        for f in frames:
            estimate, ms = _timed(lambda f=f: pipeline(f.frame, f.prior_X_CT))
            opencv.append(ms)
            opencv_valid += estimate.valid
            opencv_errors.append(opencv_error(estimate, f.X_CT_true, target))
    return ComparisonRow(
        system, camera, info.width, info.height, distance_m, noise, len(frames),
        *_stats(tracking), tracking_valid,
        *_stats(acquisition), acquisition_valid,
        *_stats(opencv), opencv_valid,
        _median([e.position_m for e in tracking_errors]),
        _median([e.attitude_rad for e in tracking_errors]),
        _median([e.position_m for e in opencv_errors]),
        _median([e.attitude_rad for e in opencv_errors]),
    )  # fmt: skip


def comparison_timings(
    systems: Sequence[str] = SYSTEMS,
    *,
    cameras: Sequence[str] = ("reference",),
    mockup: str = "default",
    distances_m: Sequence[float] = DISTANCES_M,
    noises: Sequence[str] = ("low",),
    frames: int = 10,
    seed: int = 0,
    progress: Console | None = None,
) -> list[ComparisonRow]:
    """Every system against its OpenCV pipeline on the same frames, per camera, distance and
    noise level (``compare_system``), one thread (``cv2.setNumThreads(1)``)."""
    import cv2

    if frames < 1:
        raise ValueError(f"frames must be at least 1; got {frames}")
    cv2.setNumThreads(1)
    mockup_config = load_mockup(mockup)
    target = mockup_config.target_model()
    rows = []
    for camera in cameras:
        info = load_camera(camera).camera_info()
        with MockupScene(mockup_config) as scene:
            renderer = make_renderer(scene, info, RenderConfig())
            for distance in distances_m:
                if progress is not None:
                    progress.print(f"[bold]{camera}[/] {distance:.1f} m: rendering {frames} frames")
                sets = render_bench_frames(
                    renderer, info, distance, noises, frames=frames, seed=seed
                )
                for noise in noises:
                    for system in systems:
                        row = compare_system(
                            system, sets[noise], target,
                            camera=camera, distance_m=distance, noise=noise,
                        )  # fmt: skip
                        if progress is not None:
                            progress.print(_progress_line(row))
                        rows.append(row)
    return rows


def _progress_line(row: ComparisonRow) -> str:
    return (
        f"  {row.system} {row.noise}: tracking {row.tracking_median_ms:.1f} ms "
        f"({row.tracking_valid}/{row.frames}), acquisition {row.acquisition_median_ms:.1f} ms "
        f"({row.acquisition_valid}/{row.frames}), OpenCV {row.opencv_median_ms:.1f} ms "
        f"({row.opencv_valid}/{row.frames}), ratio {row.time_ratio:.2f}"
    )


@dataclass(frozen=True, slots=True)
class FullFrameRow:
    """The three systems plus fusion on a camera's frames, ``mode`` serial (one process) or
    concurrent (a process per system): frames fully processed per second and the latency
    from a frame's arrival to its fusion (ms)."""

    camera: str
    width: int
    height: int
    mode: str
    fps: float
    seconds: float
    frames_per_s: float
    latency_p50_ms: float
    latency_p95_ms: float

    def to_dict(self) -> dict:
        values = asdict(self)
        return {k: None if isinstance(v, float) and math.isnan(v) else v for k, v in values.items()}


def full_frame_timings(
    cameras: Sequence[str] = ("reference",),
    *,
    systems: Sequence[str] = SYSTEMS,
    mockup: str = "default",
    fps: float = 30.0,
    seconds: float = 10.0,
    progress: Console | None = None,
) -> list[FullFrameRow]:
    """``bench_loop.pipeline_timing`` (the same measurement as ``satgrasp bench loop``) serial
    and concurrent, per camera, on a stretch of the approach seen at camera rate
    (``bench_loop.tracking_frames``)."""
    import cv2

    cv2.setNumThreads(1)
    rows = []
    for camera in cameras:
        if progress is not None:
            progress.print(f"[bold]{camera}[/] full frame: rendering a stretch of the approach")
        frames = tracking_frames(camera, mockup)
        info = frames[0].info
        for mode in ("serial", "concurrent"):
            timing: PipelineTiming = pipeline_timing(
                mode, frames, tuple(systems), mockup=mockup, fps=fps, seconds=seconds,
                progress=None if progress is None else progress.print,
            )  # fmt: skip
            row = FullFrameRow(
                camera, info.width, info.height, mode, fps, timing.seconds,
                timing.frames_per_s, timing.latency_p50_ms, timing.latency_p95_ms,
            )  # fmt: skip
            rows.append(row)
    return rows
