"""The reference study's test matrix, run against simulator ground truth.

Cases: distances 3 / 2 / 1.2 m with the camera square to the face; maneuvers none, ±10 cm along
x / y / z and ±10° about x / y / z, each run as one sine period over the case's frames; noise
none / low / high; the reference camera. Each case starts without a prior (acquisition) and then
tracks frame to frame, exactly as a running system would. Noise-free renderings are shared by
all noise levels and systems of a case; each frame's noise depends only on (seed, case, frame).
With ``acquisition`` every frame is also estimated without a prior (mode ``acquisition``), to
measure how reliably each system finds the target from nothing. ``mockups`` runs every case on
several mock-ups (e.g. twenty random ones, ``configuration.random_mockup``) and ``lighting``
under another light; summaries pool the mock-ups, ``mockup_table`` and ``bias_table`` show
them apart and the estimators' mean offsets (their biases).

Every frame is judged against ground truth: its errors, its NEES (is the covariance honest?),
whether it is *correct* (within 3× the accuracy target of ``hil.evaluation.targets``) or a *wrong lock*
(a valid pose with a gross error); ``loss_table`` counts the frames without one by why.
"""

from __future__ import annotations

import math
import re
import time
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from configuration.camera import load_camera
from configuration.mockup import load_mockup
from configuration.random_mockup import is_random_name, named_lighting, seed_of
from configuration.render import NoiseConfig, RenderConfig
from estimators.frame import Frame, GroundTruth
from estimators.measurement import Tracker
from estimators.registry import build_estimator
from estimators.target import facing_camera
from hil.evaluation.errors import MeasurementError, measurement_error
from hil.evaluation.fused_frames import FUSED, OpenLoopFusion
from hil.evaluation.reference import reference_text
from hil.evaluation.scenarios import MANEUVERS, REFERENCE_DISTANCES_M, Maneuver, camera_pose_for
from hil.evaluation.targets import (
    accuracy_target,
    is_correct,
    is_wrong_lock,
    judged_errors,
    target_text,
)
from sim_backends.renderer import make_renderer
from sim_backends.scene import MockupScene
from sim_backends.sensor import expose, frame_rng

NOISE_LEVELS = ("none", "low", "high")
#: Intensity of a blank frame (a lens cap, a dropout): uniform grey, then the case's noise.
BLANK_LEVEL = 0.35


@dataclass(frozen=True, slots=True)
class MatrixSpec:
    """What to run. ``estimator_options`` go to every estimator factory. ``acquisition`` also
    estimates every frame without a prior (rows of mode "acquisition"); ``blank_frames``
    replaces those frame indices by blank frames (a forced loss, to measure re-acquisition).
    ``mockups`` (names, e.g. ``random:3``), when given, replaces ``mockup``: every case runs on
    each; ``lighting``: ``default``, ``harsh`` or ``random`` (a random light per mock-up);
    ``supersample`` and ``passes``: the render's anti-aliasing (``RenderConfig``);
    ``auto_exposure``: the sensor's (``NoiseConfig``)."""

    systems: tuple[str, ...]
    distances_m: tuple[float, ...] = REFERENCE_DISTANCES_M
    maneuvers: tuple[str, ...] = tuple(m.name for m in MANEUVERS)
    noises: tuple[str, ...] = NOISE_LEVELS
    frames: int = 30
    seed: int = 0
    camera: str = "reference"
    mockup: str = "default"
    supersample: int = 1
    passes: int = 1
    estimator_options: dict = field(default_factory=dict)
    acquisition: bool = False
    blank_frames: tuple[int, ...] = ()
    mockups: tuple[str, ...] = ()
    lighting: str = "default"
    auto_exposure: bool = False

    @property
    def mockup_names(self) -> tuple[str, ...]:
        return self.mockups or (self.mockup,)


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
    blank: bool = False  # a forced loss: the frame showed nothing
    ambiguous: bool = False  # the estimator said it could not choose between two poses
    mode: str = "tracking"  # or "acquisition": estimated without any prior
    mockup: str = ""


