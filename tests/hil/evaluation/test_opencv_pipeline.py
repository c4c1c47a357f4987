"""The OpenCV comparator of ``satgrasp bench`` recovers rendered poses: it is a fair baseline,
not a broken one."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from configuration.camera import load_camera
from configuration.mockup import load_mockup
from configuration.render import NoiseConfig, RenderConfig
from estimators.frame import Frame
from estimators.geometry import Pose
from estimators.target import facing_camera
from hil.evaluation.opencv_pipeline import (
    OPENCV_SYSTEMS,
    _circle_points,
    _project,
    circle_poses_from_conic,
    ellipse_conic,
    opencv_error,
    opencv_pipeline,
)
from hil.evaluation.scenarios import camera_pose_for, target_offset
from sim_backends.renderer import PybulletRenderer
from sim_backends.scene import MockupScene
from sim_backends.sensor import expose, frame_rng

TARGET = load_mockup("default").target_model()


@pytest.fixture(scope="module")
def frames_at_2m():
    """Three low-noise reference frames at 2 m with the truth and a prior 1 cm / 1° off."""
    info = load_camera("reference").camera_info()
    rng = np.random.default_rng(3)
    out = []
    with MockupScene(load_mockup("default")) as scene:
        renderer = PybulletRenderer(scene, info, RenderConfig())
        for i, yaw in enumerate((0.0, 0.05, -0.08)):
            X_WC, _ = camera_pose_for(2.0, target_offset(0.02, -0.01, 0.0, 0.03, -0.04, yaw))
            rendering = renderer.render(X_WC)
            image = expose(
                rendering.image, rendering.depth_m, info.K, NoiseConfig(preset="low"),
                frame_rng(0, i),
            )  # fmt: skip
            turn = Pose.from_rotvec(np.radians(1.0) * np.array([0.6, 0.0, 0.8]), np.zeros(3))
            shift = 0.01 * rng.normal(size=3) / np.sqrt(3)
            prior = Pose(turn.R @ rendering.X_CT.R, rendering.X_CT.p + shift)
            out.append((Frame(image, 0.0, info, i), rendering.X_CT, prior))
    return info, out


@pytest.mark.parametrize(
    ("system", "position_m", "attitude_deg"),
    [("corners", 0.03, 5.0), ("lines", 0.04, 8.0), ("ellipses", 0.02, 6.0)],
)
def test_opencv_pipeline_recovers_a_rendered_pose_at_2m(
    frames_at_2m, system, position_m, attitude_deg
):
    """At 2 m and low noise every frame gives a pose, within a few centimetres and degrees in
    the median (four corners of a 0.3 m panel at 2 m tell the attitude only roughly)."""
    cv2.setNumThreads(1)
    info, frames = frames_at_2m
    pipeline = opencv_pipeline(system, TARGET, info)
    errors = []
    for frame, X_CT, prior in frames:
        estimate = pipeline(frame, prior)
        assert estimate.valid, estimate.reason
        errors.append(opencv_error(estimate, X_CT, TARGET))
    assert np.median([e.position_m for e in errors]) < position_m, errors
    assert np.degrees(np.median([e.attitude_rad for e in errors])) < attitude_deg, errors


def test_circle_poses_from_conic_round_trips_a_projected_circle():
    K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
    X_CT = Pose.from_rpy(0.3, -0.2, 0.1, np.array([0.1, -0.05, 2.0])) @ facing_camera(1.0).inverse()
    circle = TARGET.circle("ring_outer")
    uv = _project(_circle_points(circle, 200), X_CT, K, None).astype(np.float32)
    solutions = circle_poses_from_conic(ellipse_conic(*cv2.fitEllipseAMS(uv)), K, circle.radius)
    assert len(solutions) == 2
    center_true = X_CT.apply(circle.center_T)
    normal_true = X_CT.R @ circle.normal_T
    assert any(
        np.allclose(c, center_true, atol=1e-4) and np.allclose(n, normal_true, atol=1e-4)
        for c, n in solutions
    ), solutions
    for center, normal in solutions:  # both in front of the camera, facing it
        assert center[2] > 0 and normal @ center < 0


def test_opencv_pipeline_reports_a_target_out_of_view():
    info = load_camera("reference").camera_info()
    frame = Frame(np.zeros((info.height, info.width), np.uint8), 0.0, info, 0)
    behind = Pose(np.eye(3), np.array([50.0, 0.0, 2.0]))  # far off to the side
    for system in OPENCV_SYSTEMS:
        estimate = opencv_pipeline(system, TARGET, info)(frame, behind)
        assert not estimate.valid
        assert "in view" in estimate.reason or "out of view" in estimate.reason


def test_opencv_pipeline_rejects_an_unknown_system():
    info = load_camera("reference").camera_info()
    with pytest.raises(ValueError, match="no OpenCV pipeline for 'sonar'"):
        opencv_pipeline("sonar", TARGET, info)
