"""The simulated world's contact model: the fingertips, ``tool_reach_m`` ahead of the camera,
pressed past the ring's face plane push back on the arm, which reports it as its TCP wrench."""

import numpy as np
import pytest

from configuration.rig import load_rig
from drivers.ur_kinematics import solve_ik, ur_model
from estimators.geometry import Pose
from estimators.target import facing_camera
from sim_backends.rig_geometry import target_pose_W, track_position_at_distance
from sim_backends.world import SimRig

RIG = load_rig()
REACH, STIFFNESS = 0.34, 2000.0


def rig_near_the_face():
    """The rig with its carriage parked so the ring face is 0.5 m ahead of the start camera."""
    position = track_position_at_distance(RIG, 0.5)
    track = RIG.track.model_copy(update={"start_position": position})
    return RIG.model_copy(update={"track": track}), position


def world_with_camera_at(X_TC: Pose) -> SimRig:
    rig, position = rig_near_the_face()
    X_WT = target_pose_W(rig.track, position)
    X_BE = rig.arm.X_WB.pose.inverse() @ X_WT @ X_TC @ rig.arm.X_EC.pose.inverse()
    q, converged = solve_ik(ur_model(rig.arm.model), X_BE, np.radians(rig.arm.q0_deg))
    assert converged
    world = SimRig(
        rig,
        grasp_X_TC=facing_camera(0.35),
        start_q=q,
        tool_reach_m=REACH,
        contact_stiffness=STIFFNESS,
    )
    world.start()
    return world


@pytest.mark.parametrize("clearance", [0.02, 0.001])
def test_contact_wrench_is_zero_short_of_the_face(clearance):
    with world_with_camera_at(facing_camera(REACH + clearance)) as world:
        assert np.array_equal(world.arm.state().wrench_B, np.zeros(6))


@pytest.mark.parametrize("depth", [0.005, 0.02])
def test_contact_wrench_pushes_the_tool_back_in_proportion(depth):
    sideways = Pose(np.eye(3), np.array([0.03, -0.02, 0.0]))  # off the ring's axis
    with world_with_camera_at(sideways @ facing_camera(REACH - depth)) as world:
        state = world.arm.state()
        X_BT = world.arm.X_WB.inverse() @ world.track_model.X_WT()
        force_B, torque_B = state.wrench_B[:3], state.wrench_B[3:]
        # k·δ along the face's outward normal, i.e. back along the camera's optical axis
        assert force_B == pytest.approx(X_BT.R @ [0, 0, STIFFNESS * depth], abs=1e-3)
        X_BC = state.X_BE @ world.arm.X_EC
        assert force_B @ X_BC.R[:, 2] == pytest.approx(-STIFFNESS * depth, rel=1e-4)
        # its moment about the flange, from the fingertip
        tip_B = X_BC.apply(np.array([0.0, 0.0, REACH]))
        assert torque_B == pytest.approx(np.cross(tip_B - state.X_BE.p, force_B), abs=1e-9)
        assert np.linalg.norm(torque_B) > 0.01  # the camera sits off the flange's axis


def test_contact_model_is_off_without_a_reach():
    rig, _ = rig_near_the_face()
    with SimRig(rig, grasp_X_TC=facing_camera(0.35)) as world:
        world.start()
        assert np.array_equal(world.arm.state().wrench_B, np.zeros(6))
