import math

import numpy as np

from configuration.camera import load_camera
from configuration.mockup import load_mockup
from configuration.render import Lighting
from estimators.planar_pose import EdgeObservations, project_ideal, refine_pose
from estimators.so3 import pose_error_C
from estimators.target import facing_camera
from hil.evaluation.feature_bounds import (
    expected_mean_errors,
    feature_bound,
    panel_edge_information,
)


def test_panel_edge_bound_matches_a_monte_carlo_of_edge_points():
    camera = load_camera("reference").camera_info()
    mockup = load_mockup("default")
    X_CT = facing_camera(1.2).inverse()
    information = panel_edge_information(X_CT, camera, mockup, 0.22, Lighting())
    bound = np.linalg.inv(information)
    # Simulate what the bound assumes: a point per pixel of edge, σ/Δ across it.
    corners = mockup.target_model().panel_corners_T
    ends = np.stack([corners, np.roll(corners, -1, axis=0)], axis=1)
    contrast = 0.63 - 0.352  # panel and bus face greys under the default lighting
    rng = np.random.default_rng(0)
    errors = []
    for _ in range(150):
        uv, edge = [], []
        for i, (a, b) in enumerate(ends):
            a_uv, b_uv = project_ideal(X_CT, np.array([a, b]), camera.K)
            count = int(np.linalg.norm(b_uv - a_uv))
            t = (np.arange(count) + 0.5) / count
            points = project_ideal(X_CT, a + t[:, None] * (b - a), camera.K)
            normal = np.array([-(b_uv - a_uv)[1], (b_uv - a_uv)[0]]) / np.linalg.norm(b_uv - a_uv)
            uv.append(points + rng.normal(0, 0.22 / contrast, (count, 1)) * normal)
            edge.append(np.full(count, i))
        uv = np.concatenate(uv)
        obs = EdgeObservations(ends, np.concatenate(edge), uv, np.full(len(uv), 0.22 / contrast))
        fit = refine_pose([obs], X_CT, camera.K)
        errors.append(pose_error_C(X_CT, fit.X_CT))
    empirical = np.cov(np.array(errors).T)
    ratio = np.sqrt(np.diag(empirical) / np.diag(bound))
    assert np.all((ratio > 0.75) & (ratio < 1.3))


def test_feature_bounds_order_the_systems():
    _, lines_t, lines_r = feature_bound("lines", "low", 2.0)
    _, outline_t, outline_r = feature_bound("lines + bus-face outline", "low", 2.0)
    _, corners_t, corners_r = feature_bound("corners", "low", 2.0)
    # The panel alone fixes its tilt only to degrees; more, longer edges or spread-out discs
    # do far better.
    assert lines_r > math.radians(1.5)
    assert outline_r < lines_r / 10 and corners_r < lines_r / 10
    assert outline_t < lines_t
    assert corners_t < lines_t
    _, high_t, high_r = feature_bound("lines", "high", 2.0)
    assert high_r > lines_r and high_t > lines_t  # more noise, a looser bound


def test_expected_mean_errors_of_an_isotropic_gaussian():
    covariance = np.diag([1e-4, 1e-4, 1e-4, 1e-6, 1e-6, 1e-6])
    position, rotation = expected_mean_errors(covariance, samples=40000)
    # Mean norm of a 3-D Gaussian of σ per axis is σ·2√(2/π) ≈ 1.596σ.
    assert abs(position - 1.596e-3) < 2e-5
    assert abs(rotation - 1.596e-2) < 3e-4
