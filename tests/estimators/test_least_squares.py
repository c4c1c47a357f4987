"""The one least-squares solver: every observation type's analytic Jacobian against central
differences through its own retraction, the losses, and the loop (Gauss–Newton, LM, IRLS)."""

import math

import numpy as np
import pytest

from configuration.mockup import load_mockup
from estimators.circle_fit import CircleProblem, ConicObservations, EdgeSet, TargetProblem
from estimators.conics import circle_points
from estimators.geometry import Pose, intrinsics_from_fov, project
from estimators.least_squares import (
    Cauchy,
    Huber,
    NoLoss,
    VectorProblem,
    covariance,
    robust_sigma,
    solve,
)
from estimators.planar_pose import (
    CorrelatedEdgeObservations,
    EdgeObservations,
    PointObservations,
    PoseProblem,
    project_ideal,
)

K = intrinsics_from_fov(640, 480, 70.0)
TARGET = load_mockup("default").target_model()
X_TRUE = Pose.from_rpy(math.pi + 0.12, -0.08, 0.3, np.array([0.05, -0.03, 1.6]))
STEP = 1e-6


def _numeric_jacobian(problem, state) -> np.ndarray:
    """Central differences of the flattened residuals through ``problem.retract``."""
    columns = []
    for j in range(problem.n_params):
        e = np.zeros(problem.n_params)
        e[j] = STEP
        plus = np.concatenate(problem.residuals(problem.retract(state, e)))
        minus = np.concatenate(problem.residuals(problem.retract(state, -e)))
        columns.append((plus - minus) / (2 * STEP))
    return np.column_stack(columns)


def _assert_jacobian_matches(problem, state) -> None:
    groups, J = problem.linearize(state)
    assert J.shape == (sum(len(g) for g in groups), problem.n_params)
    numeric = _numeric_jacobian(problem, state)
    scale = np.abs(numeric).max(axis=0, keepdims=True) + 1e-12
    np.testing.assert_allclose(J / scale, numeric / scale, atol=1e-5)


def _edge_sets(X_CT, rng, names, free=()):
    sets = []
    for name in names:
        c = TARGET.circle(name)
        rim = circle_points(c.center_T, c.normal_T, c.radius, 40)
        uv = project(X_CT.apply(rim), K) + 0.5 * rng.standard_normal((40, 2))
        sets.append(EdgeSet(c, uv, free_radius=name in free))
    return tuple(sets)


def _panel_edges():
    corners = TARGET.panel_corners_T
    return np.stack([corners, np.roll(corners, -1, axis=0)], axis=1)


def _edge_observations(rng) -> EdgeObservations:
    ends = _panel_edges()
    edge = np.repeat(np.arange(len(ends)), 6)
    t = np.tile(np.linspace(0.1, 0.9, 6), len(ends))[:, None]
    points_T = ends[edge, 0] * (1 - t) + ends[edge, 1] * t
    uv = project_ideal(X_TRUE, points_T, K) + rng.normal(0, 0.5, (len(edge), 2))
    return EdgeObservations(ends, edge, uv, np.full(len(edge), 0.7))


def test_point_observations_jacobian_matches_differences():
    rng = np.random.default_rng(0)
    points_T = TARGET.points_T()
    uv = project_ideal(X_TRUE, points_T, K) + rng.normal(0, 0.5, (len(points_T), 2))
    covariances = np.tile(np.array([[0.5, 0.1], [0.1, 0.3]]), (len(uv), 1, 1))
    observations = PointObservations(points_T, uv, covariances)
    _assert_jacobian_matches(PoseProblem([observations], K), X_TRUE)


def test_edge_observations_jacobian_matches_differences():
    rng = np.random.default_rng(1)
    edges = _edge_observations(rng)
    _assert_jacobian_matches(PoseProblem([edges], K), X_TRUE)
    correlated = CorrelatedEdgeObservations(edges, np.full(4, 0.3), np.full(4, 0.2))
    _assert_jacobian_matches(PoseProblem([correlated], K), X_TRUE)


