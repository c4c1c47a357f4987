"""``satgrasp video RUN.mcap``: the logged camera frames with what each system saw and
concluded drawn on them — its feature points (from the log's Foxglove annotations), the target
model reprojected with its pose (``hil.evaluation.overlay``) — and the fused pose (the model in
white and its axes), written as a video.

A frame is logged every ``vision.log_frames_every_s`` (1 s by default; ``--set
vision.log_frames_every_s=0.1`` for a smoother video). Each system's result on the frame is
the one with the frame's capture stamp; the fused pose is the estimate of the tick nearest
the capture. Codecs (../shared/LIBRARY-FACTS.md): ``vp09`` in .mp4 plays in browsers; ``mp4v``
writes everywhere but browsers do not play it; a writer that did not open is an error.
"""

from __future__ import annotations

import bisect
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations

from configuration.camera import CameraConfig
from estimators.measurement import Measurement
from hil.analysis.trial_analysis import target_from_header
from hil.evaluation.overlay import draw_measurement
from hil.logs.triallog import TrialLog

#: BGR per system (as the Foxglove annotations' colours).
SYSTEM_BGR = {"corners": (50, 90, 255), "lines": (255, 200, 50), "ellipses": (80, 255, 100)}
CODECS = ("vp09", "mp4v", "MJPG")
#: Two stamps within this (s) are the same capture.
SAME_CAPTURE_S = 5e-4


class VideoError(ValueError):
    """The video cannot be written (the message says why)."""


def open_writer(path: Path, codec: str, fps: float, size: tuple[int, int]) -> cv2.VideoWriter:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*codec), fps, size)
    if not writer.isOpened():  # a failed writer is silent otherwise
        raise VideoError(f"OpenCV cannot write {path.suffix} with codec {codec!r} here")
    return writer


def _features(log: TrialLog) -> dict[tuple[str, float], np.ndarray]:
    """(system, capture t) → the feature points of its annotations (no reprojected loops)."""
    found = {}
    for topic, t, data in log.messages("/camera/features/"):
        message = ImageAnnotations()
        message.ParseFromString(data)
        points = [
            [(p.x, p.y) for p in item.points]
            for item in message.points
            if item.type == item.Type.POINTS
        ]
        if points:
            found[(topic.rsplit("/", 1)[-1], round(t, 3))] = np.concatenate(points).reshape(-1, 2)
    return found


def render_video(
    log_path: Path, out_path: Path, *, codec: str = "vp09", fps: float | None = None
) -> tuple[Path, int]:
    """Write the overlay video of a trial log; (path, frames written). ``fps`` defaults to the
    logged frame rate (at least 1)."""
    log = TrialLog.open(log_path)
    config = log.header.get("config") or {}
    try:
        camera = CameraConfig.model_validate(config["camera"]).camera_info()
    except (KeyError, ValueError):
        raise VideoError(f"{log_path}: the header holds no camera configuration") from None
    target = target_from_header(log.header)
    frames = list(log.frames())
    if not frames:
        raise VideoError(f"{log_path} holds no camera frames (vision.log_frames_every_s was 0)")
    vision = sorted(log.vision(), key=lambda r: r.capture_t)
    captures = [r.capture_t for r in vision]
    ticks = list(log.ticks())
    tick_t = [r.t for r in ticks]
    features = _features(log)
    if fps is None:
        spacing = np.diff([f.t for f in frames])
        fps = max(1.0, 1.0 / float(np.median(spacing))) if len(spacing) else 1.0
    writer = open_writer(out_path, codec, fps, (camera.width, camera.height))
    written = 0
    try:
        for frame in frames:
            image = frame.image()
            canvas = image if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
            if canvas.shape[:2] != (camera.height, camera.width):  # a frame logged scaled down
                canvas = cv2.resize(canvas, (camera.width, camera.height))
            lo = bisect.bisect_left(captures, frame.t - SAME_CAPTURE_S)
            hi = bisect.bisect_right(captures, frame.t + SAME_CAPTURE_S)
            for row, record in enumerate(vision[lo:hi]):
                m = record.measurement
                points = features.get((record.system, round(record.capture_t, 3)))
                if points is not None:
                    m = replace(m, features={"labeled": points})
                if target is not None:
                    color = SYSTEM_BGR.get(record.system, (0, 255, 255))
                    canvas = draw_measurement(
                        canvas, m, camera, target, model_color=color, text_row=row
                    )
            canvas = _draw_fused(canvas, ticks, tick_t, frame.t, camera, target)
            cv2.putText(
                canvas, f"t {frame.t:6.2f} s", (8, camera.height - 10),
                cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA,
            )  # fmt: skip
            writer.write(canvas)
            written += 1
    finally:
        writer.release()
    return out_path, written


def _draw_fused(canvas, ticks, tick_t, t, camera, target) -> np.ndarray:
    """The fused estimate of the tick nearest ``t``: model in white, axes of T (0.1 m)."""
    if not ticks:
        return canvas
    i = min(bisect.bisect_left(tick_t, t), len(ticks) - 1)
    if i > 0 and abs(tick_t[i - 1] - t) < abs(tick_t[i] - t):
        i -= 1
    X_CT = ticks[i].estimate.X_CT
    if X_CT is None or not np.all(np.isfinite(X_CT.matrix)):
        return canvas
    if target is not None:
        m = Measurement("fused", "tracking", t, 0, X_CT=X_CT, covariance=np.eye(6))
        canvas = draw_measurement(
            canvas, m, camera, target, model_color=(255, 255, 255), text_row=3
        )
    rvec, _ = cv2.Rodrigues(X_CT.R)
    if X_CT.p[2] > 0:
        cv2.drawFrameAxes(
            canvas, camera.K, np.asarray(camera.dist, float), rvec, X_CT.p.reshape(3, 1), 0.1, 2
        )
    return canvas


def default_video_path(log_path: Path) -> Path:
    return log_path.with_name(f"{log_path.stem}_overlay.mp4")
