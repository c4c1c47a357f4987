import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from estimators.geometry import (
    Pose,
    back_project,
    check_distortion,
    cross3,
    distort_normalized,
    field_radius,
    in_view,
    intrinsics_from_fov,
    look_at,
    normal_angle,
    padded_distortion,
    project,
    project_from,
    rotation_between,
    rotation_error_geodesic,
    rotation_error_rpy_norm,
    translation_error,
    undistort_pixels,
)

finite = st.floats(-5.0, 5.0, allow_nan=False)
vectors = st.tuples(finite, finite, finite).map(np.array)
rotvecs = st.tuples(*[st.floats(-3.0, 3.0)] * 3).map(np.array)
poses = st.builds(Pose.from_rotvec, rotvecs, vectors)

K_REF = intrinsics_from_fov(640, 480, 70.0)
DIST_OAK = np.array([-0.090, 0.110, 0.00030, -0.00040, -0.040])
DIST_RATIONAL = np.array([0.12, -0.05, 0.001, -0.0007, 0.01, 0.15, -0.03, 0.02])
#: depthai's full model: rational + thin prism + a tilted sensor (τx, τy in rad).
DIST_TILTED = np.r_[DIST_RATIONAL, 0.001, -0.002, 0.0005, 0.001, 0.012, -0.018]


@given(poses)
def test_pose_inverse_composes_to_identity(X_AB):
    assert (X_AB @ X_AB.inverse()).is_close(Pose.identity(), atol_m=1e-9, atol_rad=1e-9)
    assert (X_AB.inverse() @ X_AB).is_close(Pose.identity(), atol_m=1e-9, atol_rad=1e-9)


@given(poses, poses, poses)
def test_pose_composition_is_associative(X_AB, X_BC, X_CD):
    left = (X_AB @ X_BC) @ X_CD
    right = X_AB @ (X_BC @ X_CD)
    assert left.is_close(right, atol_m=1e-9, atol_rad=1e-9)


@given(poses, poses, vectors)
def test_pose_apply_matches_composition(X_AB, X_BC, p_C):
    assert np.allclose((X_AB @ X_BC).apply(p_C), X_AB.apply(X_BC.apply(p_C)), atol=1e-9)


@given(poses)
def test_pose_matrix_round_trip(X_AB):
    assert Pose.from_matrix(X_AB.matrix).is_close(X_AB)
    assert np.allclose(X_AB.matrix @ np.linalg.inv(X_AB.matrix), np.eye(4), atol=1e-9)


def test_pose_rejects_non_rotation():
    with pytest.raises(ValueError, match="not a rotation"):
        Pose(np.diag([1.0, 1.0, 2.0]), np.zeros(3))
    with pytest.raises(ValueError, match="not a rotation"):
        Pose(np.diag([1.0, 1.0, -1.0]), np.zeros(3))  # a reflection


def test_pose_rejects_nan_and_bad_shapes():
    with pytest.raises(ValueError, match="NaN"):
        Pose(np.eye(3), np.array([0.0, np.nan, 0.0]))
    with pytest.raises(ValueError, match="3x3"):
        Pose(np.eye(4), np.zeros(3))
    with pytest.raises(ValueError, match="last row"):
        Pose.from_matrix(np.ones((4, 4)))


def test_pose_from_matrix_orthonormalize_repairs_drift():
    R = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix() + 1e-4
    X = np.eye(4)
    X[:3, :3] = R
    repaired = Pose.from_matrix(X, orthonormalize=True)
    assert np.allclose(repaired.R @ repaired.R.T, np.eye(3), atol=1e-12)


def test_pose_is_immutable():
    X = Pose.identity()
    with pytest.raises(ValueError):
        X.p[0] = 1.0


def test_look_at_points_the_optical_axis_at_the_target():
    X_WC = look_at(np.array([1.0, 2.0, 3.0]), np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]))
    target_C = X_WC.inverse().apply(np.zeros(3))
    assert np.allclose(target_C[:2], 0.0, atol=1e-12) and target_C[2] > 0
    # Image "up" (−y_C) leans toward world +z.
    assert (-X_WC.R[:, 1])[2] > 0


# No deadline: the first example may compile the lens model (seconds, with a cold numba cache).
@settings(max_examples=200, deadline=None)
@given(
    st.floats(-0.55, 0.55),
    st.floats(-0.45, 0.45),
    st.floats(0.3, 10.0),
    st.sampled_from([None, DIST_OAK, DIST_RATIONAL, DIST_TILTED]),
)
def test_project_back_project_round_trip(x, y, z, dist):
    p_C = np.array([[x * z, y * z, z]])
    uv = project(p_C, K_REF, dist)
    ray = back_project(uv, K_REF, dist)[0]
    assert np.allclose(ray, p_C[0] / np.linalg.norm(p_C[0]), atol=1e-10)