def test_conic_observations_target_jacobian_matches_differences():
    rng = np.random.default_rng(2)
    names = ("ring_outer", "ring_inner", "thruster_inner")
    sets = _edge_sets(X_TRUE, rng, names, free=("ring_inner", "thruster_inner"))
    points_T = TARGET.points_T()[:5]
    points = PointObservations(
        points_T, project_ideal(X_TRUE, points_T, K) + 0.3, np.tile(np.eye(2), (5, 1, 1))
    )
    problem = TargetProblem(ConicObservations(sets, K), points)
    assert problem.n_params == 8
    _assert_jacobian_matches(problem, problem.state(X_TRUE, radius_offsets=[0.002, -0.001]))


def test_conic_observations_circle_jacobian_matches_differences():
    rng = np.random.default_rng(3)
    outer, inner = TARGET.circle("ring_outer"), TARGET.circle("ring_inner")
    sets = _edge_sets(X_TRUE, rng, ("ring_outer", "ring_inner"), free=("ring_inner",))
    problem = CircleProblem(ConicObservations(sets, K), outer)
    assert problem.n_params == 6
    center = X_TRUE.apply(outer.center_T) + [0.01, -0.005, 0.02]
    normal = X_TRUE.R @ outer.normal_T + [0.05, 0.02, 0.0]
    _assert_jacobian_matches(problem, problem.state(center, normal, radius_offsets=[0.001]))
    assert inner.normal_T @ outer.normal_T == pytest.approx(1.0)


def test_robust_sigma_is_the_scaled_median_absolute_deviation():
    rng = np.random.default_rng(4)
    for n in (1, 2, 7, 50):
        r = rng.normal(size=n)
        expected = max(1.4826 * np.median(np.abs(r - np.median(r))), 0.05)
        assert robust_sigma(r) == pytest.approx(expected, rel=1e-12)
    assert robust_sigma(np.zeros(0)) == 1.0


def _line_problem(x, y):
    """y ≈ a + b·x as a VectorProblem with an analytic Jacobian."""
    design = np.column_stack([np.ones_like(x), x])
    return VectorProblem(
        lambda s: [design @ s - y], 2, linearized=lambda s: ([design @ s - y], design)
    )


def test_solve_huber_ignores_gross_outliers():
    rng = np.random.default_rng(5)
    x = np.linspace(-1, 1, 200)
    y = 0.3 + 2.0 * x + rng.normal(0, 0.01, 200)
    y[::10] += 5.0
    solution = solve(_line_problem(x, y), np.zeros(2), loss=Huber(floor=1e-3), iterations=30)
    np.testing.assert_allclose(solution.state, [0.3, 2.0], atol=0.01)
    assert solution.sigmas[0] == pytest.approx(0.01, rel=0.3)


def test_solve_levenberg_and_gauss_newton_reach_plain_least_squares():
    rng = np.random.default_rng(6)
    x = np.linspace(-1, 1, 50)
    y = 0.3 + 2.0 * x + rng.normal(0, 0.1, 50)
    design = np.column_stack([np.ones_like(x), x])
    exact = np.linalg.lstsq(design, y, rcond=None)[0]
    lm = solve(_line_problem(x, y), np.zeros(2), loss=NoLoss(), iterations=20, levenberg=True)
    assert lm.converged
    np.testing.assert_allclose(lm.state, exact, atol=1e-10)
    gn = solve(_line_problem(x, y), np.zeros(2), loss=NoLoss(), iterations=20, tolerance=1e-6)
    np.testing.assert_allclose(gn.state, exact, atol=1e-10)
    # The covariance recipe: s²·(JᵀJ)⁻¹.
    np.testing.assert_allclose(
        covariance(lm.information, scale2=0.01), 0.01 * np.linalg.inv(design.T @ design)
    )
    with pytest.raises(ValueError, match="not finite"):
        solve(_line_problem(x, y * np.nan), np.zeros(2), loss=NoLoss(), levenberg=True)


