import math

import numpy as np
import pytest

from configuration.camera import load_camera
from configuration.mockup import load_mockup
from estimators.geometry import Pose, rotation_error_geodesic, translation_error
from estimators.planar_pose import (
    CorrelatedEdgeObservations,
    EdgeObservations,
    PointObservations,
    against_flip,
    choose_pose,
    fit_from_starts,
    ideal_pixels,
    ippe_poses,
    orthogonal_iteration,
    planar_flip,
    profile_widened,
    project_ideal,
    refine_pose,
    refine_pose_robust,
    retract,
    weak_perspective_flip,
    with_min_scale2,
)
from estimators.so3 import pose_error_C

CAMERA = load_camera("reference").camera_info()
K = CAMERA.K
TARGET = load_mockup("default").target_model()
POINTS_T = TARGET.points_T()  # panel corners and discs: near-planar, 6 cm deep
# A generic pose: facing the camera from 2 m, tilted and turned a little.
X_TRUE = Pose.from_rpy(
    math.radians(172), math.radians(-7), math.radians(14), np.array([0.06, -0.04, 2.0])
)


def _isotropic(n: int, sigma: float) -> np.ndarray:
    return np.tile(np.eye(2) * sigma**2, (n, 1, 1))


def _panel_edges():
    corners = TARGET.panel_corners_T
    return np.stack([corners, np.roll(corners, -1, axis=0)], axis=1)


def test_refine_pose_converges_to_truth_without_noise():
    uv = project_ideal(X_TRUE, POINTS_T, K)
    obs = PointObservations(POINTS_T, uv, _isotropic(len(uv), 0.2))
    start = retract(X_TRUE, np.array([0.05, -0.04, 0.03, 0.03, -0.02, 0.15]))
    fit = refine_pose([obs], start, K)
    assert fit.converged
    assert translation_error(X_TRUE, fit.X_CT) < 1e-9
    assert rotation_error_geodesic(X_TRUE, fit.X_CT) < 1e-10
    assert fit.rms_px < 1e-8


def test_refine_pose_covariance_is_calibrated_by_monte_carlo():
    rng = np.random.default_rng(3)
    sigma = 0.3
    uv = project_ideal(X_TRUE, POINTS_T, K)
    nees, errors = [], []
    for _ in range(300):
        measured = uv + rng.normal(0.0, sigma, uv.shape)
        obs = PointObservations(POINTS_T, measured, _isotropic(len(uv), sigma))
        fit = refine_pose([obs], X_TRUE, K)
        delta = pose_error_C(X_TRUE, fit.X_CT)
        nees.append(delta @ np.linalg.solve(fit.covariance, delta))
        errors.append(delta)
    # Mean NEES of a 6-DOF estimate with an honest covariance is 6 (± ~0.35 for 300 trials).
    assert 5.0 < np.mean(nees) < 7.2
    assert np.all(np.abs(np.mean(errors, axis=0)) < 3 * np.std(errors, axis=0) / math.sqrt(300))


def _nees(delta: np.ndarray, covariance: np.ndarray) -> float:
    return float(delta @ np.linalg.solve(covariance, delta))


def test_profile_widened_covers_the_tilt_of_a_panel_seen_square_on_from_afar():
    # Four corners of a 0.3 m panel, square-on at 3 m, 1 px noise: the tilt's χ² valley is
    # flat and bent, and the covariance at the minimum leaves over a quarter of the errors
    # beyond its 99 % bound (χ²₆ 16.8); the profile-widened one holds them.
    corners = TARGET.panel_corners_T
    X_square_on = Pose.from_rpy(math.pi, 0.0, 0.0, np.array([0.0, 0.0, 3.0]))
    uv = project_ideal(X_square_on, corners, K)
    rng = np.random.default_rng(1)
    raw, widened = [], []
    for _ in range(150):
        measured = uv + rng.normal(0.0, 1.0, uv.shape)
        obs = PointObservations(corners, measured, _isotropic(4, 1.0))
        fit = refine_pose([obs], X_square_on, K, min_scale2=1.0)
        delta = pose_error_C(X_square_on, fit.X_CT)
        raw.append(_nees(delta, fit.covariance))
        widened.append(_nees(delta, profile_widened([obs], fit, K).covariance))
    raw, widened = np.array(raw), np.array(widened)
    assert np.mean(raw > 16.8) > 0.15
    assert np.mean(widened > 16.8) <= 0.02
    assert 3.0 < np.mean(widened) < 7.0


