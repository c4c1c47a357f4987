import math

import numpy as np

from estimators.frame import CameraInfo
from estimators.geometry import Pose
from estimators.model_view import outside_circles, plane_coordinates


def test_outside_circles_keeps_points_clear_of_every_circle_and_within_reach():
    points = np.array(
        [
            [0.0, 0.0],  # inside the first circle
            [1.05, 0.0],  # just outside it
            [3.0, 3.0],  # inside the second
            [-2.0, 0.5],  # clear of both
            [4.0, -4.0],  # clear of both, beyond reach
            [math.nan, 0.0],  # a ray that missed the plane
        ]
    )
    centres = np.array([[0.0, 0.0], [3.0, 2.5]])
    radii = np.array([1.0, 0.6])
    kept = outside_circles(points, centres, radii, within=5.0)
    assert kept.tolist() == [False, True, False, True, False, False]
    # Without a reach, only the circles (and finiteness) decide; without circles, only the reach.
    assert outside_circles(points, centres, radii).tolist() == [
        False,
        True,
        False,
        True,
        True,
        False,
    ]
    no_circles = outside_circles(points, np.zeros((0, 2)), np.zeros(0), within=2.5)
    assert no_circles.tolist() == [True, True, False, True, False, False]


def test_outside_circles_agrees_with_the_distances_it_replaces():
    rng = np.random.default_rng(3)
    points = rng.uniform(-1.0, 1.0, (500, 2))
    centres = rng.uniform(-1.0, 1.0, (12, 2))
    radii = rng.uniform(0.02, 0.2, 12)
    gap = np.hypot(points[:, None, 0] - centres[:, 0], points[:, None, 1] - centres[:, 1])
    expected = np.all(gap > radii, axis=1) & (np.hypot(points[:, 0], points[:, 1]) < 0.9)
    assert np.array_equal(outside_circles(points, centres, radii, within=0.9), expected)


def test_plane_coordinates_meet_the_plane_where_the_pixels_look():
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    camera = CameraInfo(640, 480, K, np.zeros(0), "pinhole")
    X_CT = Pose(np.eye(3), np.array([0.1, -0.05, 2.0]))
    xy_T = np.array([[0.0, 0.0], [0.2, -0.1], [-0.3, 0.25]])
    on_plane = np.column_stack([xy_T, np.full(3, 0.01)])
    uv = camera.project(X_CT.apply(on_plane))
    assert np.allclose(plane_coordinates(uv, X_CT, camera, 0.01), xy_T, atol=1e-12)