def test_solve_cauchy_weights_blocks_and_restricted_steps():
    rng = np.random.default_rng(7)
    points_T = TARGET.points_T()
    uv = project_ideal(X_TRUE, points_T, K) + rng.normal(0, 0.3, (len(points_T), 2))
    uv[:3] += 40.0  # three wrong correspondences
    observations = PointObservations(points_T, uv, np.tile(np.eye(2) * 0.09, (len(uv), 1, 1)))
    start = Pose.from_rotvec(X_TRUE.rotvec + 0.01, X_TRUE.p + 0.01)
    solution = solve(
        PoseProblem([observations], K), start, loss=Cauchy(), iterations=30, tolerance=1e-6
    )
    assert np.linalg.norm(solution.state.p - X_TRUE.p) < 2e-3
    weights, _ = Cauchy().weights(PoseProblem([observations], K).residuals(solution.state))
    assert np.all(weights[:6] < 0.01) and np.all(weights[6:] > 0.2)
    # Steps restricted to the translation leave the rotation alone.
    basis = np.zeros((6, 3))
    basis[3:, :] = np.eye(3)
    fixed = solve(PoseProblem([observations], K), start, loss=NoLoss(), levenberg=True, basis=basis)
    np.testing.assert_allclose(fixed.state.R, start.R, atol=1e-12)


def test_covariance_of_an_unobserved_direction_is_large_and_positive_not_round_off():
    """A direction the information does not constrain (a circle's tilt seen head-on enters its
    image only to second order) must come out as a large positive variance: an inverse of the
    round-off left in that direction has eigenvalues of either sign (±10¹⁰ on a ring at 3 m,
    which a tracked random mock-up then reported), and a pseudo-inverse's zero claims it
    known exactly."""
    rng = np.random.default_rng(8)
    basis, _ = np.linalg.qr(rng.normal(size=(5, 5)))
    for weak in (-2e-8, 0.0, 4e-10):  # round-off of either sign, and an exact null direction
        information = basis @ np.diag([weak, 3e-9, 5.6e6, 2.8e8, 2.8e8]) @ basis.T
        cov = covariance(information)
        eigenvalues = np.linalg.eigvalsh(cov)
        assert eigenvalues.min() > 0.0
        # both weak directions unconstrained: variance at least that of 1e-10 of the best
        assert eigenvalues[-2] >= 0.99 / (1e-10 * 2.8e8)
        np.testing.assert_allclose(cov, cov.T)
    # A well-conditioned information is inverted as it was.
    information = basis @ np.diag([1.0, 2.0, 5.6e6, 2.8e8, 2.8e8]) @ basis.T
    np.testing.assert_array_equal(covariance(information, keep=3), _plain_inverse(information, 3))


def _plain_inverse(information: np.ndarray, keep: int) -> np.ndarray:
    cov = np.linalg.inv(information)[:keep, :keep]
    return 0.5 * (cov + cov.T)


def test_the_head_on_covariance_of_a_lone_circle_is_positive_definite():
    """``circle_fit.covariance_at`` the head-on pose — the ellipse system's honest covariance
    near head-on — of a ring whose edges alone were fitted: both tilt directions unobserved to
    first order, reported as large and positive (it was ±10¹⁰, and fusion refused it)."""
    from estimators.circle_fit import EdgeSet, covariance_at, fit_circle_pose
    from estimators.circle_pose import CirclePose

    outer = TARGET.circle("ring_outer")
    center = np.array([0.0, 0.0, 3.0])
    tilted = np.array([0.0, math.sin(0.05), -math.cos(0.05)])
    points = circle_points(center, tilted, outer.radius, 200)
    uv = project(points, K) + np.random.default_rng(9).normal(0, 0.1, (200, 2))
    sets = [EdgeSet(outer, uv)]
    fit = fit_circle_pose(sets, CirclePose(center, tilted), outer, K)
    head_on = covariance_at(sets, fit, CirclePose(center, np.array([0.0, 0.0, -1.0])), K,
                            reference=outer)  # fmt: skip
    eigenvalues = np.linalg.eigvalsh(head_on)
    assert eigenvalues.min() > 0.0
    assert np.sqrt(eigenvalues[-1]) > 1.0  # a tilt sd beyond a radian: unknown