def test_profile_widened_leaves_a_well_conditioned_covariance_as_it_is():
    rng = np.random.default_rng(3)
    sigma = 0.3
    uv = project_ideal(X_TRUE, POINTS_T, K)
    for _ in range(20):
        measured = uv + rng.normal(0.0, sigma, uv.shape)
        obs = PointObservations(POINTS_T, measured, _isotropic(len(uv), sigma))
        fit = refine_pose([obs], X_TRUE, K)
        covariance = profile_widened([obs], fit, K).covariance
        ratio = np.sqrt(np.diag(covariance) / np.diag(fit.covariance))
        assert np.all(ratio >= 1.0 - 1e-12)
        assert np.all(ratio < 1.02)


def test_with_min_scale2_widens_a_lucky_fit_and_leaves_the_others():
    uv = project_ideal(X_TRUE, POINTS_T, K)
    obs = PointObservations(POINTS_T, uv, _isotropic(len(uv), 0.5))
    lucky = refine_pose([obs], X_TRUE, K)  # noise-free: χ²/dof ≈ 0
    floored = with_min_scale2(lucky, 1.0)
    assert floored.scale2 == 1.0
    np.testing.assert_allclose(floored.covariance, lucky.unit_covariance, rtol=1e-9)
    assert with_min_scale2(floored, 0.5) is floored


def test_edge_observations_jacobian_matches_finite_differences():
    ends = _panel_edges()
    t = np.linspace(0.1, 0.9, 7)
    points = np.concatenate([a + t[:, None] * (b - a) for a, b in ends])
    edge = np.repeat(np.arange(4), len(t))
    uv = project_ideal(X_TRUE, points, K) + np.random.default_rng(0).normal(
        0, 0.4, (len(points), 2)
    )
    obs = EdgeObservations(ends, edge, uv, np.full(len(uv), 0.5))
    _, _, J = obs.linearize(X_TRUE, K)
    numeric = np.zeros_like(J)
    for j in range(6):
        step = np.zeros(6)
        step[j] = 1e-7
        plus = obs.linearize(retract(X_TRUE, step), K)[1]
        minus = obs.linearize(retract(X_TRUE, -step), K)[1]
        numeric[:, j] = (plus - minus) / 2e-7
    assert np.allclose(J, numeric, rtol=1e-5, atol=1e-4 * np.abs(J).max())


def test_edge_observations_give_the_pose_from_points_anywhere_on_the_edges():
    ends = _panel_edges()
    rng = np.random.default_rng(1)
    t = rng.uniform(0.1, 0.9, (4, 15))
    points = np.concatenate([a + t[i][:, None] * (b - a) for i, (a, b) in enumerate(ends)])
    uv = project_ideal(X_TRUE, points, K)
    obs = EdgeObservations(ends, np.repeat(np.arange(4), 15), uv, np.full(len(uv), 0.3))
    start = retract(X_TRUE, np.array([0.01, -0.01, 0.02, 0.01, 0.01, 0.03]))
    fit = refine_pose([obs], start, K)
    assert translation_error(X_TRUE, fit.X_CT) < 1e-7
    assert fit.rms_px < 1e-6


def test_ippe_poses_contain_the_true_planar_pose():
    corners = TARGET.panel_corners_T
    poses = ippe_poses(corners, project_ideal(X_TRUE, corners, K), K)
    assert len(poses) == 2
    best = min(poses, key=lambda X: rotation_error_geodesic(X_TRUE, X))
    assert rotation_error_geodesic(X_TRUE, best) < 1e-6
    assert translation_error(X_TRUE, best) < 1e-6
    # The other is the planar flip: a different tilt, nearly the same image of the corners.
    other = max(poses, key=lambda X: rotation_error_geodesic(X_TRUE, X))
    assert rotation_error_geodesic(X_TRUE, other) > math.radians(5)
    reprojected = project_ideal(other, corners, K) - project_ideal(X_TRUE, corners, K)
    assert np.abs(reprojected).max() < 2.0  # nearly the same image: hard to tell apart


def test_orthogonal_iteration_matches_gauss_newton():
    rng = np.random.default_rng(5)
    uv = project_ideal(X_TRUE, POINTS_T, K)
    exact = ideal_pixels(uv, K, None)
    xy = np.column_stack([(exact[:, 0] - K[0, 2]) / K[0, 0], (exact[:, 1] - K[1, 2]) / K[1, 1]])
    start = retract(X_TRUE, np.array([0.1, -0.1, 0.2, 0, 0, 0]))
    X, iterations = orthogonal_iteration(POINTS_T, xy, start.R)
    assert iterations > 1
    assert rotation_error_geodesic(X_TRUE, X) < 1e-6
    noisy = PointObservations(POINTS_T, uv + rng.normal(0, 0.3, uv.shape), _isotropic(len(uv), 0.3))
    lhm = fit_from_starts([noisy], [start], K, method="lhm")[0]
    gn = fit_from_starts([noisy], [start], K, method="gauss_newton")[0]
    assert lhm.method == "lhm"
    assert rotation_error_geodesic(lhm.X_CT, gn.X_CT) < math.radians(0.3)
    assert translation_error(lhm.X_CT, gn.X_CT) < 0.005
    assert lhm.chi2 >= gn.chi2 - 1e-9  # GN minimises the image error LHM only approximates


