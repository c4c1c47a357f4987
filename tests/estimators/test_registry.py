"""The registry's estimators follow the intrinsics each frame carries: one built estimator per
distinct CameraInfo, built on first sight, reused, bounded."""

import math
import pickle
from functools import lru_cache

import numpy as np
import pytest

from configuration.mockup import load_mockup
from configuration.render import NoiseConfig, RenderConfig
from estimators.frame import CameraInfo, Frame
from estimators.geometry import intrinsics_from_fov, rotation_error_geodesic, translation_error
from estimators.measurement import Measurement
from estimators.registry import PerCameraEstimator, build_estimator
from hil.evaluation.scenarios import camera_pose_for, target_offset
from sim_backends.renderer import PybulletRenderer
from sim_backends.scene import MockupScene
from sim_backends.sensor import expose, frame_rng
from tests.estimators.rendered import frame as rendered_frame
from tests.estimators.rendered import target

REFERENCE = CameraInfo(640, 480, intrinsics_from_fov(640, 480, 70.0), np.zeros(0), "reference")


class _Echo:
    """Answers with the camera it was built for (in ``reason``), so a test sees which one ran."""

    system = "echo"

    def __init__(self, camera: CameraInfo):
        self.camera = camera

    def estimate(self, frame, prior_X_CT=None):
        return Measurement.lost(self.system, frame, f"fx={self.camera.K[0, 0]:.1f}")


def _camera(fx: float) -> CameraInfo:
    return CameraInfo(640, 480, [[fx, 0, 319.5], [0, fx, 239.5], [0, 0, 1]], [], f"fx{fx}")


def _frame(camera: CameraInfo, seq: int = 0) -> Frame:
    return Frame(np.zeros(camera.shape, np.uint8), seq / 30, camera, seq)


def test_per_camera_estimator_builds_once_per_camera_and_routes_by_frame():
    built = []

    def build(camera):
        built.append(camera.K[0, 0])
        return _Echo(camera)

    estimator = PerCameraEstimator(build, _camera(500.0))
    assert estimator.system == "echo" and built == [500.0]
    for seq in range(3):  # the same content under another name is the same camera
        same = CameraInfo(640, 480, _camera(500.0).K, [], f"copy {seq}")
        assert estimator.estimate(_frame(same, seq)).reason == "fx=500.0"
    assert estimator.estimate(_frame(_camera(600.0))).reason == "fx=600.0"
    assert estimator.estimate(_frame(_camera(500.0))).reason == "fx=500.0"
    assert built == [500.0, 600.0] and estimator.builds == 2


def test_per_camera_estimator_keeps_a_bounded_number_of_cameras():
    built = []

    def build(camera):
        built.append(camera.K[0, 0])
        return _Echo(camera)

    estimator = PerCameraEstimator(build, _camera(500.0), capacity=2)
    for fx in (600.0, 500.0, 700.0):  # 600 is now the least recently used: dropped
        estimator.estimate(_frame(_camera(fx)))
    assert estimator.builds == 2
    estimator.estimate(_frame(_camera(500.0)))
    assert built == [500.0, 600.0, 700.0]  # 500 was kept
    estimator.estimate(_frame(_camera(600.0)))
    assert built == [500.0, 600.0, 700.0, 600.0]  # 600 rebuilt
    with pytest.raises(ValueError, match="capacity"):
        PerCameraEstimator(build, _camera(500.0), capacity=0)


def test_build_estimator_pickles_and_keeps_routing():
    estimator = build_estimator("tests.estimators.test_registry:_echo", target(), _camera(500.0))
    copy = pickle.loads(pickle.dumps(estimator))
    assert copy.estimate(_frame(_camera(600.0))).reason == "fx=600.0" and copy.builds == 2


def _echo(target, camera, **options):
    return _Echo(camera)


def test_build_estimator_rejects_bad_options_at_build_time():
    with pytest.raises(ValueError, match="unknown ellipse estimator option"):
        build_estimator("ellipses", target(), REFERENCE, no_such_option=1)
    with pytest.raises(ValueError, match="unknown estimator system"):
        build_estimator("nope", target(), REFERENCE)


@lru_cache(maxsize=1)
def _calibrated_view():
    """A frame of a calibrated camera with another K than the reference profile's and 14
    distortion coefficients (as an OAK reports), 2 m from the target; and its true X_CT."""
    K = np.array([[520.0, 0.0, 327.4], [0.0, 518.5, 236.2], [0.0, 0.0, 1.0]])
    dist = np.r_[-0.08, 0.09, 3e-4, -4e-4, -0.03, np.zeros(7), 0.004, -0.003]
    calibrated = CameraInfo(640, 480, K, dist, "calibrated")
    X_WC, _ = camera_pose_for(2.0, target_offset(0.03, -0.02, 0.0, 0.035, -0.052, 0.105))
    with MockupScene(load_mockup("default")) as scene:
        rendering = PybulletRenderer(scene, calibrated, RenderConfig()).render(X_WC)
    image = expose(rendering.image, None, K, NoiseConfig(preset="low"), frame_rng(0, 0))
    return Frame(image, 0.0, calibrated, 0), rendering.X_CT


@pytest.mark.parametrize("system", ["corners", "lines", "ellipses"])
def test_build_estimator_uses_the_intrinsics_the_frame_carries(system):
    """Built for the reference profile, fed a calibrated camera's frame: the pose is as good as
    on its own camera (before, corners and lines used the profile's K, ellipses lost it)."""
    frame, X_CT = _calibrated_view()
    estimator = build_estimator(system, target(), REFERENCE)
    m = estimator.estimate(frame)
    assert m.valid, m.reason
    if system == "ellipses":
        ring = target().circle("ring_outer")
        center = X_CT.apply(ring.center_T)
        assert np.linalg.norm(m.center_C - center) < 0.01
    else:
        assert translation_error(X_CT, m.X_CT) < 0.02
        assert math.degrees(rotation_error_geodesic(X_CT, m.X_CT)) < 2.0
    # A reference frame still goes to the reference-built estimator.
    assert estimator.estimate(rendered_frame(2.0)).valid
    assert estimator.builds == 2