@pytest.mark.parametrize(
    "dist",
    [
        np.zeros(0),
        DIST_OAK,
        DIST_RATIONAL,
        np.r_[DIST_RATIONAL, 0.001, -0.002, 0.0005, 0.001],
        DIST_TILTED,
        np.r_[np.zeros(12), 0.02, 0.0],  # tilt alone
    ],
)
def test_project_matches_opencv(dist):
    rng = np.random.default_rng(3)
    points = np.column_stack(
        [rng.uniform(-1, 1, 50), rng.uniform(-0.8, 0.8, 50), rng.uniform(1, 4, 50)]
    )
    K = np.array([[600.0, 0.0, 330.2], [0.0, 610.0, 241.7], [0.0, 0.0, 1.0]])  # OpenCV has no skew
    expected, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), K, dist)
    assert np.allclose(project(points, K, dist), expected.reshape(-1, 2), atol=1e-9)


def test_undistort_inverts_distortion_to_high_precision():
    rng = np.random.default_rng(4)
    xy = rng.uniform(-0.7, 0.7, size=(500, 2))
    uv = project(np.column_stack([xy, np.ones(len(xy))]), K_REF, DIST_OAK)
    assert np.abs(undistort_pixels(uv, K_REF, DIST_OAK) - xy).max() < 1e-10


@pytest.mark.parametrize("dist", [DIST_OAK, DIST_RATIONAL, DIST_TILTED])
def test_undistort_pixels_matches_opencv_undistort_points(dist):
    rng = np.random.default_rng(5)
    K = np.array([[600.0, 0.0, 330.2], [0.0, 610.0, 241.7], [0.0, 0.0, 1.0]])
    xy = rng.uniform(-0.6, 0.6, size=(300, 2))
    uv, _ = cv2.projectPoints(
        np.column_stack([xy, np.ones(len(xy))]), np.zeros(3), np.zeros(3), K, dist
    )
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    expected = cv2.undistortPoints(uv, K, dist, criteria=criteria).reshape(-1, 2)
    ours = undistort_pixels(uv.reshape(-1, 2), K, dist)
    assert np.abs(ours - xy).max() < 1e-10
    assert np.abs(ours - expected).max() < 1e-8


@pytest.mark.parametrize("length", [4, 5, 8, 12, 14])
def test_check_distortion_accepts_every_opencv_length(length):
    assert check_distortion(np.full(length, 0.01)).shape == (length,)


def test_padded_distortion_pads_to_the_next_opencv_length():
    assert padded_distortion(np.ones(3)).tolist() == [1, 1, 1, 0]
    assert padded_distortion(np.ones(13)).shape == (14,) and padded_distortion([]).size == 0
    with pytest.raises(ValueError, match="at most 14"):
        padded_distortion(np.ones(15))


@pytest.mark.parametrize("length", [1, 3, 6, 13, 15])
def test_check_distortion_rejects_other_lengths(length):
    with pytest.raises(ValueError, match="0, 4, 5, 8, 12 or 14 coefficients"):
        check_distortion(np.zeros(length))


def test_project_rejects_points_behind_camera_and_bad_distortion():
    with pytest.raises(ValueError, match="positive depth"):
        project(np.array([[0.0, 0.0, -1.0]]), K_REF)
    with pytest.raises(ValueError, match="coefficients"):
        distort_normalized(np.zeros((1, 2)), np.zeros(3))
    with pytest.raises(ValueError, match="shape"):
        project(np.zeros((4, 2)), K_REF)


def test_project_from_applies_the_pose():
    X_CT = Pose.from_rotvec(np.array([0.1, 0.2, 0.0]), np.array([0.1, 0.0, 2.0]))
    p_T = np.array([[0.1, 0.2, 0.0]])
    assert np.allclose(project_from(X_CT, p_T, K_REF), project(X_CT.apply(p_T), K_REF))


def test_intrinsics_from_fov_reference_camera():
    K = intrinsics_from_fov(640, 480, 70.0)
    assert K[0, 0] == pytest.approx(320.0 / np.tan(np.radians(35.0)))
    assert (K[0, 2], K[1, 2]) == (319.5, 239.5)
    with pytest.raises(ValueError, match="hfov_deg"):
        intrinsics_from_fov(640, 480, 190.0)


@given(poses, st.floats(0.0, 3.1), vectors)
def test_rotation_error_geodesic_recovers_the_applied_angle(X, angle, axis):
    if np.linalg.norm(axis) < 1e-3:
        return
    axis = axis / np.linalg.norm(axis)
    X_est = Pose(
        Rotation.from_rotvec(angle * axis).as_matrix() @ X.R, X.p + np.array([0.3, 0.0, -0.4])
    )
    assert rotation_error_geodesic(X, X_est) == pytest.approx(angle, abs=1e-7)
    assert translation_error(X, X_est) == pytest.approx(0.5)


