"""How well can circle edges fix a pose? The Cramér–Rao bound of an edge-point fit.

Edge points every ``spacing_px`` along each projected circle, each with independent Gaussian
error ``sigma_px`` across the curve: the information is JᵀJ/σ² with J the Jacobian of the
points' geometric distances to the projected circles (the same model ``circle_fit`` fits), at
the true pose. The tilt is reported as the standard deviations along the principal axes of
the normal's covariance — near head-on views one of them (tilt about the line from the ring's
centre to the thruster) is far weaker than the other.

Labeled points (the ring's holes, fitted as discs) may join with an isotropic position error
``point_sigma_px``: unlike an edge, a point also moves along the curve, so it sees the tilt to
first order.

Run ``python -m hil.evaluation.circle_bounds`` for the table quoted in docs/ellipses.md.
"""

from __future__ import annotations

import numpy as np

from estimators.circle_fit import ConicObservations, EdgeSet, TargetProblem
from estimators.conics import circle_points
from estimators.ellipses import ring_hole_layout
from estimators.geometry import Pose, intrinsics_from_fov, project
from estimators.planar_pose import PointObservations
from estimators.target import TargetModel


def circle_information(
    target: TargetModel,
    K: np.ndarray,
    X_CT: Pose,
    circles: tuple[str, ...],
    *,
    free_radius: tuple[str, ...] = (),
    sigma_px: float | dict[str, float] = 0.5,
    spacing_px: float = 1.0,
) -> np.ndarray:
    """6×6 Fisher information about [δθ, δp] of edge points every ``spacing_px`` along each of
    ``circles`` (σ across the curve ``sigma_px``, or per circle name), with the radii of
    ``free_radius`` estimated too and marginalised out (Schur complement)."""
    sets = []
    for name in circles:
        c = target.circle(name)
        dense = project(X_CT.apply(circle_points(c.center_T, c.normal_T, c.radius, 720)), K)
        perimeter = float(np.linalg.norm(np.diff(dense, axis=0), axis=1).sum())
        count = max(int(perimeter / spacing_px), 8)
        uv = project(X_CT.apply(circle_points(c.center_T, c.normal_T, c.radius, count)), K)
        sets.append(EdgeSet(c, uv, free_radius=name in free_radius))
    problem = TargetProblem(ConicObservations(tuple(sets), K))
    _, J = problem.linearize(problem.state(X_CT))
    sigmas = {name: sigma_px for name in circles} if np.isscalar(sigma_px) else sigma_px
    weights = np.concatenate([np.full(len(s.uv), 1.0 / sigmas[s.circle.name]) for s in sets])
    Jw = J * weights[:, None]  # the model's rows run set by set, point by point
    information = Jw.T @ Jw
    A, B, D = information[:6, :6], information[:6, 6:], information[6:, 6:]
    return A - B @ np.linalg.pinv(D) @ B.T if J.shape[1] > 6 else A


def tilt_bounds(
    target: TargetModel,
    K: np.ndarray,
    X_CT: Pose,
    circles: tuple[str, ...],
    *,
    free_radius: tuple[str, ...] = (),
    sigma_px: float = 0.5,
    spacing_px: float = 1.0,
    points_T: np.ndarray | None = None,
    point_sigma_px: float = 0.2,
) -> tuple[np.ndarray, float]:
    """Bounds of a 6-DOF fit to edge points on ``circles`` (and labeled ``points_T``): the
    tilt's standard deviations (rad; weak axis first, then strong) and the centre's (m, root
    of the trace)."""
    information = circle_information(
        target, K, X_CT, circles, free_radius=free_radius, sigma_px=sigma_px, spacing_px=spacing_px
    )
    if points_T is not None and len(points_T):
        uv = project(X_CT.apply(points_T), K)
        cov = np.tile(point_sigma_px**2 * np.eye(2), (len(uv), 1, 1))
        _, _, J_points = PointObservations(points_T, uv, cov).linearize(X_CT, K)
        information += J_points.T @ J_points
    covariance = np.linalg.pinv(information)
    tilts = normal_tilt_sigmas(covariance, X_CT.R[:, 2])
    center = float(np.sqrt(np.trace(covariance[3:, 3:])))
    return tilts, center


def normal_tilt_sigmas(covariance: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Standard deviations (rad) of a normal ``n`` (in C) along the principal axes of its
    error δn = δθ × n under a pose covariance over [δθ, δp]: weak axis first."""
    nx = np.array([[0, -n[2], n[1]], [n[2], 0, -n[0]], [-n[1], n[0], 0]])
    normal_cov = nx @ covariance[:3, :3] @ nx.T
    return np.sqrt(np.clip(np.linalg.eigvalsh(normal_cov)[1:], 0.0, None))[::-1]


def main() -> None:
    from configuration.mockup import load_mockup
    from hil.evaluation.scenarios import camera_pose_for, target_offset

    target = load_mockup("default").target_model()
    holes_T = ring_hole_layout(
        target, target.circle("ring_outer"), target.circle("ring_inner")
    ).points_T
    K = intrinsics_from_fov(640, 480, 70.0)
    # (edges, those with a free radius, hole position error in px or None)
    feature_sets = (
        (("ring_outer", "thruster_inner"), ("thruster_inner",), None),
        (("ring_outer", "ring_inner", "thruster_inner"), ("ring_inner", "thruster_inner"), None),
        (("ring_outer", "thruster_inner"), ("thruster_inner",), 0.1),
        (("ring_outer", "thruster_inner"), ("thruster_inner",), 0.3),
    )
    print("| distance | edges (free radius) | ring holes | tilt σ weak / strong | centre σ |")
    print("|---|---|---|---|---|")
    for distance in (3.0, 2.0, 1.2):
        _, X_CT = camera_pose_for(distance, target_offset())
        for circles, free, hole_sigma in feature_sets:
            tilts, center = tilt_bounds(
                target,
                K,
                X_CT,
                circles,
                free_radius=free,
                points_T=holes_T if hole_sigma is not None else None,
                point_sigma_px=hole_sigma or 0.0,
            )
            label = " + ".join(f"{c}{' (free)' if c in free else ''}" for c in circles)
            holes = "—" if hole_sigma is None else f"{len(holes_T)} at {hole_sigma} px"
            print(
                f"| {distance:.1f} m | {label} | {holes} | {np.degrees(tilts[0]):.2f}° / "
                f"{np.degrees(tilts[1]):.2f}° | {1000 * center:.1f} mm |"
            )


if __name__ == "__main__":
    main()
