"""The closed-form circle pose, cross-checked against independent formulations: the projected
sampled 3-D circle (points, not conics) and the basis-free cone of a circle."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimators.circle_pose import CirclePose, circle_poses_from_conic, cone_from_conic
from estimators.conics import (
    circle_cone,
    circle_image_conic,
    circle_points,
    conic_residuals,
    fit_ellipse_direct,
    normalize_conic,
)
from estimators.geometry import intrinsics_from_fov, project

K = intrinsics_from_fov(640, 480, 70.0)


def _random_circle(rng: np.random.Generator):
    center = np.array([rng.uniform(-0.6, 0.6), rng.uniform(-0.4, 0.4), rng.uniform(0.6, 4.0)])
    normal = np.array([rng.uniform(-0.8, 0.8), rng.uniform(-0.8, 0.8), -1.0])
    normal /= np.linalg.norm(normal)
    return center, normal, rng.uniform(0.05, 0.4)


def test_circle_poses_from_conic_recover_the_circle_from_projected_points():
    """Forward model independent of conics: project sampled 3-D circle points, fit a conic
    through them, and recover centre and normal (one of the two candidates)."""
    rng = np.random.default_rng(7)
    checked = 0
    for _ in range(300):
        center, normal, radius = _random_circle(rng)
        points_C = circle_points(center, normal, radius, 180)
        if np.any(points_C[:, 2] < 0.2):
            continue
        Q = fit_ellipse_direct(project(points_C, K))
        poses = circle_poses_from_conic(Q, radius, K)
        errors = [
            np.linalg.norm(p.center_C - center) + np.linalg.norm(p.normal_C - normal) for p in poses
        ]
        assert min(errors) < 1e-6, (center, normal, radius)
        for p in poses:
            # Every candidate is a circle of the right radius whose rim projects onto the conic.
            rim = project(circle_points(p.center_C, p.normal_C, radius, 36), K)
            assert np.abs(conic_residuals(Q, rim)).max() < 1e-9
            assert p.normal_C @ p.center_C < 0  # the normal faces the camera
        checked += 1
    assert checked > 200


def test_circle_poses_from_conic_head_on_degenerate_case():
    """Head on, the cone is circular (λ1 = λ2): both candidates coincide with the truth. (The
    normal depends on √(λ1 − λ2), so rounding of 1e-16 in the eigenvalues shows as ~1e-8.)"""
    for distance, radius in ((0.5, 0.3), (3.0, 0.3), (2.0, 0.05)):
        Q = circle_image_conic(np.array([0.0, 0.0, distance]), np.array([0, 0, -1.0]), radius, K)
        poses = circle_poses_from_conic(Q, radius, K)
        assert len(poses) == 2
        for p in poses:
            assert p.center_C == pytest.approx([0.0, 0.0, distance], abs=1e-7)
            assert p.normal_C == pytest.approx([0.0, 0.0, -1.0], abs=1e-7)


def test_circle_poses_from_conic_nearly_head_on_stays_continuous():
    """Tilts of 1e-5 … 1e-2 rad: the recovered tilt follows the true one (no blow-up next to
    the degenerate case)."""
    for tilt in (1e-5, 1e-4, 1e-3, 1e-2):
        normal = np.array([np.sin(tilt), 0.0, -np.cos(tilt)])
        Q = circle_image_conic(np.array([0.0, 0.0, 2.0]), normal, 0.3, K)
        best = min(
            circle_poses_from_conic(Q, 0.3, K), key=lambda p: np.linalg.norm(p.normal_C - normal)
        )
        assert best.normal_C == pytest.approx(normal, abs=1e-6)


@given(
    st.floats(-0.5, 0.5),
    st.floats(-0.4, 0.4),
    st.floats(0.7, 5.0),
    st.floats(-0.7, 0.7),
    st.floats(-0.7, 0.7),
    st.floats(0.05, 0.5),
)
@settings(max_examples=150, deadline=None)
def test_circle_cone_equals_the_homography_conic(x, y, z, tx, ty, radius):
    center = np.array([x, y, z])
    normal = np.array([np.sin(ty), np.sin(tx), -1.0])
    normal /= np.linalg.norm(normal)
    K_inv = np.linalg.inv(K)
    from_cone = normalize_conic(K_inv.T @ circle_cone(center, normal, radius) @ K_inv)
    assert from_cone == pytest.approx(circle_image_conic(center, normal, radius, K), abs=1e-9)


def test_cone_from_conic_contains_the_circle_rays():
    rng = np.random.default_rng(3)
    center, normal, radius = _random_circle(rng)
    A = cone_from_conic(circle_image_conic(center, normal, radius, K), K)
    rays = circle_points(center, normal, radius, 24)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    assert np.abs(np.einsum("ni,ij,nj->n", rays, A, rays)).max() < 1e-9


def test_circle_poses_from_conic_rejects_bad_input():
    Q = circle_image_conic(np.array([0.0, 0.0, 2.0]), np.array([0, 0, -1.0]), 0.3, K)
    with pytest.raises(ValueError, match="radius"):
        circle_poses_from_conic(Q, 0.0, K)
    with pytest.raises(ValueError, match="not elliptical"):
        circle_poses_from_conic(np.diag([1.0, 1.0, 1.0]), 0.3, K)
    with pytest.raises(ValueError, match="non-finite"):
        CirclePose(np.array([np.nan, 0, 1]), np.array([0, 0, 1.0]))
