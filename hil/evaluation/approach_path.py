"""The reference study's approach, as a test path: the camera closes from 2.5 m to 0.5 m in
front of the target while re-centring it from an off-centre, slightly rotated start.

Each frame is rendered with ground truth and fed to a ``Tracker`` (starting without a prior),
so the run measures tracking continuity, errors along the way, and — for circle features —
error against the fraction of the ring's circumference in view at close range. A frame is
*over-confident* when it claims a pose (not flagged ambiguous) whose error lies beyond its own
3σ (NEES above the 99.73 % χ² quantile): the measurement that would steer the arm off without
warning (issue 13).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from configuration.camera import load_camera
from configuration.mockup import MockupConfig, load_mockup
from configuration.random_mockup import is_random_name, named_lighting, seed_of
from configuration.render import Lighting, NoiseConfig, RenderConfig
from estimators.conics import circle_points
from estimators.frame import CameraInfo, Frame, GroundTruth
from estimators.geometry import Pose
from estimators.measurement import Tracker
from estimators.registry import build_estimator
from hil.evaluation.errors import MeasurementError, measurement_error
from hil.evaluation.scenarios import camera_pose_for, target_offset
from sim_backends.renderer import make_renderer
from sim_backends.scene import MockupScene
from sim_backends.sensor import expose, frame_rng


@dataclass(frozen=True, slots=True)
class ApproachPath:
    """Start and end of the approach: distances (m) and the target's offset at the start
    (m and rad about its own axes, as ``hil.evaluation.scenarios.target_offset``); the offset shrinks to
    zero along the path (smoothstep in time), the distance closes likewise."""

    start_distance_m: float = 2.5
    end_distance_m: float = 0.5
    start_offset: tuple[float, float, float, float, float, float] = (
        0.35,
        -0.25,
        0.0,
        math.radians(6.0),
        math.radians(-8.0),
        math.radians(15.0),
    )

    def offset(self, phase: float) -> tuple[float, Pose]:
        """(distance m, target offset) at ``phase`` in [0, 1]."""
        s = 3 * phase**2 - 2 * phase**3  # smoothstep: starts and stops gently
        distance = self.start_distance_m + (self.end_distance_m - self.start_distance_m) * s
        return distance, target_offset(*((1.0 - s) * np.array(self.start_offset)))


@dataclass(frozen=True, slots=True)
class ApproachFrame:
    index: int
    distance_m: float
    status: str
    reason: str
    error: MeasurementError
    ring_visible: float  # fraction of the reference circle's circumference in view
    six_dof: bool
    time_ms: float
    ambiguous: bool = False
    mockup: str = ""

    @property
    def overconfident(self) -> bool:
        """A valid, unflagged answer whose error lies beyond its own 3σ (see module docstring)."""
        if self.status == "lost" or self.ambiguous:
            return False
        if self.six_dof:
            return bool(self.error.nees_pose > THREE_SIGMA_NEES[6])
        return bool(self.error.nees_circle > THREE_SIGMA_NEES[5])


#: NEES beyond which an error lies outside its covariance's "3σ" (99.73 %) region.
THREE_SIGMA_NEES = {dof: float(chi2.ppf(0.9973, dof)) for dof in (5, 6)}


def circle_visible_fraction(X_CT: Pose, center_T, normal_T, radius: float, camera) -> float:
    """Fraction of a target circle's circumference that the camera images."""
    rim = X_CT.apply(circle_points(center_T, normal_T, radius, 360))
    return float(camera.in_view(rim).mean())


@dataclass(frozen=True, slots=True)
class PathFrame:
    """One rendered frame of the approach path with its distance (m); the frame carries its
    ground truth (``frame.truth.X_CT``)."""

    index: int
    distance_m: float
    frame: Frame


def render_approach(
    info: CameraInfo,
    mockup_config: MockupConfig,
    *,
    frames: int = 120,
    noise: str = "low",
    path: ApproachPath | None = None,
    seed: int = 0,
    fps: float = 30.0,
    light: Lighting | None = None,
    auto_exposure: bool = False,
    supersample: int = 1,
    start: int = 0,
) -> Iterator[PathFrame]:
    """Render the approach ``path`` in ``frames`` frames (seeded sensor noise, the camera's
    auto-exposure if asked) under ``light`` (the default light when None), ``supersample``²
    samples a pixel (as ``RenderConfig``), frame ``i`` stamped ``i / fps``; from frame ``start``
    on (each frame is rendered as in the whole path: one can be looked at alone)."""
    path = path or ApproachPath()
    noise_config = NoiseConfig(preset=noise, auto_exposure=auto_exposure)
    render = RenderConfig(supersample=supersample, lighting=light or Lighting())
    with MockupScene(mockup_config) as scene:
        renderer = make_renderer(scene, info, render)
        for i in range(start, frames):
            distance, offset = path.offset(i / max(frames - 1, 1))
            X_WC, _ = camera_pose_for(distance, offset)
            rendering = renderer.render(X_WC)
            image = expose(
                rendering.image, rendering.depth_m, info.K, noise_config, frame_rng(seed, i)
            )
            truth = GroundTruth(rendering.X_CT, rendering.X_WC)
            yield PathFrame(i, distance, Frame(image, i / fps, info, i, truth))


