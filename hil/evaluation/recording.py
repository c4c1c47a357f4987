"""``satgrasp record``: the open-loop approach path (``approach_path.render_approach``) saved as
a camera recording that the OAK driver replays — the video, the camera's calibration as depthai
JSON (written by depthai's own ``CalibrationHandler``), and the ground truth as JSON lines —
and the check that replaying it gives the poses the direct frames give.

Files in the recording directory:

* ``video.avi``: the frames, FFV1 (lossless; depthai's ``ReplayVideo`` decodes it) or MJPG;
  mono cameras are stored as one grey plane;
* ``calibration.json``: ``eepromToJsonFile`` of the camera's K and distortion at its size,
  socket CAM_A;
* ``truth.jsonl``: one line per frame: ``seq``, ``stamp`` (capture, s), ``distance_m``,
  ``X_CT`` (4×4 nested list, the pose of the target in the camera);
* ``recording.json``: how it was made (camera, channels, fps, frames, codec, noise, seed).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from configuration.camera import load_camera
from configuration.mockup import load_mockup
from drivers.oak import OakReplay, ReplayFinished, write_calibration
from estimators.frame import CameraInfo
from estimators.geometry import Pose, rotation_error_geodesic, translation_error
from estimators.measurement import Measurement, Tracker
from estimators.registry import build_estimator
from estimators.target import TargetModel
from hil.evaluation.approach_path import ApproachPath, PathFrame, render_approach
from hil.evaluation.errors import measurement_error
from hil.evaluation.targets import CORRECT_FACTOR, judged_errors, target_along_approach

VIDEO = "video.avi"
CALIBRATION = "calibration.json"
TRUTH = "truth.jsonl"
METADATA = "recording.json"
#: codec name → OpenCV fourcc. FFV1 is lossless; MJPG is lossy even at quality 100.
CODECS = {"ffv1": "FFV1", "mjpg": "MJPG"}


@dataclass(frozen=True, slots=True)
class TruthRecord:
    """Ground truth of one recorded frame: capture stamp (s), distance (m) and ``X_CT``."""

    seq: int
    stamp: float
    distance_m: float
    X_CT: Pose

    def to_dict(self) -> dict:
        return {
            "seq": self.seq,
            "stamp": self.stamp,
            "distance_m": self.distance_m,
            "X_CT": self.X_CT.to_list(),
        }

    @staticmethod
    def from_dict(record: dict) -> TruthRecord:
        return TruthRecord(
            int(record["seq"]),
            float(record["stamp"]),
            float(record["distance_m"]),
            Pose.from_matrix(np.asarray(record["X_CT"], dtype=float), orthonormalize=True),
        )


@dataclass(frozen=True, slots=True)
class Recording:
    """Where a recording's files are and how it was made."""

    directory: Path
    camera: str
    mockup: str
    channels: int
    fps: float
    frames: int
    codec: str
    noise: str
    seed: int

    @property
    def video(self) -> Path:
        return self.directory / VIDEO

    @property
    def calibration(self) -> Path:
        return self.directory / CALIBRATION

    @property
    def truth(self) -> Path:
        return self.directory / TRUTH

    def replay(self, *, realtime: bool = False) -> OakReplay:
        """The recording as an OAK camera (not yet connected)."""
        return OakReplay(
            self.video, self.calibration, channels=self.channels, fps=self.fps, realtime=realtime
        )

    def read_truth(self) -> list[TruthRecord]:
        with self.truth.open(encoding="utf-8") as lines:
            return [TruthRecord.from_dict(json.loads(line)) for line in lines if line.strip()]

    @staticmethod
    def load(directory: Path) -> Recording:
        """A recording written by ``record_approach`` (its ``recording.json``)."""
        path = Path(directory) / METADATA
        if not path.is_file():
            raise ValueError(f"{directory} is not a recording (no {METADATA})")
        fields = json.loads(path.read_text(encoding="utf-8"))
        return Recording(directory=Path(directory), **fields)


