"""The reference study's test matrix, run against simulator ground truth.

Cases: distances 3 / 2 / 1.2 m with the camera square to the face; maneuvers none, ±10 cm along
x / y / z and ±10° about x / y / z, each run as one sine period over the case's frames; noise
none / low / high; the reference camera. Each case starts without a prior (acquisition) and then
tracks frame to frame, exactly as a running system would. Noise-free renderings are shared by
all noise levels and systems of a case; each frame's noise depends only on (seed, case, frame).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from drivers.base import Frame, GroundTruth
from estimators.measurement import Tracker
from estimators.registry import build_estimator
from hil.config import NoiseConfig, RenderConfig, load_camera, load_mockup
from hil.evaluation import MeasurementError, measurement_error
from hil.reference import reference_text
from hil.scenarios import MANEUVERS, REFERENCE_DISTANCES_M, Maneuver, camera_pose_for
from sim_backends.renderer import PybulletRenderer
from sim_backends.scene import MockupScene
from sim_backends.sensor import expose, frame_rng

NOISE_LEVELS = ("none", "low", "high")
#: A valid measurement this far from the truth is a wrong lock (position m, attitude rad).
WRONG_LOCK_POSITION_M = 0.05
WRONG_LOCK_ATTITUDE_RAD = math.radians(10.0)
#: … unless its own covariance covers the error: 99.9 % quantiles of χ² with 6 and 5 degrees of
#: freedom (a measurement without a covariance has NaN here, which never covers).
WRONG_LOCK_NEES_POSE = 22.46
WRONG_LOCK_NEES_CIRCLE = 20.52
#: Intensity of a blank frame (a lens cap, a dropout): uniform grey, then the case's noise.
BLANK_LEVEL = 0.35


@dataclass(frozen=True, slots=True)
class MatrixSpec:
    """What to run. ``estimator_options`` go to every estimator factory.

    ``acquire_every_frame`` drops the prior before every frame (measures acquisition alone);
    ``blank_frames`` replaces those frame indices by blank frames (a forced loss, to measure
    re-acquisition).
    """

    systems: tuple[str, ...]
    distances_m: tuple[float, ...] = REFERENCE_DISTANCES_M
    maneuvers: tuple[str, ...] = tuple(m.name for m in MANEUVERS)
    noises: tuple[str, ...] = NOISE_LEVELS
    frames: int = 30
    seed: int = 0
    camera: str = "reference"
    mockup: str = "default"
    supersample: int = 1
    estimator_options: dict = field(default_factory=dict)
    acquire_every_frame: bool = False
    blank_frames: tuple[int, ...] = ()


@dataclass(frozen=True, slots=True)
class FrameResult:
    system: str
    distance_m: float
    maneuver: str
    noise: str
    index: int
    status: str
    reason: str
    error: MeasurementError
    residual_px: float
    time_ms: float
    had_prior: bool
    blank: bool = False
    ambiguous: bool = False


def _maneuver(name: str) -> Maneuver:
    for m in MANEUVERS:
        if m.name == name:
            return m
    raise ValueError(f"unknown maneuver {name!r}; known: {', '.join(m.name for m in MANEUVERS)}")


def _case_seed(spec: MatrixSpec, distance_index: int, maneuver_index: int, noise_index: int) -> int:
    return spec.seed * 1_000_003 + distance_index * 10_007 + maneuver_index * 101 + noise_index


def run_case_group(spec: MatrixSpec, distance_m: float, maneuver_name: str) -> list[FrameResult]:
    """All noise levels and systems of one (distance, maneuver): render once, estimate many."""
    camera = load_camera(spec.camera).camera_info()
    mockup = load_mockup(spec.mockup)
    target = mockup.target_model()
    maneuver = _maneuver(maneuver_name)
    distance_index = spec.distances_m.index(distance_m)
    maneuver_index = spec.maneuvers.index(maneuver_name)
    with MockupScene(mockup) as scene:
        renderer = PybulletRenderer(scene, camera, RenderConfig(supersample=spec.supersample))
        renderings = []
        for i in range(spec.frames):
            X_WC, _ = camera_pose_for(distance_m, maneuver.offset(i / spec.frames))
            renderings.append(renderer.render(X_WC))
    results = []
    for noise_index, noise in enumerate(spec.noises):
        noise_config = NoiseConfig(preset=noise)
        seed = _case_seed(spec, distance_index, maneuver_index, noise_index)
        trackers = {
            s: Tracker(build_estimator(s, target, camera, **spec.estimator_options))
            for s in spec.systems
        }
        for i, rendering in enumerate(renderings):
            blank = i in spec.blank_frames
            scene_image = np.full_like(rendering.image, BLANK_LEVEL) if blank else rendering.image
            image = expose(
                scene_image, rendering.depth_m, camera.K, noise_config, frame_rng(seed, i)
            )
            frame = Frame(
                image, float(i) / 30.0, camera, i, GroundTruth(rendering.X_CT, rendering.X_WC)
            )
            for system, tracker in trackers.items():
                if spec.acquire_every_frame:
                    tracker.reset()
                had_prior = tracker.prior_X_CT is not None
                m = tracker.update(frame)
                results.append(
                    FrameResult(
                        system,
                        distance_m,
                        maneuver_name,
                        noise,
                        i,
                        m.status,
                        m.reason,
                        measurement_error(m, rendering.X_CT, target),
                        m.residual_px,
                        m.time_ms,
                        had_prior,
                        blank,
                        m.ambiguous,
                    )
                )
    return results


def run_matrix(
    spec: MatrixSpec, *, jobs: int = 1, progress: Callable[[str], None] | None = None
) -> list[FrameResult]:
    """Run every case of ``spec``; ``jobs`` > 1 spreads (distance, maneuver) groups over processes."""
    for name in spec.maneuvers:
        _maneuver(name)
    groups = [(d, m) for d in spec.distances_m for m in spec.maneuvers]
    results: list[FrameResult] = []
    start = time.perf_counter()

    def report(done: int, group: tuple[float, str]) -> None:
        if progress is not None:
            elapsed = time.perf_counter() - start
            progress(f"[{done}/{len(groups)}] {group[0]:.1f} m {group[1]} ({elapsed:.0f} s)")

    if jobs <= 1:
        for done, group in enumerate(groups, 1):
            results.extend(run_case_group(spec, *group))
            report(done, group)
    else:
        with ProcessPoolExecutor(max_workers=jobs) as pool:
            futures = [pool.submit(run_case_group, spec, *g) for g in groups]
            for done, (future, group) in enumerate(zip(futures, groups, strict=True), 1):
                results.extend(future.result())
                report(done, group)
    return results


# --- summaries ------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class CaseSummary:
    """Statistics of one (system, distance, maneuver, noise) case over its frames.

    Errors are over the frames with a valid estimate; ``position`` is the translation (6-DOF)
    or circle-centre (5-DOF) error, ``attitude`` the rotation or normal error; ``normal`` the
    circle normal's error when a circle pose is measured. ``wrong`` counts valid frames beyond
    the wrong-lock gate, not covered by their own covariance and not flagged ambiguous (``ambiguous`` counts the flagged ones);
    ``recovery_max`` is the longest run of lost frames after a blank
    stretch (frames to re-acquire); blank frames are excluded from everything else but ``lost``.
    """

    system: str
    distance_m: float
    maneuver: str
    noise: str
    frames: int
    valid: int
    position_mean_m: float
    position_std_m: float
    attitude_mean_rad: float
    attitude_std_rad: float
    roll_mean_rad: float
    lost: int
    longest_loss: int
    acquired_ok: int
    acquired_tries: int
    time_median_ms: float
    time_p95_ms: float
    normal_mean_rad: float = math.nan
    normal_std_rad: float = math.nan
    wrong: int = 0
    recovery_max: int = 0
    blank: int = 0
    ambiguous: int = 0


def _recovery(rows: Sequence[FrameResult]) -> int:
    """Longest run of lost frames right after a blank stretch (0 when valid at once)."""
    longest = 0
    for k, r in enumerate(rows):
        if r.blank and (k + 1 < len(rows) and not rows[k + 1].blank):
            run = 0
            for after in rows[k + 1 :]:
                if after.status != "lost" or after.blank:
                    break
                run += 1
            longest = max(longest, run)
    return longest


def _wrong_lock(r: FrameResult) -> bool:
    """A valid, unqualified answer beyond the gate that its own covariance does not cover
    (normalised error beyond the 99.9 % χ² quantile): a lock on the wrong thing, not a noisy
    answer that says it is noisy. An answer flagged ambiguous is not a wrong lock either."""
    if r.status == "lost" or r.ambiguous:
        return False
    beyond = not r.error.position_m <= WRONG_LOCK_POSITION_M or not (
        r.error.attitude_rad <= WRONG_LOCK_ATTITUDE_RAD
    )
    if not math.isnan(r.error.nees_pose):
        covered = r.error.nees_pose <= WRONG_LOCK_NEES_POSE
    else:
        covered = r.error.nees_circle <= WRONG_LOCK_NEES_CIRCLE
    return beyond and not covered


def _longest_run(flags: Sequence[bool]) -> int:
    longest = current = 0
    for flag in flags:
        current = current + 1 if flag else 0
        longest = max(longest, current)
    return longest


def summarize(results: Iterable[FrameResult]) -> list[CaseSummary]:
    cases: dict[tuple, list[FrameResult]] = {}
    for r in results:
        cases.setdefault((r.system, r.distance_m, r.maneuver, r.noise), []).append(r)
    summaries = []
    for (system, distance, maneuver, noise), rows in cases.items():
        rows.sort(key=lambda r: r.index)
        seen = [r for r in rows if not r.blank]
        valid = [r for r in seen if r.status != "lost"]
        pos = np.array([r.error.position_m for r in valid])
        att = np.array([r.error.attitude_rad for r in valid])
        roll = np.array([r.error.roll_rad for r in valid if not math.isnan(r.error.roll_rad)])
        normal = np.array([r.error.normal_rad for r in valid if not math.isnan(r.error.normal_rad)])
        no_prior = [r for r in seen if not r.had_prior]
        times = np.array([r.time_ms for r in seen])
        summaries.append(
            CaseSummary(
                system,
                distance,
                maneuver,
                noise,
                len(seen),
                len(valid),
                float(pos.mean()) if len(pos) else math.nan,
                float(pos.std()) if len(pos) else math.nan,
                float(att.mean()) if len(att) else math.nan,
                float(att.std()) if len(att) else math.nan,
                float(roll.mean()) if len(roll) else math.nan,
                len(seen) - len(valid),
                _longest_run([r.status == "lost" for r in rows]),
                sum(r.status == "acquired" for r in no_prior),
                len(no_prior),
                float(np.median(times)),
                float(np.percentile(times, 95)),
                float(normal.mean()) if len(normal) else math.nan,
                float(normal.std()) if len(normal) else math.nan,
                sum(_wrong_lock(r) for r in valid),
                _recovery(rows),
                len(rows) - len(seen),
                sum(r.ambiguous for r in valid),
            )
        )
    return summaries


def markdown_table(summaries: Sequence[CaseSummary]) -> str:
    """One row per case: our mean ± std beside the reference's low-noise range, wrong locks,
    and — when a system measures circles — the circle normal's error and the roll error; with
    blank frames, the frames needed to re-acquire after them."""
    circles = any(not math.isnan(s.normal_mean_rad) for s in summaries)
    blanks = any(s.blank for s in summaries)
    header = (
        "| system | distance | maneuver | noise | valid | wrong | position mean ± std "
        "| attitude mean ± std "
    )
    rule = "|---|---|---|---|---|---|---|---|"
    if circles:
        header += "| normal mean ± std | roll mean "
        rule += "---|---|"
    header += "| reference (low noise) | longest loss "
    rule += "---|---|"
    if blanks:
        header += "| re-acquired after "
        rule += "---|"
    header += "| median / p95 ms |"
    rule += "---|"
    lines = [header, rule]
    for s in sorted(summaries, key=lambda s: (s.system, -s.distance_m, s.noise, s.maneuver)):
        row = (
            f"| {s.system} | {s.distance_m:.1f} m | {s.maneuver} | {s.noise} | {s.valid}/{s.frames} "
            f"| {s.wrong}{f' ({s.ambiguous} amb.)' if s.ambiguous else ''} "
            f"| {100 * s.position_mean_m:.2f} ± {100 * s.position_std_m:.2f} cm "
            f"| {math.degrees(s.attitude_mean_rad):.2f} ± {math.degrees(s.attitude_std_rad):.2f}° "
        )
        if circles:
            row += (
                f"| {math.degrees(s.normal_mean_rad):.2f} ± {math.degrees(s.normal_std_rad):.2f}° "
                f"| {math.degrees(s.roll_mean_rad):.2f}° "
            )
        row += f"| {reference_text(s.system, s.distance_m)} | {s.longest_loss} "
        if blanks:
            row += f"| {s.recovery_max + 1 if s.blank else '–'} "
        row += f"| {s.time_median_ms:.1f} / {s.time_p95_ms:.1f} |"
        lines.append(row)
    return "\n".join(lines) + "\n"