def _maneuver(name: str) -> Maneuver:
    for m in MANEUVERS:
        if m.name == name:
            return m
    raise ValueError(f"unknown maneuver {name!r}; known: {', '.join(m.name for m in MANEUVERS)}")


def case_seed(
    spec: MatrixSpec,
    distance_index: int,
    maneuver_index: int,
    noise_index: int,
    mockup_index: int = 0,
) -> int:
    return (
        spec.seed * 1_000_003
        + distance_index * 10_007
        + maneuver_index * 101
        + noise_index
        + mockup_index * 7_000_003
    )


def run_case_group(
    spec: MatrixSpec, distance_m: float, maneuver_name: str, mockup_name: str | None = None
) -> list[FrameResult]:
    """All noise levels and systems of one (mock-up, distance, maneuver): render once,
    estimate many."""
    camera = load_camera(spec.camera).camera_info()
    mockup_name = spec.mockup_names[0] if mockup_name is None else mockup_name
    mockup_index = spec.mockup_names.index(mockup_name)
    mockup = load_mockup(mockup_name)
    target = mockup.target_model()
    maneuver = _maneuver(maneuver_name)
    distance_index = spec.distances_m.index(distance_m)
    maneuver_index = spec.maneuvers.index(maneuver_name)
    light_seed = seed_of(mockup_name) if is_random_name(mockup_name) else mockup_index
    render_config = RenderConfig(
        supersample=spec.supersample,
        passes=spec.passes,
        lighting=named_lighting(spec.lighting, light_seed),
    )
    with MockupScene(mockup) as scene:
        renderer = make_renderer(scene, camera, render_config)
        renderings = []
        for i in range(spec.frames):
            X_WC, _ = camera_pose_for(distance_m, maneuver.offset(i / spec.frames))
            renderings.append(renderer.render(X_WC))
    results = []
    for noise_index, noise in enumerate(spec.noises):
        noise_config = NoiseConfig(preset=noise, auto_exposure=spec.auto_exposure)
        seed = case_seed(spec, distance_index, maneuver_index, noise_index, mockup_index)
        trackers = {
            s: Tracker(build_estimator(s, target, camera, **spec.estimator_options))
            for s in spec.systems
            if s != FUSED
        }
        # the camera stands still and the target maneuvers: M is the target's nominal pose
        X_CM = facing_camera(distance_m).inverse()
        fusion = OpenLoopFusion(target, X_CM) if FUSED in spec.systems else None
        for i, rendering in enumerate(renderings):
            blank = i in spec.blank_frames
            scene = np.full_like(rendering.image, BLANK_LEVEL) if blank else rendering.image
            image = expose(scene, rendering.depth_m, camera.K, noise_config, frame_rng(seed, i))
            frame = Frame(
                image, float(i) / 30.0, camera, i, GroundTruth(rendering.X_CT, rendering.X_WC)
            )
            case = (distance_m, maneuver_name, noise, i, rendering.X_CT, target, blank)
            measurements = []
            for system, tracker in trackers.items():
                had_prior = tracker.prior_X_CT is not None
                measurements.append(tracker.update(frame))
                results.append(
                    _frame_result(
                        measurements[-1], system, *case, had_prior, "tracking", mockup_name
                    )
                )
                if spec.acquisition:
                    m = Tracker(tracker.estimator).update(frame)  # no prior at all
                    results.append(
                        _frame_result(m, system, *case, False, "acquisition", mockup_name)
                    )
            if fusion is not None:
                m = fusion.update(frame, measurements)
                results.append(_frame_result(m, FUSED, *case, i > 0, "tracking", mockup_name))
    return results


def _frame_result(
    m,
    system,
    distance_m,
    maneuver,
    noise,
    index,
    X_CT_true,
    target,
    blank,
    had_prior,
    mode,
    mockup_name="",
) -> FrameResult:
    return FrameResult(
        system,
        distance_m,
        maneuver,
        noise,
        index,
        m.status,
        m.reason,
        measurement_error(m, X_CT_true, target),
        m.residual_px,
        m.time_ms,
        had_prior,
        blank,
        m.ambiguous,
        mode,
        mockup_name,
    )