def record_approach(
    out_dir: Path,
    *,
    frames: int = 120,
    noise: str = "low",
    camera: str = "reference",
    mockup: str = "default",
    seed: int = 0,
    codec: str = "ffv1",
    jpeg_quality: int = 100,
    path: ApproachPath | None = None,
    on_frame: Callable[[PathFrame], None] | None = None,
) -> Recording:
    """Render the approach path and save it as a recording in ``out_dir`` (created).

    ``on_frame`` sees every rendered frame before it is encoded (e.g. to estimate the direct
    frames). ``jpeg_quality`` (0–100) applies to MJPG only.
    """
    if codec not in CODECS:
        raise ValueError(f"codec must be one of {', '.join(CODECS)}; got {codec!r}")
    camera_config = load_camera(camera)
    info = camera_config.camera_info()
    mockup_config = load_mockup(mockup)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    recording = Recording(
        out_dir,
        camera,
        mockup,
        info.channels,
        camera_config.fps,
        frames,
        codec,
        noise,
        seed,
    )
    writer = _video_writer(recording.video, codec, recording.fps, info, jpeg_quality)
    grey_to_bgr = codec == "mjpg" and info.channels == 1
    try:
        with recording.truth.open("w", encoding="utf-8") as truth:
            for rendered in render_approach(
                info,
                mockup_config,
                frames=frames,
                noise=noise,
                path=path,
                seed=seed,
                fps=recording.fps,
            ):
                if on_frame is not None:
                    on_frame(rendered)
                frame = rendered.frame
                image = frame.image
                if image.dtype != np.uint8:
                    raise ValueError(f"frame {frame.seq} is {image.dtype}, not 8-bit")
                writer.write(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if grey_to_bgr else image)
                record = TruthRecord(frame.seq, frame.stamp, rendered.distance_m, frame.truth.X_CT)
                truth.write(json.dumps(record.to_dict()) + "\n")
    finally:
        writer.release()
    write_calibration(info, recording.calibration)
    fields = {k: getattr(recording, k) for k in Recording.__dataclass_fields__ if k != "directory"}
    (out_dir / METADATA).write_text(json.dumps(fields, indent=1) + "\n", encoding="utf-8")
    return recording


def _video_writer(
    path: Path, codec: str, fps: float, info: CameraInfo, jpeg_quality: int
) -> cv2.VideoWriter:
    """FFV1 through FFmpeg (mono frames as one grey plane); MJPG through OpenCV's own encoder,
    the one that honours ``jpeg_quality`` (FFmpeg's ignores it and errs several times more:
    docs/oak.md). That encoder's grey-only files do not decode, so MJPG is written as BGR."""
    if codec == "mjpg":
        api, color = cv2.CAP_OPENCV_MJPEG, True
    else:
        api, color = cv2.CAP_FFMPEG, info.channels == 3
    fourcc = cv2.VideoWriter_fourcc(*CODECS[codec])
    writer = cv2.VideoWriter(str(path), api, fourcc, fps, (info.width, info.height), color)
    if not writer.isOpened():
        raise OSError(f"OpenCV cannot write {codec} video {path}")
    if codec == "mjpg" and not writer.set(cv2.VIDEOWRITER_PROP_QUALITY, float(jpeg_quality)):
        writer.release()
        raise OSError(f"OpenCV's MJPEG writer refused quality {jpeg_quality}")
    return writer


# --- replay check ---------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ReplayComparison:
    """One system's poses on the replayed frames against the recorded truth and against the
    direct (never encoded) frames of the same recording.

    ``*_error`` are (position m, attitude rad) max over the frames valid in both, judged as the
    accuracy targets judge them (circle centre and normal for the ellipse system);
    ``within_bounds`` counts replayed frames within ``CORRECT_FACTOR`` × the target of their
    distance; ``difference`` is the max (translation m, rotation rad) between the replayed and
    the direct pose (the circle's centre and normal for a 5-DOF answer).
    """

    system: str
    frames: int
    valid_direct: int
    valid_replayed: int
    within_bounds: int
    direct_error: tuple[float, float]
    replayed_error: tuple[float, float]
    difference: tuple[float, float]


