"""Trial-log channels that Foxglove's 3-D and image panels understand, in its published protobuf
schemas (``foxglove-schemas-protobuf``), written beside the JSON ticks:

| topic | schema | one message per |
|---|---|---|
| ``/tf`` | ``foxglove.FrameTransforms`` | tick, decimated to ``transforms_hz``: W→B, B→E, E→C, W→M, M→T (the truth, in simulation), M→T_fused; and per estimator result C→T_<system> at its capture |
| ``/estimate/fused`` | ``foxglove.PoseInFrame`` | tick with an estimate (decimated like ``/tf``): the fused X_CT in frame C |
| ``/estimate/<system>`` | ``foxglove.PoseInFrame`` | valid estimator result: its X_CT (5-DOF circles: centre, z along the normal) in C at capture |
| ``/camera/features/<system>`` | ``foxglove.ImageAnnotations`` | estimator result, at most ``annotations_hz`` per system: the points it used (``bounded_features``) and the ring reprojected from its pose |
| ``/camera/calibration`` | ``foxglove.CameraCalibration`` | logged frame: K, distortion (plumb_bob, or rational_polynomial beyond 5 coefficients), size, frame C |

Frames are still ``foxglove.CompressedImage`` (JSON) on ``/camera/image``, now in frame ``C``.
Frame names are the project's monogram letters (docs/architecture.md).

``FoxgloveRecorder`` wraps a ``TrialLogWriter`` with the control loop's recorder interface, so
the loop writes as before. Its cost sits inside the tick, so the tick's transforms are
decimated to ``transforms_hz`` (25 Hz) and the image annotations to ``annotations_hz`` (10 Hz
per system); measured figures are in docs/trial_logs.md.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.PointsAnnotation_pb2 import PointsAnnotation
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from google.protobuf import descriptor_pb2

from estimators.conics import circle_points
from estimators.frame import CameraInfo
from estimators.geometry import Pose, project
from estimators.target import TargetModel
from hil.logs.records import TickRecord, VisionRecord

TF_TOPIC = "/tf"
FUSED_TOPIC = "/estimate/fused"
CALIBRATION_TOPIC = "/camera/calibration"
CAMERA_FRAME = "C"
#: Feature points kept per name and result (log size; the wall clock's vision process keeps
#: this many when it strips features before they cross into the control process).
MAX_FEATURE_POINTS = 120
#: Feature sets drawn (``Measurement.features`` names), the rest are dropped.
DRAWN_FEATURES = ("labeled", "corners")
SYSTEM_COLORS = {
    "corners": (1.0, 0.35, 0.2),
    "lines": (0.2, 0.8, 1.0),
    "ellipses": (0.4, 1.0, 0.3),
}


def descriptor_set(message_class) -> bytes:
    """The serialized ``FileDescriptorSet`` of a protobuf message type and its imports — the
    schema data MCAP's ``protobuf`` encoding expects."""
    files = descriptor_pb2.FileDescriptorSet()
    seen: set[str] = set()

    def add(file) -> None:
        if file.name in seen:
            return
        seen.add(file.name)
        for dependency in file.dependencies:
            add(dependency)
        proto = descriptor_pb2.FileDescriptorProto()
        file.CopyToProto(proto)
        files.file.append(proto)

    add(message_class.DESCRIPTOR.file)
    return files.SerializeToString()


