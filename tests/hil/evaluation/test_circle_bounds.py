"""The edge-fit Cramér–Rao bound: scales as it must, and says which edges carry the tilt."""

import numpy as np
import pytest

from configuration.mockup import load_mockup
from estimators.geometry import intrinsics_from_fov
from hil.evaluation.circle_bounds import tilt_bounds
from hil.evaluation.scenarios import camera_pose_for, target_offset

TARGET = load_mockup("default").target_model()
K = intrinsics_from_fov(640, 480, 70.0)


def test_tilt_bounds_scale_with_noise_and_distance():
    _, X_far = camera_pose_for(3.0, target_offset())
    _, X_near = camera_pose_for(1.2, target_offset())
    circles = ("ring_outer", "thruster_inner")
    far, center_far = tilt_bounds(TARGET, K, X_far, circles, free_radius=("thruster_inner",))
    doubled, _ = tilt_bounds(
        TARGET, K, X_far, circles, free_radius=("thruster_inner",), sigma_px=1.0
    )
    near, center_near = tilt_bounds(TARGET, K, X_near, circles, free_radius=("thruster_inner",))
    assert doubled == pytest.approx(2 * far, rel=1e-6)
    assert np.all(near < far) and center_near < center_far
    assert far[0] > 5 * far[1]  # near head-on, one tilt axis is much weaker than the other


def test_tilt_bounds_concentric_edge_strengthens_the_weak_axis():
    _, X = camera_pose_for(2.0, target_offset())
    without, _ = tilt_bounds(TARGET, K, X, ("ring_outer", "thruster_inner"))
    with_inner, _ = tilt_bounds(TARGET, K, X, ("ring_outer", "ring_inner", "thruster_inner"))
    assert with_inner[0] < 0.5 * without[0]
