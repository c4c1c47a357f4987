"""Timing benchmarks (not tests): numbers for notes and READMEs, measured on this machine."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from rich.console import Console

from configuration.camera import load_camera
from configuration.mockup import load_mockup
from configuration.render import NoiseConfig, RenderConfig
from hil.evaluation.scenarios import camera_pose_for, target_offset
from sim_backends.renderer import PybulletRenderer
from sim_backends.scene import MockupScene
from sim_backends.sensor import expose, frame_rng


@dataclass(frozen=True, slots=True)
class RenderTiming:
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
        for supersample in supersamples:
            renderer = PybulletRenderer(scene, info, RenderConfig(supersample=supersample))
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
                    distance, supersample, float(np.median(times)), float(np.percentile(times, 95))
                )
                if progress is not None:
                    progress.print(
                        f"  {distance:.1f} m, supersample {supersample}: {row.median_ms:.1f} ms"
                    )
                rows.append(row)
    return rows


@dataclass(frozen=True, slots=True)
class EstimatorTiming:
    system: str
    mode: str  # "tracking" (prior given) or "acquisition" (no prior)
    distance_m: float
    median_ms: float
    p95_ms: float
    valid: int
    frames: int


def estimator_timings(
    systems: tuple[str, ...],
    *,
    camera: str = "reference",
    mockup: str = "default",
    distances_m: tuple[float, ...] = (3.0, 2.0, 1.2),
    frames: int = 20,
    noise: str = "low",
    seed: int = 0,
    progress: Console | None = None,
) -> list[EstimatorTiming]:
    """Wall time per frame of each estimator, one thread, in two modes: tracking (the prior is
    the previous frame's estimate, as in a running loop) and acquisition (no prior). Frames
    follow the reference's turn-about-y maneuver with the given noise."""
    import cv2

    from estimators.frame import Frame
    from estimators.registry import build_estimator
    from hil.evaluation.scenarios import MANEUVERS

    cv2.setNumThreads(1)
    info = load_camera(camera).camera_info()
    mockup_config = load_mockup(mockup)
    target = mockup_config.target_model()
    noise_config = NoiseConfig(preset=noise)
    maneuver = next(m for m in MANEUVERS if m.name == "turn_y_10deg")
    rows = []
    with MockupScene(mockup_config) as scene:
        renderer = PybulletRenderer(scene, info, RenderConfig())
        for distance in distances_m:
            images = []
            for i in range(frames):
                X_WC, _ = camera_pose_for(distance, maneuver.offset(i / frames))
                rendering = renderer.render(X_WC)
                images.append(
                    expose(
                        rendering.image, rendering.depth_m, info.K, noise_config, frame_rng(seed, i)
                    )
                )
            for system in systems:
                estimator = build_estimator(system, target, info)
                for mode in ("tracking", "acquisition"):
                    times, valid, prior = [], 0, None
                    for i, image in enumerate(images):
                        frame = Frame(image, i / 30.0, info, i)
                        start = time.perf_counter()
                        m = estimator.estimate(frame, prior if mode == "tracking" else None)
                        times.append(1000.0 * (time.perf_counter() - start))
                        valid += m.valid
                        prior = m.prior if m.valid else None
                    row = EstimatorTiming(
                        system,
                        mode,
                        distance,
                        float(np.median(times)),
                        float(np.percentile(times, 95)),
                        valid,
                        frames,
                    )
                    if progress is not None:
                        progress.print(
                            f"  {system} {mode} {distance:.1f} m: {row.median_ms:.1f} ms"
                        )
                    rows.append(row)
    return rows