def _pose_difference(a: Measurement, b: Measurement) -> tuple[float, float]:
    if a.X_CT is not None and b.X_CT is not None:
        return translation_error(a.X_CT, b.X_CT), rotation_error_geodesic(a.X_CT, b.X_CT)
    if a.center_C is not None and b.center_C is not None:
        cosine = float(np.clip(np.dot(a.normal_C, b.normal_C), -1.0, 1.0))
        return float(np.linalg.norm(a.center_C - b.center_C)), math.acos(cosine)
    return math.inf, math.inf


def compare_systems(
    systems: Sequence[str],
    target: TargetModel,
    truth: Sequence[TruthRecord],
    direct: dict[str, dict[int, Measurement]],
    replayed: dict[str, dict[int, Measurement]],
    noise: str,
) -> list[ReplayComparison]:
    """Per system: replayed and direct poses against the truth and against each other."""
    by_seq = {t.seq: t for t in truth}
    rows = []
    for system in systems:
        direct_errors, replayed_errors, differences, within = [], [], [], 0
        for seq, m in replayed[system].items():
            record = by_seq[seq]
            if not m.valid:
                continue
            error = judged_errors(system, measurement_error(m, record.X_CT, target))
            bound = target_along_approach(system, record.distance_m, noise)
            within += bound is not None and (
                error[0] <= CORRECT_FACTOR * bound[0] and error[1] <= CORRECT_FACTOR * bound[1]
            )
            d = direct[system].get(seq)
            if d is not None and d.valid:
                replayed_errors.append(error)
                direct_errors.append(
                    judged_errors(system, measurement_error(d, record.X_CT, target))
                )
                differences.append(_pose_difference(m, d))

        def worst(pairs: list[tuple[float, float]]) -> tuple[float, float]:
            return tuple(np.max(pairs, axis=0)) if pairs else (math.nan, math.nan)

        rows.append(
            ReplayComparison(
                system,
                len(truth),
                sum(m.valid for m in direct[system].values()),
                sum(m.valid for m in replayed[system].values()),
                within,
                worst(direct_errors),
                worst(replayed_errors),
                worst(differences),
            )
        )
    return rows


@dataclass(frozen=True, slots=True)
class ReplayRun:
    """The measurements on a replay (by system, then seq) and its frames' timing."""

    measurements: dict[str, dict[int, Measurement]]
    seqs: list[int]
    latency_s: list[float]  # capture stamp → read, per frame
    wall_s: float


def estimate_replay(
    recording: Recording, systems: Iterable[str], target: TargetModel, *, realtime: bool = False
) -> ReplayRun:
    """Replay ``recording`` through ``OakReplay`` and track it with each system."""
    systems = list(systems)
    measurements: dict[str, dict[int, Measurement]] = {s: {} for s in systems}
    seqs, latency = [], []
    started = time.monotonic()
    with recording.replay(realtime=realtime) as camera:
        trackers = {s: Tracker(build_estimator(s, target, camera.info)) for s in systems}
        while True:
            try:
                frame = camera.read(timeout_s=5.0)
            except ReplayFinished:
                break
            seqs.append(frame.seq)
            latency.append(frame.latency_s)
            for s in systems:
                measurements[s][frame.seq] = trackers[s].update(frame)
    return ReplayRun(measurements, seqs, latency, time.monotonic() - started)


@dataclass(frozen=True, slots=True)
class ReplayCheck:
    """A recording, the systems' measurements on its direct frames and on its replay, and
    their comparison."""

    recording: Recording
    direct: dict[str, dict[int, Measurement]]
    replay: ReplayRun
    comparison: list[ReplayComparison]