def test_rotation_error_rpy_norm_matches_single_axis_angle():
    X = Pose.identity()
    for axis in range(3):
        rpy = np.zeros(3)
        rpy[axis] = np.radians(7.0)
        X_est = Pose.from_rpy(*rpy, np.zeros(3))
        assert rotation_error_rpy_norm(X, X_est) == pytest.approx(np.radians(7.0), abs=1e-12)
    # For combined rotations the two metrics differ, but both stay small together.
    X_est = Pose.from_rpy(0.01, -0.02, 0.015, np.zeros(3))
    assert rotation_error_rpy_norm(X, X_est) == pytest.approx(
        rotation_error_geodesic(X, X_est), rel=0.01
    )


def test_normal_angle_is_oriented():
    n = np.array([0.0, 0.0, 1.0])
    assert normal_angle(n, n) == 0.0
    assert normal_angle(n, -n) == pytest.approx(np.pi)
    assert normal_angle(n, np.array([0.0, np.sin(0.1), np.cos(0.1)])) == pytest.approx(0.1)
    assert normal_angle(n, np.array([0.0, 1e-9, 1.0])) == pytest.approx(1e-9, rel=1e-6)


def test_distortion_where_the_rational_denominator_vanishes_is_not_finite_and_does_not_raise():
    """Far outside a calibrated field a rational model's denominator can reach zero: NumPy gave
    a non-finite point there, and so must the compiled model (numba's default is to raise)."""
    dist = np.array([0.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0])  # 1 + k4·r² = 0 at r = 1
    out = distort_normalized(np.array([[1.0, 0.0], [0.1, 0.2]]), dist)
    assert not np.all(np.isfinite(out[0]))
    assert np.allclose(out[1], np.array([0.1, 0.2]) / (1.0 - 0.05))


def test_cross3_is_nps_cross_to_the_last_bit():
    rng = np.random.default_rng(11)
    for a, b in rng.normal(size=(200, 2, 3)) * 10.0 ** rng.integers(-6, 6, size=(200, 1, 1)):
        assert np.array_equal(cross3(a, b), np.cross(a, b))


@pytest.mark.parametrize(
    "a, b",
    [
        ([0.0, 0.0, 1.0], [0.3, -0.2, 0.9]),
        ([1.0, 2.0, 3.0], [-2.0, 0.5, 0.1]),
        ([0.0, 0.0, 1.0], [0.0, 0.0, 1.0]),  # the same direction: no turn
        ([0.0, 0.0, 1.0], [0.0, 0.0, -2.0]),  # opposite: a half turn
        ([1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]),
    ],
)
def test_rotation_between_turns_one_direction_onto_the_other_by_the_smallest_angle(a, b):
    a, b = np.asarray(a), np.asarray(b)
    R = rotation_between(a, b)
    unit_a, unit_b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.linalg.det(R) > 0
    assert np.allclose(R @ unit_a, unit_b, atol=1e-12)
    angle = Rotation.from_matrix(R).magnitude()
    assert angle == pytest.approx(np.arccos(np.clip(unit_a @ unit_b, -1, 1)), abs=1e-9)


@pytest.mark.parametrize("dist", [None, DIST_RATIONAL, DIST_TILTED])
@pytest.mark.parametrize("margin_px", [0.0, 3.0, -20.0])
def test_in_view_is_in_front_within_the_field_and_inside_the_pixels_outer_edges(dist, margin_px):
    """The test written out in NumPy, point by point, against the compiled one."""
    rng = np.random.default_rng(5)
    points = np.column_stack(
        [rng.uniform(-3, 3, 4000), rng.uniform(-2, 2, 4000), rng.uniform(-0.5, 3, 4000)]
    )
    K = np.array([[600.0, 0.0, 319.5], [0.0, 600.0, 239.5], [0.0, 0.0, 1.0]])
    width, height = 640, 480
    limit = 1.02 * field_radius(K, dist, width, height)
    expected = np.zeros(len(points), bool)
    for i, (x, y, z) in enumerate(points):
        if z > 1e-9 and np.hypot(x / z, y / z) <= limit:
            u, v = project(np.array([[x, y, z]]), K, dist)[0]
            expected[i] = (margin_px - 0.5 <= u <= width - 0.5 - margin_px) and (
                margin_px - 0.5 <= v <= height - 0.5 - margin_px
            )
    got = in_view(points, K, dist, width, height, margin_px=margin_px)
    assert 100 < expected.sum() < len(points) - 100
    assert np.array_equal(got, expected)
