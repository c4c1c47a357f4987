"""Foxglove's channels in a trial log, read with the plain MCAP reader; and a SIGKILLed
simulated trial recovered by `satgrasp recover` into a file that reader reads to the end."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from mcap.reader import make_reader
from typer.testing import CliRunner

from configuration.camera import load_camera
from configuration.mockup import load_mockup
from estimators.geometry import Pose
from hil.cli import app
from hil.logs.foxglove import MAX_FEATURE_POINTS, FoxgloveRecorder, bounded_features, quat_xyzw
from hil.logs.triallog import TrialLogWriter
from tests.hil.logs.synthetic_log import make_trial, synthetic_frame

REPO = Path(__file__).resolve().parents[3]
DECODERS = {
    "foxglove.FrameTransforms": FrameTransforms,
    "foxglove.PoseInFrame": PoseInFrame,
    "foxglove.ImageAnnotations": ImageAnnotations,
    "foxglove.CameraCalibration": CameraCalibration,
}


def _recorder(path: Path, header: dict) -> FoxgloveRecorder:
    camera = load_camera("reference").camera_info()
    return FoxgloveRecorder(
        TrialLogWriter(path, header),
        X_WB=Pose.identity(),
        X_EC=Pose.from_rpy(0.0, 0.0, 0.1, np.array([0.0, 0.05, 0.1])),
        X_WM=lambda s: Pose(np.eye(3), np.array([s, 0.0, 0.0])),
        camera=camera,
        target=load_mockup("default").target_model(),
        transforms_hz=25.0,
    )


@pytest.fixture(scope="module")
def foxglove_log(tmp_path_factory):
    """Six seconds of a synthetic trial at 125 Hz through the recorder, every tenth vision
    result with 500 feature points, a frame every second."""
    path = tmp_path_factory.mktemp("fox") / "trial.mcap"
    trial = make_trial(seed=3, rate_hz=125.0)
    vision = [r for r in trial.vision if r.t < 6.0]
    rng = np.random.default_rng(0)
    with _recorder(path, trial.header) as log:
        for i, record in enumerate(vision):
            if i % 10 == 0 and record.measurement.valid:
                features = {"labeled": rng.uniform(0, 400, (500, 2)), "extracted": np.zeros((9, 2))}
                m = dataclasses.replace(record.measurement, features=features)
                record = dataclasses.replace(record, measurement=m)
            log.write_vision(record)
        for second in range(6):
            log.write_frame(float(second), synthetic_frame(2.0))
        for record in (r for r in trial.ticks if r.t < 6.0):
            log.write_tick(record)
    return path


def test_plain_reader_lists_foxglove_schemas_and_decodes_one_message_of_each(foxglove_log):
    with foxglove_log.open("rb") as f:
        reader = make_reader(f)
        names = {s.name for s in reader.get_summary().schemas.values()}
        assert set(DECODERS) | {"foxglove.CompressedImage"} <= names
        first: dict[str, object] = {}
        for schema, channel, message in reader.iter_messages():
            if schema.name in DECODERS and schema.name not in first:
                assert schema.encoding == "protobuf" and channel.message_encoding == "protobuf"
                decoded = DECODERS[schema.name]()
                decoded.ParseFromString(message.data)
                first[schema.name] = (channel.topic, decoded)
            elif schema.name == "foxglove.CompressedImage" and schema.name not in first:
                first[schema.name] = (channel.topic, json.loads(message.data))
    assert set(first) == set(DECODERS) | {"foxglove.CompressedImage"}
    topic, tf = first["foxglove.FrameTransforms"]
    assert topic == "/tf"
    assert {(t.parent_frame_id, t.child_frame_id) for t in tf.transforms} >= {
        ("W", "B"), ("B", "E"), ("E", "C"), ("W", "M"), ("M", "T")
    }  # fmt: skip
    _, pose = first["foxglove.PoseInFrame"]
    assert pose.frame_id == "C" and pose.pose.orientation.w != 0.0
    _, calibration = first["foxglove.CameraCalibration"]
    K = load_camera("reference").camera_info().K
    assert list(calibration.K) == pytest.approx(K.ravel().tolist()) and calibration.width == 640
    _, annotations = first["foxglove.ImageAnnotations"]
    assert annotations.points and all(
        len(p.points) <= MAX_FEATURE_POINTS for p in annotations.points
    )
    _, image = first["foxglove.CompressedImage"]
    assert image["frame_id"] == "C" and image["format"] == "jpeg"


def test_foxglove_transforms_hold_every_estimator_and_the_fused_target(foxglove_log):
    children = set()
    with foxglove_log.open("rb") as f:
        for _, _, message in make_reader(f).iter_messages(topics=["/tf"]):
            tf = FrameTransforms()
            tf.ParseFromString(message.data)
            children |= {t.child_frame_id for t in tf.transforms}
    assert {"T_corners", "T_lines", "T_ellipses", "T_fused"} <= children


def test_quat_xyzw_matches_scipy_on_random_rotations():
    from scipy.spatial.transform import Rotation

    for R in Rotation.random(50, random_state=4).as_matrix():
        q = np.array(quat_xyzw(R))
        reference = Rotation.from_matrix(R).as_quat()
        assert min(np.abs(q - reference).max(), np.abs(q + reference).max()) < 1e-9


def test_bounded_features_thins_each_drawn_set_and_drops_the_rest():
    kept = bounded_features({"labeled": np.zeros((1000, 2)), "extracted": np.zeros((5, 2))}, 50)
    assert set(kept) == {"labeled"} and kept["labeled"].shape == (50, 2)


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_recover_of_a_sigkilled_simulated_trial_reads_to_the_end(tmp_path):
    """A simulated approach killed with SIGKILL once its log holds a few flushes: the plain
    reader fails on it, `satgrasp recover` writes a file it reads to the end, Foxglove's
    channels included."""
    child = subprocess.Popen(
        [sys.executable, "-c", "from hil.cli import main; main()", "approach", "--no-report"]
        + ["--seed", "2", "--log-dir", str(tmp_path)],
        cwd=REPO,
        start_new_session=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + 400
    try:
        while time.monotonic() < deadline and child.poll() is None:
            logs = list(tmp_path.glob("*.mcap"))
            if logs and logs[0].stat().st_size > 500_000:
                break
            time.sleep(0.2)
    finally:
        os.killpg(child.pid, signal.SIGKILL)
        child.wait()
    assert child.returncode == -signal.SIGKILL and logs
    killed = logs[0]
    with killed.open("rb") as f, pytest.raises(Exception):  # noqa: B017 — no footer, no index
        list(make_reader(f).iter_messages())
    fixed = tmp_path / "fixed.mcap"
    result = CliRunner().invoke(app, ["recover", str(killed), "--out", str(fixed)])
    assert result.exit_code == 0, result.output
    with fixed.open("rb") as f:
        messages = [(channel.topic, m.log_time) for _, channel, m in make_reader(f).iter_messages()]
    topics = {topic for topic, _ in messages}
    assert {"/trial/header", "/trial/tick", "/vision/result", "/tf", "/estimate/fused"} <= topics
    assert len(messages) > 100
    again = CliRunner().invoke(app, ["recover", str(killed), "--out", str(fixed)])
    assert again.exit_code == 2 and "exists" in again.output


def test_the_recorder_loads_the_lens_kernel_before_the_loop_not_in_a_tick(tmp_path):
    """The ring is drawn through the camera's lens by a compiled kernel, and its first call
    loads it: 120 ms, which in a tick aborted every wall-clock approach with the OAK camera at
    its first estimate (deadline 24 ms). Built, the recorder has loaded it. A fresh process:
    in this one other tests may have loaded it already."""
    script = f"""
import numpy as np
from configuration.camera import load_camera
from configuration.mockup import load_mockup
from estimators.geometry import Pose
from estimators.lens_distortion import project_distorted
from hil.logs.foxglove import FoxgloveRecorder
from hil.logs.triallog import TrialLogWriter

assert not project_distorted.signatures
FoxgloveRecorder(
    TrialLogWriter({str(tmp_path / "trial.mcap")!r}, {{"config": {{}}, "seed": 1}}),
    X_WB=Pose.identity(),
    X_EC=Pose.identity(),
    X_WM=lambda s: Pose.identity(),
    camera=load_camera("oak_d_rgb").camera_info(),
    target=load_mockup("default").target_model(),
)
print(len(project_distorted.signatures))
"""
    done = subprocess.run(
        [sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert int(done.stdout.split()[-1]) >= 1