def record_and_check(
    out_dir: Path,
    systems: Sequence[str] = ("corners", "lines", "ellipses"),
    *,
    realtime: bool = False,
    **record_options,
) -> ReplayCheck:
    """``record_approach`` while tracking the direct frames with each system, then replay the
    recording through ``OakReplay`` (every frame unless ``realtime``), track it the same way
    and compare (``compare_systems``)."""
    mockup_config = load_mockup(record_options.get("mockup", "default"))
    target = mockup_config.target_model()
    info = load_camera(record_options.get("camera", "reference")).camera_info()
    trackers = {s: Tracker(build_estimator(s, target, info)) for s in systems}
    direct: dict[str, dict[int, Measurement]] = {s: {} for s in systems}

    def track(rendered: PathFrame) -> None:
        for s in systems:
            direct[s][rendered.frame.seq] = trackers[s].update(rendered.frame)

    recording = record_approach(out_dir, on_frame=track, **record_options)
    replay = estimate_replay(recording, systems, target, realtime=realtime)
    comparison = compare_systems(
        systems, target, recording.read_truth(), direct, replay.measurements, recording.noise
    )
    return ReplayCheck(recording, direct, replay, comparison)


@dataclass(frozen=True, slots=True)
class ReplayTiming:
    """How the replay path delivers frames when nothing else runs: paced at the recorded
    ``fps`` (period between capture stamps, capture stamp → ``read`` latency) and unpaced
    (wall time per frame: decoding, conversion and hand-over)."""

    fps: float
    frames: int
    period_median_s: float
    period_max_s: float
    latency_median_s: float
    latency_p95_s: float
    latency_max_s: float
    unpaced_frame_s: float

    def text(self) -> str:
        ms = 1000.0
        return (
            f"replay paced at {self.fps:g} fps: {self.frames} frames, period median "
            f"{ms * self.period_median_s:.1f} ms (max {ms * self.period_max_s:.1f}), stamp → read "
            f"median {ms * self.latency_median_s:.2f} ms, p95 {ms * self.latency_p95_s:.2f}, "
            f"max {ms * self.latency_max_s:.2f}; unpaced {ms * self.unpaced_frame_s:.1f} ms/frame"
        )


def _read_all(camera: OakReplay) -> list:
    frames = []
    while True:
        try:
            frames.append(camera.read(timeout_s=5.0))
        except ReplayFinished:
            return frames


def replay_timing(recording: Recording) -> ReplayTiming:
    """Replay ``recording`` twice with a reader that only takes frames: paced, then unpaced."""
    with recording.replay(realtime=True) as camera:
        paced = _read_all(camera)
    started = time.perf_counter()
    with recording.replay(realtime=False) as camera:
        unpaced = _read_all(camera)
    unpaced_s = (time.perf_counter() - started) / max(len(unpaced), 1)
    periods = np.diff([f.stamp for f in paced[1:]])  # the first period starts at activation
    latency = np.array([f.latency_s for f in paced])
    return ReplayTiming(
        recording.fps,
        len(paced),
        float(np.median(periods)) if len(periods) else math.nan,
        float(np.max(periods)) if len(periods) else math.nan,
        float(np.median(latency)),
        float(np.percentile(latency, 95)),
        float(np.max(latency)),
        unpaced_s,
    )


def markdown_comparison(rows: Sequence[ReplayComparison]) -> str:
    """The comparison as a markdown table (cm, degrees; differences in mm and degrees)."""
    lines = [
        "| system | frames | valid direct / replayed | replayed within 3× target "
        "| max error direct | max error replayed | max replayed − direct |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r.system} | {r.frames} | {r.valid_direct} / {r.valid_replayed} "
            f"| {r.within_bounds} "
            f"| {100 * r.direct_error[0]:.2f} cm / {math.degrees(r.direct_error[1]):.2f}° "
            f"| {100 * r.replayed_error[0]:.2f} cm / {math.degrees(r.replayed_error[1]):.2f}° "
            f"| {1000 * r.difference[0]:.3f} mm / {math.degrees(r.difference[1]):.4f}° |"
        )
    return "\n".join(lines) + "\n"
