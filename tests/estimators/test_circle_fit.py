"""Least-squares circle and target poses from edge points: recovery of the truth, robustness
to outliers, nuisance radii, and the covariance against Monte-Carlo scatter."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from configuration.mockup import load_mockup
from estimators.circle_fit import (
    CircleProblem,
    ConicObservations,
    EdgeSet,
    covariance_at,
    fit_circle_pose,
    fit_target_pose,
    pose_response,
    stacked_displacements,
)
from estimators.circle_pose import CirclePose
from estimators.conics import circle_plane_basis, circle_points
from estimators.geometry import Pose, intrinsics_from_fov, normal_angle, project
from estimators.planar_pose import PointObservations
from hil.evaluation.scenarios import camera_pose_for, target_offset

K = intrinsics_from_fov(640, 480, 70.0)
TARGET = load_mockup("default").target_model()
X_TRUE = Pose.from_rpy(np.pi + 0.12, -0.08, 0.3, np.array([0.05, -0.03, 1.6]))


def edge_points(circle, X_CT, n, noise_px, rng, scale_radius=1.0):
    rim = circle_points(circle.center_T, circle.normal_T, circle.radius * scale_radius, n)
    uv = project(X_CT.apply(rim), K)
    return uv + noise_px * rng.standard_normal(uv.shape)


def test_fit_circle_pose_recovers_ring_from_a_perturbed_start():
    rng = np.random.default_rng(0)
    outer, inner = TARGET.circle("ring_outer"), TARGET.circle("ring_inner")
    sets = [
        EdgeSet(outer, edge_points(outer, X_TRUE, 200, 0.3, rng)),
        EdgeSet(inner, edge_points(inner, X_TRUE, 160, 0.3, rng)),
    ]
    start = CirclePose(X_TRUE.p + [0.03, -0.02, 0.1], X_TRUE.R @ [0.05, 0.03, 1.0])
    fit = fit_circle_pose(sets, start, outer, K)
    assert np.linalg.norm(fit.pose.center_C - X_TRUE.p) < 2e-3
    assert np.degrees(normal_angle(fit.pose.normal_C, X_TRUE.R[:, 2])) < 0.5
    assert fit.covariance.shape == (5, 5) and np.all(np.linalg.eigvalsh(fit.covariance) > 0)
    assert fit.sigma_px == pytest.approx((0.3, 0.3), rel=0.25)


def test_pose_response_predicts_the_refit_after_a_systematic_edge_displacement():
    """``pose_response`` is the fit's linear response: noise-free ring edges pushed outward on
    one side (as an unresolved wall would), refitted, move the 5-DOF pose as predicted. (The
    push stays within the Huber loss's quadratic zone, whose noise floor is 0.05 px.)"""
    rng = np.random.default_rng(2)
    outer, inner = TARGET.circle("ring_outer"), TARGET.circle("ring_inner")
    clean = [edge_points(outer, X_TRUE, 240, 0.0, rng), edge_points(inner, X_TRUE, 200, 0.0, rng)]
    truth = CirclePose(X_TRUE.p, X_TRUE.R[:, 2])
    sets = [EdgeSet(outer, clean[0]), EdgeSet(inner, clean[1], free_radius=True)]
    fit = fit_circle_pose(sets, truth, outer, K)
    # Outer samples right of the ring's image centre, pushed 0.03 px away from it.
    centre = project(X_TRUE.p[None], K)[0]
    away = clean[0] - centre
    side = away[:, 0] > 0
    moved = clean[0] + np.where(side, 0.03, 0.0)[:, None] * away / np.linalg.norm(
        away, axis=1, keepdims=True
    )
    problem = CircleProblem(ConicObservations((EdgeSet(outer, clean[0]),), K), outer)
    state = problem.state(truth.center_C, truth.normal_C)
    before = problem.residuals(state)[0]
    problem_moved = CircleProblem(ConicObservations((EdgeSet(outer, moved),), K), outer)
    displacement = problem_moved.residuals(state)[0] - before
    assert np.all(np.abs(displacement[~side]) < 1e-9) and np.all(np.abs(displacement[side]) > 0.02)

    response = pose_response(sets, fit, fit.pose, K, reference=outer)
    predicted = response @ stacked_displacements(response, [displacement, np.zeros(len(clean[1]))])
    refit = fit_circle_pose([EdgeSet(outer, moved), sets[1]], fit.pose, outer, K)
    u, v = circle_plane_basis(fit.pose.normal_C)
    dn = refit.pose.normal_C - fit.pose.normal_C
    actual = np.concatenate([refit.pose.center_C - fit.pose.center_C, [dn @ u, dn @ v]])
    assert np.linalg.norm(actual[:3]) > 1e-4  # (the push moves the ring measurably)
    np.testing.assert_allclose(predicted, actual, rtol=0.05, atol=2e-6)


def test_fit_target_pose_recovers_six_dof_and_ignores_outliers():
    rng = np.random.default_rng(1)
    names = ("ring_outer", "ring_inner", "thruster_inner")
    sets = []
    for name in names:
        circle = TARGET.circle(name)
        uv = edge_points(circle, X_TRUE, 120, 0.2, rng)
        uv[::10] += rng.uniform(-15, 15, uv[::10].shape)  # 10 % gross outliers
        sets.append(EdgeSet(circle, uv, free_radius=name != "ring_outer"))
    start = Pose.from_rotvec(X_TRUE.rotvec + [0.02, -0.03, 0.1], X_TRUE.p + [0.02, 0.01, 0.05])
    fit = fit_target_pose(sets, start, K)
    assert np.linalg.norm(fit.pose.p - X_TRUE.p) < 2e-3
    assert np.degrees(np.linalg.norm(fit.pose.R.T @ X_TRUE.R - np.eye(3))) < 1.0
    assert all(abs(r) < 2e-3 for r in fit.radius_offsets)
    for residuals, inliers in zip(fit.residuals, fit.inliers, strict=True):
        assert inliers.sum() >= 0.85 * len(residuals)


def test_fit_target_pose_free_radius_absorbs_a_biased_size():
    """The thruster's edge found 4 % inside its true radius (a lip blurred into it): with a
    free radius the pose is unbiased, with the radius fixed it is pulled off."""
    rng = np.random.default_rng(2)
    ring, thruster = TARGET.circle("ring_outer"), TARGET.circle("thruster_inner")
    ring_uv = edge_points(ring, X_TRUE, 200, 0.02, rng)
    thruster_uv = edge_points(thruster, X_TRUE, 60, 0.02, rng, scale_radius=0.96)
    errors = {}
    for free in (True, False):
        fit = fit_target_pose(
            [EdgeSet(ring, ring_uv), EdgeSet(thruster, thruster_uv, free_radius=free)], X_TRUE, K
        )
        errors[free] = np.degrees(normal_angle(fit.pose.R[:, 2], X_TRUE.R[:, 2]))
    assert errors[True] < 0.1 and errors[False] > 3.0 * errors[True], errors


def test_fit_circle_pose_covariance_matches_monte_carlo_scatter():
    """Independent Gaussian edge noise: the covariance predicts the scatter of the estimates
    (mean NEES ≈ 5 for the five parameters)."""
    outer, inner = TARGET.circle("ring_outer"), TARGET.circle("ring_inner")
    truth = CirclePose(X_TRUE.p, X_TRUE.R[:, 2])
    nees = []
    for seed in range(40):
        rng = np.random.default_rng(100 + seed)
        sets = [
            EdgeSet(outer, edge_points(outer, X_TRUE, 150, 0.5, rng)),
            EdgeSet(inner, edge_points(inner, X_TRUE, 120, 0.5, rng)),
        ]
        fit = fit_circle_pose(sets, truth, outer, K)
        u, v = circle_plane_basis(fit.pose.normal_C)
        dn = truth.normal_C - fit.pose.normal_C
        e = np.concatenate([truth.center_C - fit.pose.center_C, [dn @ u, dn @ v]])
        nees.append(e @ np.linalg.solve(fit.covariance, e))
    assert 3.5 < np.mean(nees) < 7.0


def test_fit_circle_pose_rejects_off_axis_circles():
    outer = TARGET.circle("ring_outer")
    thruster = TARGET.circle("thruster_exit")
    with pytest.raises(ValueError, match="not coaxial"):
        fit_circle_pose(
            [EdgeSet(thruster, np.zeros((10, 2)))],
            CirclePose(X_TRUE.p, X_TRUE.R[:, 2]),
            outer,
            K,
        )


def _ring_holes_T() -> np.ndarray:
    return np.array([f.p_T for f in TARGET.point_features if f.name.startswith("ring_bolt")])


def test_fit_target_pose_with_labeled_points_fixes_the_weak_tilt_axis():
    """Head-on at 3 m, the ring and the thruster's edges leave the tilt about the line through
    them weak; eight labeled holes (0.15 px) move to first order with it. Monte Carlo: the
    joint fit's normal error is several times smaller, its covariance predicts its scatter
    (NEES ≈ 6), and ``covariance_at`` at the solution gives the fit's own covariance."""
    _, X = camera_pose_for(3.0, target_offset())
    ring, thruster = TARGET.circle("ring_outer"), TARGET.circle("thruster_inner")
    holes_T = _ring_holes_T()
    errors = {False: [], True: []}
    nees = []
    for seed in range(30):
        rng = np.random.default_rng(300 + seed)
        sets = [
            EdgeSet(ring, edge_points(ring, X, 140, 0.5, rng)),
            EdgeSet(thruster, edge_points(thruster, X, 40, 0.5, rng), free_radius=True),
        ]
        uv = project(X.apply(holes_T), K) + 0.15 * rng.standard_normal((len(holes_T), 2))
        points = PointObservations(holes_T, uv, np.tile(0.15**2 * np.eye(2), (len(uv), 1, 1)))
        for with_points in (False, True):
            fit = fit_target_pose(sets, X, K, points=points if with_points else None)
            errors[with_points].append(np.degrees(normal_angle(fit.pose.R[:, 2], X.R[:, 2])))
        rotation = Rotation.from_matrix(X.R @ fit.pose.R.T).as_rotvec()
        e = np.concatenate([rotation, X.p - fit.pose.p])
        nees.append(e @ np.linalg.solve(fit.covariance, e))
        assert fit.point_residuals.shape == (2 * len(holes_T),) and fit.point_sigma >= 1.0
    assert np.mean(errors[True]) < 0.3 * np.mean(errors[False]), errors
    assert np.mean(errors[True]) < 1.2
    assert 3.5 < np.mean(nees) < 9.0, nees
    again = covariance_at(sets, fit, fit.pose, K, points=points)
    scale = 1.0 / np.sqrt(np.diag(fit.covariance))  # (the fit's Huber weights differ a little)
    assert np.abs(scale[:, None] * (again - fit.covariance) * scale).max() < 0.1


def test_edge_weight_scales_information_but_not_the_estimate():
    """Edge samples that are not independent carry less information: an ``edge_weight`` of
    ¼ leaves an edge-only estimate where it was and quadruples its covariance."""
    rng = np.random.default_rng(7)
    ring, thruster = TARGET.circle("ring_outer"), TARGET.circle("thruster_inner")
    sets = [
        EdgeSet(ring, edge_points(ring, X_TRUE, 150, 0.3, rng)),
        EdgeSet(thruster, edge_points(thruster, X_TRUE, 50, 0.3, rng), free_radius=True),
    ]
    start = Pose.from_rotvec(X_TRUE.rotvec + [0.01, -0.01, 0.02], X_TRUE.p + [0.01, 0.0, 0.02])
    full = fit_target_pose(sets, start, K, iterations=10)
    quarter = fit_target_pose(sets, start, K, iterations=10, edge_weight=0.25)
    assert np.allclose(full.pose.p, quarter.pose.p, atol=1e-5)
    assert np.allclose(quarter.covariance, 4.0 * full.covariance, rtol=1e-3)