def test_refine_pose_robust_shrugs_off_wrong_correspondences():
    rng = np.random.default_rng(2)
    uv = project_ideal(X_TRUE, POINTS_T, K) + rng.normal(0, 0.2, (len(POINTS_T), 2))
    uv[[3, 7, 11, 15]] += rng.uniform(8, 15, (4, 2))  # four wrong labels
    obs = PointObservations(POINTS_T, uv, _isotropic(len(uv), 0.2))
    X, chi2 = refine_pose_robust(obs, retract(X_TRUE, np.full(6, 0.01)), K)
    assert rotation_error_geodesic(X_TRUE, X) < math.radians(0.3)
    assert set(np.flatnonzero(chi2 > 16)) == {3, 7, 11, 15}


def test_choose_pose_decides_by_residual_then_prior():
    # A panel tilted 15° at 3 m seen through its four corners at σ = 1 px: its planar flip,
    # 25° away, fits them almost as well — the residuals cannot decide.
    X_tilted = Pose.from_rpy(
        math.radians(165), math.radians(3), math.radians(10), np.array([0.1, 0.05, 3.0])
    )
    corners = TARGET.panel_corners_T
    uv = project_ideal(X_tilted, corners, K)
    obs = PointObservations(corners, uv, _isotropic(4, 1.0))
    fits = fit_from_starts([obs], ippe_poses(corners, uv, K), K)
    assert len(fits) == 2
    assert rotation_error_geodesic(fits[0].X_CT, fits[1].X_CT) > math.radians(20)
    choice = choose_pose(fits)
    assert choice.ambiguous and choice.decided_by == "lower_residual"
    # The prior picks: the one nearest to it.
    for prior in (fits[0].X_CT, fits[1].X_CT):
        chosen = choose_pose(fits, prior)
        assert chosen.decided_by == "prior"
        assert rotation_error_geodesic(prior, chosen.fit.X_CT) < math.radians(1)
    # Precise corners make the flip's residual decisive.
    precise = PointObservations(corners, uv, _isotropic(4, 0.3))
    decided = choose_pose(fit_from_starts([precise], ippe_poses(corners, uv, K), K))
    assert decided.decided_by == "residual"
    assert rotation_error_geodesic(X_tilted, decided.fit.X_CT) < 1e-6
    # So do the mock-up's features off the panel's plane (ring 6 cm in front of the bus face),
    # even at σ = 1 px, from both flips as starts.
    all_uv = project_ideal(X_tilted, POINTS_T, K)
    all_obs = PointObservations(POINTS_T, all_uv, _isotropic(len(POINTS_T), 1.0))
    both = choose_pose(fit_from_starts([all_obs], [fits[0].X_CT, fits[1].X_CT], K))
    assert not both.ambiguous
    assert rotation_error_geodesic(X_tilted, both.fit.X_CT) < 1e-6


def test_weak_perspective_flip_is_the_other_ippe_pose_as_a_start():
    # The panel tilted 15° at 3 m: the flip of the true pose lies next to the exact flip
    # (``planar_flip``, IPPE's other pose; the two differ by the weak-perspective
    # approximation) and images the corners alike; flipping twice gives the pose back.
    X_tilted = Pose.from_rpy(
        math.radians(165), math.radians(3), math.radians(10), np.array([0.1, 0.05, 3.0])
    )
    corners = TARGET.panel_corners_T
    flipped = weak_perspective_flip(X_tilted, corners)
    other = planar_flip(X_tilted, corners, K)  # the exact flip: IPPE's other pose
    assert other is not None
    assert rotation_error_geodesic(X_tilted, flipped) > math.radians(20)
    assert rotation_error_geodesic(other, flipped) < math.radians(2)
    moved = project_ideal(flipped, corners, K) - project_ideal(X_tilted, corners, K)
    assert np.abs(moved).max() < 2.0
    assert rotation_error_geodesic(X_tilted, weak_perspective_flip(flipped, corners)) < 1e-9
    assert translation_error(X_tilted, weak_perspective_flip(flipped, corners)) < 1e-9


