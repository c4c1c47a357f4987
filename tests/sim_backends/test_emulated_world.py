"""The emulated rig in this process (no ur-rtde client here: its constructors hold the GIL):
the UR controller drives the world's own arm, so the camera follows what the controller does;
the track and gripper answer the real Modbus drivers at their endpoints; faults by name."""

import numpy as np
import pytest

from configuration.rig import ModbusEndpoint, load_rig
from drivers.base import DeviceError, DeviceTimeout
from drivers.gripper_robotiq import RobotiqGripper
from drivers.track_modbus import ModbusTrack
from estimators.geometry import Pose
from sim_backends.emulated_world import EmulatedEndpoints, EmulatedRig
from sim_backends.ur_emulator import free_loopback_host

# Wall-clock trials run alone (`make test` runs them after the rest, one at a time): beside
# another test on two cores they starve their own emulators and vision processes.
pytestmark = pytest.mark.wall_clock

RIG = load_rig("rig")
GRASP = Pose(np.eye(3), np.array([0.0, 0.0, 0.35]))  # far from any pose these tests reach


def endpoints() -> EmulatedEndpoints:
    modbus = free_loopback_host()
    return EmulatedEndpoints(
        free_loopback_host(),
        ModbusEndpoint(host=modbus, port=5020, device_id=1, timeout_s=0.1),
        ModbusEndpoint(host=modbus, port=5021, device_id=9, timeout_s=0.1),
    )


@pytest.fixture
def world():
    with EmulatedRig(RIG, endpoints(), grasp_X_TC=GRASP) as world:
        world.start()
        yield world


def test_emulated_rig_controller_drives_the_arm_the_camera_is_rendered_from(world):
    captures = []
    world.on_capture = captures.append
    X_WC0 = world.arm.camera_pose_W()
    V = np.array([0.0, 0.05, 0.0, 0.0, 0.0, 0.0])  # 5 cm/s along y_B
    world.controller.speed(V, acceleration=10.0)
    world.advance(1.0)
    # one arm: the controller's published joints are the world's arm's
    assert np.allclose(world.controller.q, world.arm.q)
    moved_W = world.arm.camera_pose_W().p - X_WC0.p
    R_WB = RIG.arm.X_WB.pose.R
    assert np.allclose(moved_W, R_WB @ V[:3] * 1.0, atol=2e-3), moved_W  # ramp: < 1 mm short
    assert len(captures) == 16  # 15 fps from 0 to 1 s, both ends, each on the 4 ms grid
    assert np.allclose(np.diff(captures), 1.0 / 15.0, atol=world.grid_s)


def test_emulated_rig_serves_track_and_gripper_to_their_drivers(world):
    track_at, gripper_at = world.endpoints.track, world.endpoints.gripper
    track = ModbusTrack.over_tcp(track_at.host, track_at.port, track_at.device_id, timeout_s=0.5)
    gripper = RobotiqGripper.over_tcp(
        gripper_at.host, gripper_at.port, gripper_at.device_id, timeout_s=0.5
    )
    try:
        for device in (track, gripper):
            device.connect()
            device.activate()
        track.move_velocity(0.1)
        world.advance(0.4)  # the models move only with the world
        state = track.state()  # (a request at least every 0.5 s: the track's watchdog)
        # 0.2 s ramp at 0.5 m/s² to 0.1 m/s, then 0.2 s at it: 0.03 m
        assert state.position == pytest.approx(0.03, abs=1e-3) and state.moving
        assert world.track_model.position == pytest.approx(state.position, abs=1e-6)
        assert not gripper.state().activated  # activation takes 0.5 s
        world.advance(0.2)
        assert gripper.state().activated
    finally:
        track.close()
        gripper.close()


def test_emulated_rig_silenced_modbus_device_times_out_then_answers_again(world):
    at = world.endpoints.track
    track = ModbusTrack.over_tcp(at.host, at.port, at.device_id, timeout_s=0.1)
    try:
        track.connect()
        world.inject("track", "silence", True)
        with pytest.raises(DeviceTimeout, match=r"no reply within 0\.1 s"):
            track.state()
        world.inject("track", "silence", False)
        assert track.state().fault is None
        world.inject("track", "inject_drive_fault")
        assert "drive fault" in track.state().fault
    finally:
        track.close()


def test_emulated_rig_injects_ur_faults_by_name_and_refuses_others(world):
    world.inject("ur", "protective_stop")
    assert world.controller.halted
    with pytest.raises(DeviceError, match="not a fault of the emulated rig"):
        world.inject("ur", "set_joint_positions", [0.0] * 6)
    with pytest.raises(DeviceError, match="not a fault"):
        world.inject("camera", "silence")


def test_emulated_rig_on_a_taken_address_says_which_port(world):
    taken = EmulatedEndpoints(
        world.endpoints.ur_host,
        ModbusEndpoint(host=free_loopback_host(), port=5020, device_id=1),
        ModbusEndpoint(host=free_loopback_host(), port=5021, device_id=9),
    )
    with pytest.raises(OSError, match=rf"cannot listen on {world.endpoints.ur_host}:29999"):
        EmulatedRig(RIG, taken, grasp_X_TC=GRASP)


def test_emulated_endpoints_refuse_a_non_loopback_address():
    local = ModbusEndpoint(host="127.0.0.1", port=5020, device_id=1)
    with pytest.raises(ValueError, match="loopback"):
        EmulatedEndpoints("192.168.1.10", local, local.model_copy(update={"device_id": 9}))
    with pytest.raises(ValueError, match="same Modbus address"):
        EmulatedEndpoints("127.0.0.2", local, local)
