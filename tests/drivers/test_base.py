import numpy as np
import pytest

from drivers.base import Arm, ArmState, Camera, CameraInfo, Frame, ServoCommand, frame_problem
from estimators.geometry import Pose, intrinsics_from_fov
from hil.config import NoiseConfig, load_camera, load_mockup
from hil.scenarios import camera_pose_for, target_offset
from sim_backends.camera import SimCamera, Viewpoint
from sim_backends.renderer import PybulletRenderer
from sim_backends.scene import MockupScene

INFO = CameraInfo(640, 480, intrinsics_from_fov(640, 480, 70.0), np.zeros(0), "reference")


def test_camera_info_validates():
    with pytest.raises(ValueError, match="K must have shape"):
        CameraInfo(640, 480, np.eye(2), np.zeros(0), "x")
    with pytest.raises(ValueError, match="not an upper-triangular"):
        CameraInfo(640, 480, -np.eye(3), np.zeros(0), "x")
    with pytest.raises(ValueError, match="coefficients"):
        CameraInfo(640, 480, np.eye(3), np.zeros(3), "x")
    with pytest.raises(ValueError, match="channels"):
        CameraInfo(640, 480, np.eye(3), np.zeros(0), "x", channels=2)


def test_camera_info_in_view_rejects_fold_back_of_distortion():
    oak = load_camera("oak_d_rgb").camera_info()
    far_outside = np.array(
        [[-2.069, 1.363, 1.2585]]
    )  # projects *into* the image through the polynomial
    uv = oak.project(far_outside)[0]
    assert 0 <= uv[0] < oak.width and 0 <= uv[1] < oak.height
    assert not oak.in_view(far_outside)[0]
    assert oak.in_view(np.array([[0.1, 0.05, 1.2]]))[0]
    assert not oak.in_view(np.array([[0.0, 0.0, -1.0]]))[0]


@pytest.mark.parametrize(
    ("image", "problem"),
    [
        (np.zeros((0, 0), np.uint8), "empty"),
        (np.zeros((480, 641), np.uint8), "does not match"),
        (np.full((480, 640), np.nan, np.float32), "NaN"),
        (np.zeros((480, 640), np.int32), "neither uint8 nor float"),
        ([[0]], "not an array"),
    ],
)
def test_frame_problem_names_what_is_wrong(image, problem):
    assert problem in frame_problem(Frame(image, 0.0, INFO, 0))


def test_frame_problem_accepts_a_good_frame():
    assert frame_problem(Frame(np.zeros((480, 640), np.uint8), 1.0, INFO, 0)) is None


def test_servo_command_rejects_nan_and_arm_state_reports_faults():
    with pytest.raises(ValueError, match="NaN"):
        ServoCommand(0.0, np.array([0, 0, np.nan, 0, 0, 0]))
    halt = ServoCommand.halt(1.0, "stale estimate")
    assert halt.stop and not np.any(halt.V_BE)
    state = ArmState(0.0, np.zeros(6), Pose.identity(), np.zeros(6), protective_stop=True)
    assert state.fault_reason == "protective stop"
    assert ArmState(0.0, np.zeros(6), Pose.identity(), np.zeros(6)).fault_reason is None


def test_sim_camera_is_a_camera_and_frames_carry_truth():
    mockup = load_mockup("default")
    info = load_camera("reference").camera_info()
    X_WC, X_CT = camera_pose_for(2.0, target_offset(0.05))
    with MockupScene(mockup) as scene:
        camera = SimCamera(
            PybulletRenderer(scene, info),
            lambda: Viewpoint(X_WC),
            NoiseConfig(preset="low"),
            seed=4,
            clock=iter(range(100)).__next__,
        )
        assert isinstance(camera, Camera)
        assert not isinstance(camera, Arm)
        with pytest.raises(Exception, match="not connected"):
            camera.read()
        camera.connect()
        first, second = camera.read(), camera.read()
    assert (first.seq, second.seq) == (0, 1) and (first.stamp, second.stamp) == (0, 1)
    assert frame_problem(first) is None
    assert first.truth.X_CT.is_close(X_CT, atol_m=1e-12, atol_rad=1e-12)
    assert not np.array_equal(first.image, second.image)  # fresh noise per frame