def run_approach(
    system: str,
    *,
    frames: int = 120,
    noise: str = "low",
    camera: str = "reference",
    mockup: str = "default",
    path: ApproachPath | None = None,
    seed: int = 0,
    circle: str = "ring_outer",
    estimator_options: dict | None = None,
    lighting: str = "default",
    auto_exposure: bool = False,
    supersample: int = 1,
) -> list[ApproachFrame]:
    """Track ``system`` along the approach; one result per frame. ``lighting``: ``default``,
    ``harsh`` or ``random`` (the mock-up's random light); ``auto_exposure``: the sensor's;
    ``supersample``: the renderer's samples per pixel side (1: the reference study's path)."""
    info = load_camera(camera).camera_info()
    mockup_config = load_mockup(mockup)
    target = mockup_config.target_model()
    reference = target.circle(circle)
    tracker = Tracker(build_estimator(system, target, info, **(estimator_options or {})))
    light = named_lighting(lighting, seed_of(mockup) if is_random_name(mockup) else seed)
    results = []
    for rendered in render_approach(
        info,
        mockup_config,
        frames=frames,
        noise=noise,
        path=path,
        seed=seed,
        light=light,
        auto_exposure=auto_exposure,
        supersample=supersample,
    ):
        m = tracker.update(rendered.frame)
        X_CT = rendered.frame.truth.X_CT
        results.append(
            ApproachFrame(
                rendered.index,
                rendered.distance_m,
                m.status,
                m.reason,
                measurement_error(m, X_CT, target),
                circle_visible_fraction(
                    X_CT, reference.center_T, reference.normal_T, reference.radius, info
                ),
                m.X_CT is not None,
                m.time_ms,
                m.ambiguous,
                str(mockup),
            )
        )
    return results


def _valid_errors(rows: list[ApproachFrame]) -> tuple[list[ApproachFrame], np.ndarray, np.ndarray]:
    """The valid frames of ``rows``, their position errors (cm) and their normal errors (°) —
    the attitude error for frames without a circle pose."""
    valid = [r for r in rows if r.status != "lost"]
    pos = np.array([r.error.position_m for r in valid]) * 100
    att = np.degrees(
        [
            r.error.normal_rad if not math.isnan(r.error.normal_rad) else r.error.attitude_rad
            for r in valid
        ]
    )
    return valid, pos, att


def markdown_approach(results: list[ApproachFrame], bins: tuple[float, ...]) -> str:
    """Errors binned by distance (``bins`` edges in m, descending): valid frames, position and
    attitude (normal for circle poses) mean / max, visible circumference, 6-DOF share."""
    lines = [
        "| distance | frames | valid | 6-DOF | circle in view | position mean / max "
        "| normal (or attitude) mean / max |",
        "|---|---|---|---|---|---|---|",
    ]
    for hi, lo in itertools.pairwise(bins):
        rows = [r for r in results if lo < r.distance_m <= hi]
        if not rows:
            continue
        valid, pos, att = _valid_errors(rows)
        visible = np.array([r.ring_visible for r in rows])
        lines.append(
            f"| {hi:.2f}–{lo:.2f} m | {len(rows)} | {len(valid)} | {sum(r.six_dof for r in valid)} "
            f"| {100 * visible.min():.0f}–{100 * visible.max():.0f} % "
            + (
                f"| {pos.mean():.2f} / {pos.max():.2f} cm | {att.mean():.2f} / {att.max():.2f}° |"
                if valid
                else "| – | – |"
            )
        )
    return "\n".join(lines) + "\n"


def markdown_visible(results: list[ApproachFrame], bins: tuple[float, ...]) -> str:
    """Errors of the frames whose circle is partly out of view, binned by the fraction of its
    circumference in view (``bins`` edges, descending, e.g. 1.0, 0.9, …)."""
    lines = [
        "| circle in view | frames | valid | position mean / max | normal (or attitude) mean / max |",
        "|---|---|---|---|---|",
    ]
    for hi, lo in itertools.pairwise(bins):
        rows = [r for r in results if lo <= r.ring_visible < hi]
        if not rows:
            continue
        valid, pos, att = _valid_errors(rows)
        lines.append(
            f"| {100 * lo:.0f}–{100 * hi:.0f} % | {len(rows)} | {len(valid)} "
            + (
                f"| {pos.mean():.3f} / {pos.max():.3f} cm | {att.mean():.3f} / {att.max():.3f}° |"
                if valid
                else "| – | – |"
            )
        )
    return "\n".join(lines) + "\n"
