"""CameraInfo and Frame: validation, view masks, and what makes a frame unusable."""

import numpy as np
import pytest

from configuration.camera import load_camera
from estimators.frame import CameraInfo, Frame, frame_problem
from estimators.geometry import intrinsics_from_fov, undistort_pixels
from estimators.planar_pose import ideal_pixels

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


def test_camera_info_key_is_the_content_not_the_name():
    same = CameraInfo(640, 480, INFO.K.copy(), np.zeros(0), "another name")
    assert same.key == INFO.key and hash(same.key) == hash(INFO.key)
    moved = INFO.K.copy()
    moved[0, 2] += 1e-6
    assert CameraInfo(640, 480, moved, np.zeros(0), "reference").key != INFO.key
    assert CameraInfo(640, 480, INFO.K, np.zeros(0), "reference", channels=3).key != INFO.key
    tilted = CameraInfo(640, 480, INFO.K, np.r_[np.zeros(12), 0.01, 0.0], "reference")
    assert tilted.key != INFO.key and tilted.dist.shape == (14,)


def test_ideal_pixels_imaged_by_a_distorting_camera_and_back():
    """``image_of_ideal`` applies the lens that ``ideal_pixels`` removes: a round trip returns
    the ideal pixels, and the OAK's lens moves its corners by pixels."""
    camera = load_camera("oak_d_rgb").camera_info()
    uv_ideal = np.array([[10.0, 20.0], [640.0, 400.0], [1250.0, 780.0]])
    imaged = camera.image_of_ideal(uv_ideal)
    assert np.abs(imaged[[0, 2]] - uv_ideal[[0, 2]]).min() > 3.0
    np.testing.assert_allclose(ideal_pixels(imaged, camera.K, camera.dist), uv_ideal, atol=1e-6)
    np.testing.assert_allclose(INFO.image_of_ideal(uv_ideal), uv_ideal, atol=1e-9)


def test_whole_pixels_are_undistorted_from_the_cameras_grid_to_the_bit():
    camera = load_camera("oak_d_rgb").camera_info()
    rng = np.random.default_rng(3)
    whole = np.column_stack(
        [rng.integers(0, camera.width, 500), rng.integers(0, camera.height, 500)]
    ).astype(float)
    grid = camera.undistorted_grid()
    assert camera.undistorted_grid() is grid  # built once
    assert grid.shape == (camera.height, camera.width, 2)
    np.testing.assert_array_equal(
        camera.undistort(whole), undistort_pixels(whole, camera.K, camera.dist)
    )
    # Sub-pixel points and points off the image are computed, not looked up.
    for points in (whole + 0.25, whole - [camera.width, 0]):
        np.testing.assert_array_equal(
            camera.undistort(points), undistort_pixels(points, camera.K, camera.dist)
        )
    corner = camera.undistort(np.array([[0.0, 0.0]]))[0]
    assert np.linalg.norm(corner - grid[0, 0]) == 0.0 and abs(corner[0]) > 0.5


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