def run_matrix(
    spec: MatrixSpec, *, jobs: int = 1, progress: Callable[[str], None] | None = None
) -> list[FrameResult]:
    """Run every case of ``spec``; ``jobs`` > 1 spreads (distance, maneuver, mock-up) groups
    over processes."""
    for name in spec.maneuvers:
        _maneuver(name)
    named_lighting(spec.lighting)
    for name in spec.mockup_names:
        load_mockup(name)  # a bad name fails here, once, with its reason
    groups = [
        (d, m, k) for k in spec.mockup_names for d in spec.distances_m for m in spec.maneuvers
    ]
    results: list[FrameResult] = []
    start = time.perf_counter()

    def report(done: int, group: tuple[float, str, str]) -> None:
        if progress is not None:
            elapsed = time.perf_counter() - start
            where = f" {group[2]}" if len(spec.mockup_names) > 1 else ""
            progress(f"[{done}/{len(groups)}] {group[0]:.1f} m {group[1]}{where} ({elapsed:.0f} s)")

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
    """Statistics of one (system, distance, maneuver, noise, mode) case over its frames.

    Errors are over the frames with a valid estimate (blank frames excluded from everything
    but ``lost``); ``position`` is the translation (6-DOF) or circle-centre (5-DOF) error,
    ``attitude`` the rotation or normal error, ``normal`` the circle normal's error when a
    circle is measured. ``correct``: frames within 3× the case's accuracy target (-1 without a
    target; the ellipse system is judged on its circle); ``wrong_locks``: valid frames wrong
    without saying so (``hil.evaluation.targets.is_wrong_lock``); ``ambiguous``: valid frames the
    estimator flagged ambiguous; ``longest_gap``: the longest run of frames without a correct
    estimate (without a target: without a valid one); ``recovery_max``: the longest run of lost
    frames right after a blank stretch; ``nees_mean`` / ``nees_circle_mean``: mean NEES of the
    6-DOF / 5-DOF estimates (6 / 5 for honest covariances).
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
    mode: str = "tracking"
    correct: int = -1
    wrong_locks: int = 0
    longest_gap: int = 0
    nees_mean: float = math.nan
    nees_circle_mean: float = math.nan
    normal_mean_rad: float = math.nan
    normal_std_rad: float = math.nan
    ambiguous: int = 0
    blank: int = 0
    recovery_max: int = 0

    @property
    def target(self) -> tuple[float, float] | None:
        return accuracy_target(self.system, self.distance_m, self.noise)

    @property
    def judged_means(self) -> tuple[float, float]:
        """The mean errors the target is about (the circle's for the ellipse system)."""
        if self.system == "ellipses" and not math.isnan(self.normal_mean_rad):
            return self.position_mean_m, self.normal_mean_rad
        return self.position_mean_m, self.attitude_mean_rad

    @property
    def within_target(self) -> bool | None:
        """Whether the mean errors meet the case's accuracy target (None without one)."""
        target = self.target
        if target is None or self.valid == 0:
            return None
        position, attitude = self.judged_means
        return position <= target[0] and attitude <= target[1]


def _longest_run(flags: Sequence[bool]) -> int:
    longest = current = 0
    for flag in flags:
        current = current + 1 if flag else 0
        longest = max(longest, current)
    return longest


def _recovery(rows: Sequence[FrameResult]) -> int:
    """Longest run of lost frames right after a blank stretch (0 when valid at once)."""
    longest = 0
    for k, r in enumerate(rows[:-1]):
        if r.blank and not rows[k + 1].blank:
            run = 0
            for after in rows[k + 1 :]:
                if after.status != "lost" or after.blank:
                    break
                run += 1
            longest = max(longest, run)
    return longest


def _mean_std(values: list[float]) -> tuple[float, float]:
    finite = np.array([v for v in values if not math.isnan(v)])
    return (float(finite.mean()), float(finite.std())) if len(finite) else (math.nan, math.nan)


def summarize(results: Iterable[FrameResult]) -> list[CaseSummary]:
    cases: dict[tuple, list[FrameResult]] = {}
    for r in results:
        cases.setdefault((r.system, r.distance_m, r.maneuver, r.noise, r.mode), []).append(r)
    summaries = []
    for (system, distance, maneuver, noise, mode), rows in cases.items():
        rows.sort(key=lambda r: r.index)
        seen = [r for r in rows if not r.blank]
        valid = [r for r in seen if r.status != "lost"]
        position = _mean_std([r.error.position_m for r in valid])
        attitude = _mean_std([r.error.attitude_rad for r in valid])
        normal = _mean_std([r.error.normal_rad for r in valid])
        no_prior = [r for r in seen if not r.had_prior]
        times = np.array([r.time_ms for r in seen])
        target = accuracy_target(system, distance, noise)
        judged = [
            r.status != "lost" and is_correct(*judged_errors(system, r.error), target) for r in seen
        ]
        good = judged if target is not None else [r.status != "lost" for r in seen]
        summaries.append(
            CaseSummary(
                system,
                distance,
                maneuver,
                noise,
                len(seen),
                len(valid),
                *position,
                *attitude,
                _mean_std([r.error.roll_rad for r in valid])[0],
                len(seen) - len(valid),
                _longest_run([r.status == "lost" for r in seen]),
                sum(r.status == "acquired" for r in no_prior),
                len(no_prior),
                float(np.median(times)) if len(times) else math.nan,
                float(np.percentile(times, 95)) if len(times) else math.nan,
                mode,
                sum(bool(j) for j in judged) if target is not None else -1,
                sum(is_wrong_lock(r.error, distance, ambiguous=r.ambiguous) for r in valid),
                _longest_run([not g for g in good]),
                _mean_std([r.error.nees_pose for r in valid])[0],
                _mean_std([r.error.nees_circle for r in valid])[0],
                *normal,
                sum(r.ambiguous for r in valid),
                len(rows) - len(seen),
                _recovery(rows),
            )
        )
    return summaries


def _fmt_mean_std(mean: float, std: float, scale: float, unit: str) -> str:
    if math.isnan(mean):
        return "–"
    return f"{scale * mean:.2f} ± {scale * std:.2f}{unit}"


def _nees_text(values_6: list[float], values_5: list[float]) -> str:
    """Mean NEES, 6-DOF if there is any, else the 5-DOF circle's (marked "/5")."""
    six = [v for v in values_6 if not math.isnan(v)]
    five = [v for v in values_5 if not math.isnan(v)]
    if six:
        return f"{np.mean(six):.1f}"
    return f"{np.mean(five):.1f}/5" if five else "–"


def _wrong_text(wrong: int, ambiguous: int) -> str:
    return f"{wrong} ({ambiguous} amb.)" if ambiguous else str(wrong)


def overview_table(summaries: Sequence[CaseSummary]) -> str:
    """Per system, noise and distance over the seven maneuvers (tracking): the range of the
    cases' mean errors beside the target and the reference's low-noise range, whether every
    case meets the target, frames valid / correct / wrong locks, the longest stretch without
    a correct pose, and the mean NEES."""
    groups: dict[tuple, list[CaseSummary]] = {}
    for s in summaries:
        if s.mode == "tracking":
            groups.setdefault((s.system, s.noise, s.distance_m), []).append(s)
    blanks = any(s.blank for s in summaries)
    lines = [
        "| system | noise | distance | position means | attitude means | target (×1.5 high) "
        "| all cases meet it | reference (low noise) | valid | correct | wrong locks "
        "| longest gap | NEES |" + (" re-acquired after blanks |" if blanks else ""),
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|" + ("---|" if blanks else ""),
    ]
    order = {"none": 0, "low": 1, "high": 2}
    for (system, noise, distance), rows in sorted(
        groups.items(), key=lambda g: (g[0][0], order.get(g[0][1], 3), -g[0][2])
    ):
        pos = [100 * r.judged_means[0] for r in rows]
        att = [math.degrees(r.judged_means[1]) for r in rows]
        frames = sum(r.frames for r in rows)
        meets = [r.within_target for r in rows]
        meets_text = (
            "–" if meets[0] is None else ("yes" if all(meets) else f"{sum(meets)}/{len(meets)}")
        )
        correct = "–" if rows[0].correct < 0 else f"{sum(r.correct for r in rows)}/{frames}"
        nees_text = _nees_text([r.nees_mean for r in rows], [r.nees_circle_mean for r in rows])
        recovery = f" {max(r.recovery_max for r in rows) + 1} frame(s) |" if blanks else ""
        lines.append(
            f"| {system} | {noise} | {distance:.1f} m | {min(pos):.2f}–{max(pos):.2f} cm "
            f"| {min(att):.2f}–{max(att):.2f}° | {target_text(system, distance)} | {meets_text} "
            f"| {reference_text(system, distance)} | {sum(r.valid for r in rows)}/{frames} "
            f"| {correct} | {_wrong_text(sum(r.wrong_locks for r in rows), sum(r.ambiguous for r in rows))} "
            f"| {max(r.longest_gap for r in rows)} | {nees_text} |{recovery}"
        )
    return "\n".join(lines) + "\n"


def markdown_table(summaries: Sequence[CaseSummary]) -> str:
    """An overview per system, noise and distance (``overview_table``), then one row per
    tracking case: our mean ± std beside the target and the reference's low-noise range;
    correct frames (within 3× target), wrong locks, the longest stretch without a correct
    pose, NEES and time. For the ellipse system the attitude is the circle normal's error and
    the roll error (6-DOF with the thruster) has its own column. Acquisition cases (if run)
    follow in their own table."""
    lines = [
        "| system | distance | maneuver | noise | valid | position mean ± std | attitude mean ± std "
        "| roll mean | target (low noise) | reference (low noise) | correct | wrong locks "
        "| longest gap | NEES | median / p95 ms |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    tracking = [s for s in summaries if s.mode == "tracking"]
    for s in sorted(tracking, key=lambda s: (s.system, -s.distance_m, s.noise, s.maneuver)):
        meets = s.within_target
        mark = "" if meets is None else (" ✓" if meets else " ✗")
        correct = "–" if s.correct < 0 else f"{s.correct}/{s.frames}"
        circle = s.system == "ellipses" and not math.isnan(s.normal_mean_rad)
        attitude = (
            (s.normal_mean_rad, s.normal_std_rad)
            if circle
            else (s.attitude_mean_rad, s.attitude_std_rad)
        )
        roll = "–" if math.isnan(s.roll_mean_rad) else f"{math.degrees(s.roll_mean_rad):.2f}°"
        lines.append(
            f"| {s.system} | {s.distance_m:.1f} m | {s.maneuver} | {s.noise} | {s.valid}/{s.frames} "
            f"| {_fmt_mean_std(s.position_mean_m, s.position_std_m, 100, ' cm')} "
            f"| {_fmt_mean_std(*attitude, 180 / math.pi, '°')}{mark} | {roll} "
            f"| {target_text(s.system, s.distance_m)} "
            f"| {reference_text(s.system, s.distance_m)} | {correct} "
            f"| {_wrong_text(s.wrong_locks, s.ambiguous)} "
            f"| {s.longest_gap} | {_nees_text([s.nees_mean], [s.nees_circle_mean])} "
            f"| {s.time_median_ms:.1f} / {s.time_p95_ms:.1f} |"
        )
    text = overview_table(summaries) + "\n" + "\n".join(lines) + "\n"
    acquisition = [s for s in summaries if s.mode == "acquisition"]
    if acquisition:
        text += "\n" + acquisition_table(acquisition)
    return text


def acquisition_table(summaries: Sequence[CaseSummary]) -> str:
    """Acquisition without a prior, per system, noise and distance (all maneuvers pooled)."""
    groups: dict[tuple, list[CaseSummary]] = {}
    for s in summaries:
        if s.mode == "acquisition":
            groups.setdefault((s.system, s.noise, s.distance_m), []).append(s)
    lines = [
        "| system | noise | distance | acquired | correct | wrong locks | median / p95 ms |",
        "|---|---|---|---|---|---|---|",
    ]
    for (system, noise, distance), rows in sorted(
        groups.items(), key=lambda g: (g[0][0], g[0][1], -g[0][2])
    ):
        frames = sum(r.frames for r in rows)
        valid = sum(r.valid for r in rows)
        correct = sum(max(r.correct, 0) for r in rows)
        wrong = _wrong_text(sum(r.wrong_locks for r in rows), sum(r.ambiguous for r in rows))
        median = float(np.median([r.time_median_ms for r in rows]))
        p95 = float(max(r.time_p95_ms for r in rows))
        correct_text = f"{correct}/{frames}" if rows[0].correct >= 0 else "–"
        lines.append(
            f"| {system} | {noise} | {distance:.1f} m | {valid}/{frames} ({100 * valid / frames:.1f} %) "
            f"| {correct_text} | {wrong} | {median:.1f} / {p95:.1f} |"
        )
    return "\n".join(lines) + "\n"


def loss_reason(reason: str) -> str:
    """A lost frame's reason with its figures left out, so that frames lost for one reason
    count together: the last failure (acquisition's, where tracking fell back to it), without
    the count of hypotheses tried, every number a ``#`` and every list of numbers ``[#…]``."""
    last = reason.split("; ")[-1]
    last = re.sub(r"^\w+ failed \((.*)\)$", r"\1", last)
    last = re.sub(r"^\d+ hypotheses rejected: ", "", last)
    numbered = re.sub(r"-?\d+(\.\d+)?", "#", last)
    return re.sub(r"\[#(, #)*\]", "[#…]", numbered)  # a list of any length


def loss_table(results: Iterable[FrameResult], top: int = 8) -> str:
    """Why frames were lost: per system and mode, the ``top`` most frequent reasons
    (``loss_reason``) with their count per distance — where to look first when a system fails
    to lock. Forced losses (blank frames) are left out; '' when no other frame was lost."""
    lost = [r for r in results if r.status == "lost" and not r.blank]
    if not lost:
        return ""
    distances = sorted({r.distance_m for r in lost}, reverse=True)
    counts: dict[tuple[str, str], dict[str, dict[float, int]]] = {}
    for r in lost:
        by_reason = counts.setdefault((r.system, r.mode), {})
        per_distance = by_reason.setdefault(loss_reason(r.reason), {})
        per_distance[r.distance_m] = per_distance.get(r.distance_m, 0) + 1
    header = " | ".join(f"{d:g} m" for d in distances)
    lines = [
        f"| system | mode | why lost | {header} | all |",
        "|---|---|---|" + "---|" * (len(distances) + 1),
    ]
    for (system, mode), by_reason in sorted(counts.items()):
        ranked = sorted(by_reason.items(), key=lambda item: -sum(item[1].values()))
        for reason, per_distance in ranked[:top]:
            cells = " | ".join(str(per_distance.get(d, 0)) for d in distances)
            lines.append(
                f"| {system} | {mode} | {reason} | {cells} | {sum(per_distance.values())} |"
            )
        if len(ranked) > top:
            rest = [sum(v.get(d, 0) for _, v in ranked[top:]) for d in distances]
            cells = " | ".join(map(str, rest))
            lines.append(f"| {system} | {mode} | (other reasons) | {cells} | {sum(rest)} |")
    return "\n".join(lines) + "\n"


#: Bias allowed per axis (issue 13): 0.2 mm, or 0.2 standard deviations of the error when larger.
BIAS_LIMIT_M = 0.0002
BIAS_LIMIT_SIGMA = 0.2


def bias_table(results: Iterable[FrameResult]) -> str:
    """Mean offset (estimate − truth) of the target's position along the camera's x, y, z per
    system, noise and distance over the valid tracking frames of every maneuver and mock-up:
    the estimators' biases, beside their standard deviations and the limit max(0.2 mm,
    0.2 σ); ✓ when every axis is within it."""
    groups: dict[tuple, list[FrameResult]] = {}
    for r in results:
        if r.mode == "tracking" and not r.blank and r.status != "lost":
            offset = np.asarray(r.error.offset_C, dtype=float)
            if np.all(np.isfinite(offset)):
                groups.setdefault((r.system, r.noise, r.distance_m), []).append(r)
    lines = [
        "| system | noise | distance | frames | bias x / y / z (mm) | sd x / y / z (mm) "
        "| limit x / y / z (mm) | within |",
        "|---|---|---|---|---|---|---|---|",
    ]
    order = {"none": 0, "low": 1, "high": 2}
    for (system, noise, distance), rows in sorted(
        groups.items(), key=lambda g: (g[0][0], order.get(g[0][1], 3), -g[0][2])
    ):
        offsets = 1000.0 * np.array([r.error.offset_C for r in rows], dtype=float)
        mean, sd = offsets.mean(axis=0), offsets.std(axis=0)
        limit = np.maximum(1000.0 * BIAS_LIMIT_M, BIAS_LIMIT_SIGMA * sd)
        ok = bool(np.all(np.abs(mean) <= limit))
        lines.append(
            f"| {system} | {noise} | {distance:.1f} m | {len(rows)} "
            f"| {' / '.join(f'{v:+.2f}' for v in mean)} | {' / '.join(f'{v:.2f}' for v in sd)} "
            f"| {' / '.join(f'{v:.2f}' for v in limit)} | {'✓' if ok else '✗'} |"
        )
    return "\n".join(lines) + "\n"


def mockup_table(results: Iterable[FrameResult]) -> str:
    """Per mock-up and system: tracking frames valid, frames acquired without a prior (when
    run), wrong locks and ambiguous answers, and the worst case's mean errors as a share of
    its target (≤ 1 meets every target)."""
    rows = list(results)
    by: dict[tuple[str, str], list[FrameResult]] = {}
    for r in rows:
        by.setdefault((r.mockup, r.system), []).append(r)
    worst: dict[tuple[str, str], float] = {}
    for (mockup, system), group in by.items():
        cases: dict[tuple, list[FrameResult]] = {}
        for r in group:
            if r.mode == "tracking" and not r.blank and r.status != "lost":
                cases.setdefault((r.distance_m, r.maneuver, r.noise), []).append(r)
        share = 0.0
        for (distance, _, noise), case in cases.items():
            target = accuracy_target(system, distance, noise)
            if target is None:
                continue
            errors = [judged_errors(system, r.error) for r in case]
            position = float(np.nanmean([e[0] for e in errors]))
            attitude = float(np.nanmean([e[1] for e in errors]))
            share = max(share, position / target[0], attitude / target[1])
        worst[(mockup, system)] = share
    lines = [
        "| mock-up | system | tracking valid | acquired without prior | wrong locks (ambiguous) "
        "| worst case mean / target |",
        "|---|---|---|---|---|---|",
    ]
    for (mockup, system), group in sorted(by.items()):
        tracking = [r for r in group if r.mode == "tracking" and not r.blank]
        acquisition = [r for r in group if r.mode == "acquisition" and not r.blank]
        valid = sum(r.status != "lost" for r in tracking)
        acquired = (
            f"{sum(r.status != 'lost' for r in acquisition)}/{len(acquisition)}"
            if acquisition
            else "–"
        )
        wrong = sum(
            is_wrong_lock(r.error, r.distance_m, ambiguous=r.ambiguous)
            for r in group
            if r.status != "lost"
        )
        ambiguous = sum(r.ambiguous for r in group if r.status != "lost")
        lines.append(
            f"| {mockup} | {system} | {valid}/{len(tracking)} | {acquired} "
            f"| {wrong} ({ambiguous}) | {worst[(mockup, system)]:.2f} |"
        )
    return "\n".join(lines) + "\n"
