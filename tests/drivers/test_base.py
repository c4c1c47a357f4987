import numpy as np
import pytest

from configuration.camera import load_camera
from configuration.mockup import load_mockup
from configuration.render import NoiseConfig
from drivers.base import Arm, ArmState, Camera, ServoCommand
from estimators.frame import frame_problem
from estimators.geometry import Pose
from hil.evaluation.scenarios import camera_pose_for, target_offset
from sim_backends.camera import SimCamera, Viewpoint
from sim_backends.renderer import PybulletRenderer
from sim_backends.scene import MockupScene


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
        with pytest.raises(Exception, match="not streaming"):
            camera.read()
        with pytest.raises(Exception, match="not connected"):
            camera.activate()
        camera.connect()
        camera.activate()
        first, second = camera.read(), camera.read()
    assert (first.seq, second.seq) == (0, 1) and (first.stamp, second.stamp) == (0, 1)
    assert frame_problem(first) is None
    assert first.truth.X_CT.is_close(X_CT, atol_m=1e-12, atol_rad=1e-12)
    assert not np.array_equal(first.image, second.image)  # fresh noise per frame