def quat_xyzw(R: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (x, y, z, w) of a rotation matrix (Shepperd's method; cheaper than
    scipy's ``Rotation`` for one matrix)."""
    m = R
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > 0.0:
        s = 2.0 * math.sqrt(1.0 + trace)
        return ((m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4)
    if m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        return (s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s)
    if m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        return ((m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s)
    s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
    return ((m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4, (m[1, 0] - m[0, 1]) / s)


def circle_pose(center_C: np.ndarray, normal_C: np.ndarray) -> Pose:
    """A pose at a circle's centre with z along its normal (roll arbitrary: 5-DOF)."""
    z = np.asarray(normal_C, float) / np.linalg.norm(normal_C)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return Pose(np.column_stack([x, np.cross(z, x), z]), np.asarray(center_C, float))


def bounded_features(
    features: Mapping[str, np.ndarray], max_points: int = MAX_FEATURE_POINTS
) -> dict[str, np.ndarray]:
    """The drawn feature sets, each evenly thinned to at most ``max_points`` points."""
    kept = {}
    for name in DRAWN_FEATURES:
        points = features.get(name)
        if points is None:
            continue
        points = np.asarray(points, dtype=float).reshape(-1, 2)
        if len(points) > max_points:
            points = points[np.linspace(0, len(points) - 1, max_points).astype(int)]
        kept[name] = points
    return kept


def _set_pose(target, X: Pose) -> None:
    target.position.x, target.position.y, target.position.z = map(float, X.p)
    q = quat_xyzw(X.R)
    target.orientation.x, target.orientation.y = float(q[0]), float(q[1])
    target.orientation.z, target.orientation.w = float(q[2]), float(q[3])


def _set_stamp(target, stamp_ns: int) -> None:
    target.seconds, target.nanos = divmod(int(stamp_ns), 1_000_000_000)


class FoxgloveRecorder:
    """The control loop's recorder (``hil.runtime.loop.TrialRecorder``) over a
    ``TrialLogWriter`` that also writes the Foxglove channels of the module docstring. Any
    other attribute is the writer's."""

    def __init__(
        self,
        log: Any,
        *,
        X_WB: Pose,
        X_EC: Pose,
        X_WM: Any,
        camera: CameraInfo,
        target: TargetModel | None = None,
        transforms_hz: float = 25.0,
        annotations_hz: float = 10.0,
    ):
        self._log = log
        self._X_WB, self._X_EC, self._X_WM = X_WB, X_EC, X_WM
        self._camera = camera
        self._period = 1.0 / transforms_hz if transforms_hz > 0 else math.inf
        self._next_tf = -math.inf
        self._annotation_period = 1.0 / annotations_hz if annotations_hz > 0 else math.inf
        self._next_annotation: dict[str, float] = {}
        self._ring_T = None
        if target is not None and target.has_circle("ring_outer"):
            ring = target.circle("ring_outer")
            self._ring_T = circle_points(ring.center_T, ring.normal_T, ring.radius, 48)
            # The ring is drawn through the lens, whose projection is a numba kernel: its first
            # call loads it (120 ms), and in a tick it aborted wall-clock approaches with the
            # OAK camera at their first estimate (deadline 24 ms). Loaded here, before the loop.
            project(self._ring_T[:1] + [0.0, 0.0, 1.0], camera.K, camera.dist)
        self._topics: set[str] = set()
        self._calibration: bytes | None = None

    def __getattr__(self, name: str) -> Any:
        return getattr(self._log, name)

    # --- the recorder interface ---------------------------------------------------------
    def write_tick(self, record: TickRecord) -> bool:
        written = self._log.write_tick(record)
        if record.t >= self._next_tf:
            self._next_tf = record.t + self._period
            self._tick_transforms(record)
        return written

    def write_vision(self, record: VisionRecord) -> bool:
        written = self._log.write_vision(record)
        m = record.measurement
        stamp = self._log.stamp_ns(record.capture_t)
        X_CT = m.X_CT
        if X_CT is None and m.center_C is not None and m.normal_C is not None:
            X_CT = circle_pose(m.center_C, m.normal_C)
        if m.valid and X_CT is not None:
            tf = FrameTransforms()
            self._transform(tf, stamp, CAMERA_FRAME, f"T_{record.system}", X_CT)
            self._write(TF_TOPIC, FrameTransforms, record.t, tf)
            self._write(
                f"/estimate/{record.system}", PoseInFrame, record.t, self._pose(stamp, X_CT)
            )
        due = self._next_annotation.get(record.system, -math.inf)
        if record.capture_t < due:
            return written
        self._next_annotation[record.system] = record.capture_t + self._annotation_period
        annotations = self._annotations(record.system, m.features, X_CT if m.valid else None, stamp)
        if annotations is not None:
            self._write(
                f"/camera/features/{record.system}", ImageAnnotations, record.capture_t, annotations
            )
        return written

    def write_encoded_frame(self, t: float, data: bytes, *, encoding: str = "jpeg") -> bool:
        written = self._log.write_encoded_frame(t, data, encoding=encoding, frame_id=CAMERA_FRAME)
        self._write(CALIBRATION_TOPIC, CameraCalibration, t, self._calibration_message(t))
        return written

    def write_frame(self, t: float, image: np.ndarray, **options: Any) -> bool:
        written = self._log.write_frame(t, image, **{"frame_id": CAMERA_FRAME, **options})
        self._write(CALIBRATION_TOPIC, CameraCalibration, t, self._calibration_message(t))
        return written

    def write_event(self, t: float, kind: str, message: str, /, **data: Any) -> bool:
        return self._log.write_event(t, kind, message, **data)

    def close(self) -> None:
        self._log.close()

    def __enter__(self) -> FoxgloveRecorder:
        return self

    def __exit__(self, *exc: Any) -> None:
        self._log.__exit__(*exc)

    # --- messages -----------------------------------------------------------------------
    def _write(self, topic: str, kind: type, t: float, message: Any) -> None:
        if topic not in self._topics:
            if not self._log.add_channel(
                topic, kind.DESCRIPTOR.full_name, "protobuf", descriptor_set(kind), "protobuf"
            ):
                return
            self._topics.add(topic)
        self._log.write_message(topic, t, message.SerializeToString())

    @staticmethod
    def _transform(tf: FrameTransforms, stamp: int, parent: str, child: str, X: Pose) -> None:
        item = tf.transforms.add()
        _set_stamp(item.timestamp, stamp)
        item.parent_frame_id, item.child_frame_id = parent, child
        item.translation.x, item.translation.y, item.translation.z = map(float, X.p)
        q = quat_xyzw(X.R)
        item.rotation.x, item.rotation.y = float(q[0]), float(q[1])
        item.rotation.z, item.rotation.w = float(q[2]), float(q[3])

    def _pose(self, stamp: int, X_CT: Pose) -> PoseInFrame:
        message = PoseInFrame(frame_id=CAMERA_FRAME)
        _set_stamp(message.timestamp, stamp)
        _set_pose(message.pose, X_CT)
        return message

    def _tick_transforms(self, record: TickRecord) -> None:
        stamp = self._log.stamp_ns(record.t)
        tf = FrameTransforms()
        self._transform(tf, stamp, "W", "B", self._X_WB)
        X_WM = None
        if record.arm is not None:
            self._transform(tf, stamp, "B", "E", record.arm.X_BE)
            self._transform(tf, stamp, "E", CAMERA_FRAME, self._X_EC)
        if record.track is not None:
            X_WM = self._X_WM(record.track.position)
            self._transform(tf, stamp, "W", "M", X_WM)
        if X_WM is not None and record.truth is not None and record.truth.X_WT is not None:
            self._transform(tf, stamp, "M", "T", X_WM.inverse() @ record.truth.X_WT)
        estimate = record.estimate
        if estimate.X_MT is not None:
            self._transform(tf, stamp, "M", "T_fused", estimate.X_MT)
        self._write(TF_TOPIC, FrameTransforms, record.t, tf)
        if estimate.X_CT is not None:
            self._write(FUSED_TOPIC, PoseInFrame, record.t, self._pose(stamp, estimate.X_CT))

    def _annotations(
        self, system: str, features: Mapping[str, np.ndarray], X_CT: Pose | None, stamp: int
    ) -> ImageAnnotations | None:
        kept = bounded_features(features)
        if not kept and (X_CT is None or self._ring_T is None):
            return None
        r, g, b = SYSTEM_COLORS.get(system, (1.0, 1.0, 0.0))
        message = ImageAnnotations()
        for points in kept.values():
            item = message.points.add(type=PointsAnnotation.Type.POINTS, thickness=3.0)
            _set_stamp(item.timestamp, stamp)
            item.outline_color.CopyFrom(Color(r=r, g=g, b=b, a=1.0))
            for u, v in points:
                item.points.add(x=float(u), y=float(v))
        ring_C = None if X_CT is None or self._ring_T is None else X_CT.apply(self._ring_T)
        if ring_C is not None and np.all(ring_C[:, 2] > 0):
            uv = project(ring_C, self._camera.K, self._camera.dist)
            item = message.points.add(type=PointsAnnotation.Type.LINE_LOOP, thickness=1.5)
            _set_stamp(item.timestamp, stamp)
            item.outline_color.CopyFrom(Color(r=r, g=g, b=b, a=0.8))
            for u, v in uv:
                item.points.add(x=float(u), y=float(v))
        return message

    def _calibration_message(self, t: float) -> CameraCalibration:
        info = self._camera
        K = np.asarray(info.K, float)
        message = CameraCalibration(
            frame_id=CAMERA_FRAME,
            width=int(info.width),
            height=int(info.height),
            distortion_model="plumb_bob",
        )
        _set_stamp(message.timestamp, self._log.stamp_ns(t))
        distortion = np.asarray(info.dist, float).ravel()
        if len(distortion) > 5:
            message.distortion_model = "rational_polynomial"
        message.D.extend(float(d) for d in distortion)
        message.K.extend(float(k) for k in K.ravel())
        message.R.extend([1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0])
        message.P.extend(
            [K[0, 0], K[0, 1], K[0, 2], 0.0, K[1, 0], K[1, 1], K[1, 2], 0.0, 0.0, 0.0, 1.0, 0.0]
        )
        return message
