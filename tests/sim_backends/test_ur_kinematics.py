import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from drivers.ur_kinematics import (
    UR_MODELS,
    damped_least_squares,
    forward_kinematics,
    jacobian,
    joint_frames,
    solve_ik,
    ur_model,
)
from estimators.geometry import Pose
from sim_backends.bullet import connect_direct, pybullet, silenced_fds
from sim_backends.ur_urdf import JOINT_NAMES, ur_urdf, urdf_path

UR10E = ur_model("ur10e")


def _pybullet_flange(client: int, body: int, q: np.ndarray) -> Pose:
    for j in range(6):
        pybullet.resetJointState(body, j, q[j], physicsClientId=client)
    link = pybullet.getLinkState(body, 6, computeForwardKinematics=True, physicsClientId=client)
    return Pose(Rotation.from_quat(link[5]).as_matrix(), np.array(link[4]))


def test_forward_kinematics_matches_shipped_urdf_in_pybullet():
    client = connect_direct()
    try:
        with silenced_fds():
            body = pybullet.loadURDF(
                str(urdf_path("ur10e")), useFixedBase=True, physicsClientId=client
            )
        names = [
            pybullet.getJointInfo(body, j, physicsClientId=client)[1].decode() for j in range(6)
        ]
        assert names == list(JOINT_NAMES)
        assert pybullet.getJointInfo(body, 6, physicsClientId=client)[12].decode() == "tool0"
        rng = np.random.default_rng(7)
        for _ in range(20):
            q = rng.uniform(UR10E.lower, UR10E.upper)
            X_dh = forward_kinematics(UR10E, q)
            X_pb = _pybullet_flange(client, body, q)
            # pybullet works in float32-ish precision for link states
            assert X_dh.is_close(X_pb, atol_m=1e-6, atol_rad=1e-6)
        lower, upper = pybullet.getJointInfo(body, 2, physicsClientId=client)[
            8:10
        ]  # elbow limits from the file
        assert (lower, upper) == pytest.approx((-math.pi, math.pi))
    finally:
        pybullet.disconnect(client)


def test_shipped_urdf_is_the_generated_one():
    assert urdf_path("ur10e").read_text() == ur_urdf(UR10E)


def test_urdf_path_names_the_missing_file():
    with pytest.raises(FileNotFoundError, match="ur5e"):
        urdf_path("ur5e")
    with pytest.raises(ValueError, match="unknown arm model 'ur7'"):
        urdf_path("ur7")


def test_forward_kinematics_zero_pose_matches_published_geometry():
    # All joints at zero: the arm lies stretched along −x of the base; the flange sits at
    # x = a2 + a3, y = −(d4 + d6) (the shoulder and wrist offsets), z = d1 − d5, its z axis
    # pointing along −y (UR's zero pose as drawn on UR's DH page).
    X = forward_kinematics(UR10E, np.zeros(6))
    assert X.p == pytest.approx([-0.6127 - 0.57155, -(0.17415 + 0.11655), 0.1807 - 0.11985])
    assert X.R[:, 2] == pytest.approx([0.0, -1.0, 0.0], abs=1e-12)


def test_forward_kinematics_upright_pose_points_the_arm_up():
    # q2 = q4 = −90°: upper arm and forearm vertical, so the wrist is 1.18 m above the
    # shoulder; then the flange sits d5 further forward along the base y and looks down −y.
    q = np.radians([0.0, -90.0, 0.0, -90.0, 0.0, 0.0])
    X = forward_kinematics(UR10E, q)
    d1, a2, a3, d4, d5, d6 = 0.1807, 0.6127, 0.57155, 0.17415, 0.11985, 0.11655
    assert X.p == pytest.approx([0.0, -(d4 + d6), d1 + a2 + a3 + d5])
    assert X.R[:, 2] == pytest.approx([0.0, -1.0, 0.0], abs=1e-12)


def test_ur_models_carry_published_speeds():
    assert np.degrees(UR10E.max_joint_speed) == pytest.approx([120, 120, 180, 180, 180, 180])
    assert np.degrees(ur_model("ur5e").max_joint_speed) == pytest.approx([180] * 6)
    assert UR10E.upper[2] == pytest.approx(math.pi)
    assert UR10E.upper[0] == pytest.approx(2 * math.pi)


@pytest.mark.parametrize("name", sorted(UR_MODELS))
def test_jacobian_matches_finite_differences(name):
    model = ur_model(name)
    rng = np.random.default_rng(3)
    for _ in range(5):
        q = rng.uniform(-3.0, 3.0, 6)
        J = jacobian(model, q)
        X0 = forward_kinematics(model, q)
        h = 1e-6
        for i in range(6):
            dq = np.zeros(6)
            dq[i] = h
            X1 = forward_kinematics(model, q + dq)
            v = (X1.p - X0.p) / h
            w = Rotation.from_matrix(X1.R @ X0.R.T).as_rotvec() / h
            assert J[:3, i] == pytest.approx(v, abs=1e-5)
            assert J[3:, i] == pytest.approx(w, abs=1e-5)


def test_damped_least_squares_is_exact_away_from_singularities():
    q = np.radians([164.0, -55.7, 118.2, 117.5, -74.0, 0.0])
    J = jacobian(UR10E, q)
    V = np.array([0.1, -0.05, 0.02, 0.1, 0.0, -0.2])
    qd, sigma_min = damped_least_squares(J, V, sigma_threshold=0.05, damping_max=0.05)
    assert sigma_min > 0.05
    assert J @ qd == pytest.approx(V, abs=1e-12)


def test_damped_least_squares_bounds_joint_speed_at_a_singularity():
    q = np.radians([0.0, -90.0, 0.0, -90.0, 0.0, 0.0])  # wrist 2 at 0: wrist singularity
    J = jacobian(UR10E, q)
    sigma = np.linalg.svd(J, compute_uv=False)
    assert sigma[-1] < 1e-9
    U, _, _ = np.linalg.svd(J)
    V = 0.1 * U[:, -1]  # the direction the arm cannot move in
    qd, sigma_min = damped_least_squares(J, V, sigma_threshold=0.05, damping_max=0.05)
    assert sigma_min < 1e-9
    assert np.all(np.isfinite(qd)) and np.max(np.abs(qd)) < 1e-6


def test_solve_ik_round_trips_forward_kinematics():
    rng = np.random.default_rng(11)
    q_start = np.radians([164.0, -55.7, 118.2, 117.5, -74.0, 0.0])
    for _ in range(5):
        q_goal = q_start + rng.uniform(-0.3, 0.3, 6)
        X_goal = forward_kinematics(UR10E, q_goal)
        q, ok = solve_ik(UR10E, X_goal, q_start)
        assert ok
        assert forward_kinematics(UR10E, q).is_close(X_goal, atol_m=1e-6, atol_rad=1e-6)


def test_joint_frames_rejects_bad_joint_vectors():
    with pytest.raises(ValueError, match="shape"):
        joint_frames(UR10E, np.zeros(5))
    with pytest.raises(ValueError, match="NaN"):
        joint_frames(UR10E, np.array([0.0, np.nan, 0, 0, 0, 0]))
