"""Compile (or load from numba's cache) every compiled kernel of the estimators before the first
frame needs them.

numba compiles a kernel at its first call: 25–35 CPU-seconds for all of them on the development
machine when nothing is cached, under a second from the cache. A vision worker that met its first
frame cold would deliver it tens of seconds late; ``compile_kernels`` runs each public entry
point once on a small synthetic image, with the argument types a frame brings, so the worker
pays that cost before it reports ready.
"""

from __future__ import annotations

import numpy as np

from estimators.circle_edges import sample_projected_circle, visible_pixels
from estimators.circle_fit import ConicObservations, EdgeSet
from estimators.clipped_noise import clipped_likelihood_terms, clipped_moments
from estimators.corners import _extrema_near
from estimators.edge_fit import coarse_edge_offsets, fit_edge_points, fit_line_robust
from estimators.edge_search import search_edges
from estimators.frame import CameraInfo
from estimators.geometry import Pose, distort_normalized, project, undistort_pixels
from estimators.imaging import smoothed_gradient
from estimators.least_squares import Huber, median, robust_sigma
from estimators.model_support import _contour_samples, _group_sums
from estimators.model_view import outside_circles
from estimators.panel_edges import strips_along_edge
from estimators.planar_pose import (
    CorrelatedEdgeObservations,
    EdgeObservations,
    PointObservations,
    projection_jacobian,
)
from estimators.point_fit import fit_corners, fit_discs
from estimators.target import Circle3D


def compile_kernels() -> None:
    """Run every compiled kernel once (results discarded)."""
    size = 64
    v, u = np.mgrid[0:size, 0:size].astype(np.float32)
    # A bright disc on a dark field, and a vertical step (an edge) — float32 like ImageStack.
    pixels = np.where((u - 20) ** 2 + (v - 20) ** 2 < 36, 0.8, 0.2).astype(np.float32)
    pixels[:, 40:] = 0.7
    clipped_likelihood_terms(np.array([0.0, 0.5, 1.0]), np.array([0.1, 0.5, 0.9]), 0.1)
    clipped_moments(np.array([0.1, 0.5]), 0.1)
    robust_sigma(np.array([0.1, -0.2, 0.3]))
    Huber().weights([np.array([0.1, -0.2, 0.3])])
    median(np.array([0.1, -0.2, 0.3]))
    lens = np.array([0.1, -0.05, 0.001, 0.002, 0.01])
    distort_normalized(np.array([[0.1, -0.2]]), lens)
    undistort_pixels(
        np.array([[10.0, 20.0]]), np.array([[200.0, 0, 32], [0, 200.0, 32], [0, 0, 1]]), lens
    )
    project(
        np.array([[0.1, -0.2, 1.0]]), np.array([[200.0, 0, 32], [0, 200.0, 32], [0, 0, 1]]), lens
    )
    centers = np.column_stack([np.full(8, 40.0), np.linspace(10.0, 54.0, 8)])
    normals = np.tile([-1.0, 0.0], (8, 1))
    for sigma in (0.0, 0.05):
        fit_edge_points(pixels, centers, normals, 3.0, 3.0, search_px=2.0, noise_sigma=sigma)
    coarse_edge_offsets(pixels, centers, normals, 3.0, 4.0)
    field = smoothed_gradient(pixels, 1.0, 0.05)
    for prior_sigma_px in (None, 1.0):
        search_edges(field, centers, -normals, 1, 4.0, prior_sigma_px=prior_sigma_px)
    fit_line_robust(centers + np.random.default_rng(0).normal(0, 0.1, centers.shape), np.ones(8))
    A = (np.eye(2) * 1000.0)[None]  # 1 mm per px, one disc
    fit_discs(
        pixels, np.array([[20.0, 20.0]]), A, np.array([0.006]), np.array([0.012]), noise_sigma=0.05
    )
    fit_corners(
        pixels,
        np.array([[40.0, 32.0]]),
        np.array([[[0.0, 1.0], [0.0, -1.0]]]),
        np.array([6.0]),
        noise_sigma=0.05,
    )
    ring = Circle3D("ring", np.zeros(3), np.array([0.0, 0.0, 1.0]), 0.1)
    angles = np.linspace(0.0, 2.0 * np.pi, 12, endpoint=False)
    edges = EdgeSet(ring, np.column_stack([32 + 20 * np.cos(angles), 32 + 20 * np.sin(angles)]))
    conics = ConicObservations((edges,), np.array([[200.0, 0, 32], [0, 200.0, 32], [0, 0, 1]]))
    centre, normal, radius = (
        np.array([[0.0, 0.0, 1.0]]),
        np.array([[0.0, 0.0, 1.0]]),
        np.array([0.1]),
    )
    conics.linearize(
        centre, normal, radius, np.ones((6, 1, 3)), np.ones((6, 1, 3)), np.ones((6, 1))
    )
    outside_circles(np.ones((2, 2)), np.zeros((1, 2)), np.ones(1), within=2.0)
    _extrema_near(pixels, np.array([[20.0, 20.0]]), np.array([3.0]), np.array([1.0]))
    _group_sums(np.zeros(2, np.int64), np.ones(2), np.ones(2), 1)
    points = PointObservations(np.eye(3), np.ones((3, 2)), np.tile(np.eye(2), (3, 1, 1)))
    points.linearize(Pose(np.eye(3), np.array([0.0, 0.0, 1.0])), conics.K)
    projection_jacobian(Pose(np.eye(3), np.array([0.0, 0.0, 1.0])), np.eye(3), conics.K)
    for dist in (np.zeros(0), lens):
        camera = CameraInfo(64, 64, conics.K, dist, "warm-up")
        strips_along_edge(
            Pose(np.eye(3), np.array([0.0, 0.0, 1.0])),
            camera,
            np.array([-0.05, -0.05, 0.0]),
            np.array([0.05, -0.05, 0.0]),
            np.zeros(3),
            4.0,
        )
        sample_projected_circle(
            np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 1.0]), 0.05, camera, spacing_px=2.0
        )
        visible_pixels(np.array([[0.0, 0.0, 1.0]]), camera, 0.0, 1.0)
        # (``ModelSupport.contour_scores``'s kernels, with the argument types it passes)
        _contour_samples(
            np.zeros((2, 3)),
            np.ones((2, 3)),
            np.zeros(2, np.int64),
            1,
            np.eye(3)[None],
            np.array([[0.0, 0.0, 1.0]]),
            np.ones((1, 2), bool),
            np.array(camera.K),
            *camera.lens,
            4.0,
            1.0,
            64,
            64,
        )
    ends = np.array([[[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]], [[0.0, 0.0, 0.0], [0.0, 0.1, 0.0]]])
    lines = EdgeObservations(ends, np.array([0, 0, 1, 1]), np.ones((4, 2)), np.ones(4))
    CorrelatedEdgeObservations(lines, np.ones(2), np.ones(2)).linearize(
        Pose(np.eye(3), np.array([0.0, 0.0, 1.0])), conics.K
    )


if __name__ == "__main__":  # `python -m estimators.warmup` (make does it after installing)
    import time

    started = time.perf_counter()
    compile_kernels()
    print(f"estimators' compiled kernels ready ({time.perf_counter() - started:.1f} s)")