def test_against_flip_says_when_only_the_prior_kept_the_flip():
    # A fit from the prior alone stays in the prior's minimum. Weighed against the flip, the
    # choice says so where the residuals cannot decide (σ = 1 px) and turns to the true pose
    # where they can (σ = 0.3 px).
    X_tilted = Pose.from_rpy(
        math.radians(165), math.radians(3), math.radians(10), np.array([0.1, 0.05, 3.0])
    )
    corners = TARGET.panel_corners_T
    uv = project_ideal(X_tilted, corners, K)
    wrong = weak_perspective_flip(X_tilted, corners)
    for sigma, decided_by in ((1.0, "prior"), (0.3, "residual")):
        obs = PointObservations(corners, uv, _isotropic(4, sigma))
        alone = choose_pose(fit_from_starts([obs], [wrong], K), wrong)
        assert alone.decided_by == "only"
        assert rotation_error_geodesic(X_tilted, alone.fit.X_CT) > math.radians(20)
        weighed = against_flip(alone, obs, K, wrong)
        assert weighed.decided_by == decided_by
    assert rotation_error_geodesic(X_tilted, weighed.fit.X_CT) < 1e-6


def test_observations_reject_mismatched_shapes():
    with pytest.raises(ValueError, match="covariances"):
        PointObservations(POINTS_T, np.zeros((len(POINTS_T), 2)), _isotropic(3, 1.0))
    with pytest.raises(ValueError, match="same length"):
        EdgeObservations(_panel_edges(), np.zeros(3, int), np.zeros((4, 2)), np.ones(4))
    with pytest.raises(ValueError, match="does not exist"):
        EdgeObservations(_panel_edges(), np.array([0, 4]), np.zeros((2, 2)), np.ones(2))
    with pytest.raises(ValueError, match="at least 6 residuals"):
        refine_pose(
            [PointObservations(POINTS_T[:2], np.zeros((2, 2)), _isotropic(2, 1))], X_TRUE, K
        )
    with pytest.raises(ValueError, match="pose method"):
        fit_from_starts([], [X_TRUE], K, method="ransac")  # type: ignore[arg-type]


def test_correlated_edge_whitening_is_generalised_least_squares():
    """‖M·(r/σ)‖² equals rᵀΣ⁻¹r with Σ_e = D_e + A_e·Q_e·A_eᵀ formed explicitly per edge."""
    rng = np.random.default_rng(3)
    ends_T = rng.normal(size=(2, 2, 3))
    counts = (7, 12)
    edge = np.repeat([0, 1], counts)
    uv = np.concatenate(
        [
            np.array([100.0, 50.0]) + np.outer(np.linspace(0, 80, counts[0]), [1.0, 0.3]),
            np.array([20.0, 200.0]) + np.outer(np.linspace(0, 150, counts[1]), [-0.2, 1.0]),
        ]
    ) + rng.normal(scale=0.2, size=(sum(counts), 2))
    sigma = rng.uniform(0.05, 0.4, size=len(uv))
    offset, turn = np.array([0.1, 0.3]), np.array([0.05, 0.2])
    observations = CorrelatedEdgeObservations(
        EdgeObservations(ends_T, edge, uv, sigma), offset, turn
    )
    r = rng.normal(scale=0.5, size=len(uv))
    whitened = observations.whiten(r / sigma)
    assert whitened.shape == (len(uv) + 4,)
    expected = 0.0
    for e in (0, 1):
        points, r_e = uv[edge == e], r[edge == e]
        centre = points.mean(axis=0)
        direction = np.linalg.svd(points - centre)[2][0]
        along = (points - centre) @ direction
        A = np.column_stack([np.ones(len(points)), along / np.abs(along).max()])
        Sigma = np.diag(sigma[edge == e] ** 2) + A @ np.diag([offset[e] ** 2, turn[e] ** 2]) @ A.T
        expected += r_e @ np.linalg.solve(Sigma, r_e)
    assert whitened @ whitened == pytest.approx(expected, rel=1e-9)


def test_projection_jacobian_matches_finite_differences_and_refuses_points_behind():
    from estimators.planar_pose import projection_jacobian

    uv, J, depth = projection_jacobian(X_TRUE, POINTS_T, K)
    assert np.allclose(uv, project_ideal(X_TRUE, POINTS_T, K), atol=1e-9)
    assert np.allclose(depth, X_TRUE.apply(POINTS_T)[:, 2])
    numeric = np.zeros_like(J)
    for j in range(6):
        step = np.zeros(6)
        step[j] = 1e-7
        plus = projection_jacobian(retract(X_TRUE, step), POINTS_T, K)[0]
        minus = projection_jacobian(retract(X_TRUE, -step), POINTS_T, K)[0]
        numeric[:, :, j] = (plus - minus) / 2e-7
    assert np.allclose(J, numeric, rtol=1e-5, atol=1e-4 * np.abs(J).max())
    behind = projection_jacobian(Pose(np.eye(3), np.zeros(3)), np.array([[0.1, 0.2, -1.0]]), K)
    assert np.isnan(behind[0]).all() and np.isnan(behind[1]).any() and behind[2][0] == -1.0
