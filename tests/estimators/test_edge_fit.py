import math

import cv2
import numpy as np

from estimators.edge_fit import fit_edge_points, fit_line_robust, intersect

SIZE = 80


def _half_plane_image(normal, offset, inside, outside):
    """Area-sampled image of the half plane n·x ≥ c (brighter ``inside``)."""
    s = 8
    grid = (np.arange(SIZE * s) + 0.5) / s - 0.5
    v, u = np.meshgrid(grid, grid, indexing="ij")
    fine = ((u * normal[0] + v * normal[1]) >= offset).astype(np.float32)
    mask = cv2.resize(fine, (SIZE, SIZE), interpolation=cv2.INTER_AREA)
    return outside + (inside - outside) * mask


def _slanted_edge(angle_deg, offset, inside, outside):
    """The half-plane image whose edge has the normal at ``angle_deg``, that normal, the edge's
    direction, and the edge's point nearest the image's middle."""
    angle = math.radians(angle_deg)
    normal = np.array([math.cos(angle), math.sin(angle)])
    tangent = np.array([-normal[1], normal[0]])
    foot = normal * offset
    foot = foot + ((np.array([40.0, 40.0]) - foot) @ tangent) * tangent
    return _half_plane_image(normal, offset, inside, outside), normal, tangent, foot


def test_fit_edge_points_locates_a_slanted_edge_from_an_offset_prediction():
    angle, offset = math.radians(12.0), 40.3
    clean, normal, tangent, foot = _slanted_edge(12.0, offset, 0.63, 0.35)
    rng = np.random.default_rng(8)
    errors, z = [], []
    for _ in range(30):
        noisy = clean + rng.normal(0, 0.22, clean.shape).astype(np.float32)
        # Prediction 2.5 px off and tilted 2°: the search absorbs it.
        t = np.linspace(-25, 25, 9)
        predicted_normal = np.array([math.cos(angle + 0.035), math.sin(angle + 0.035)])
        centers = foot + t[:, None] * tangent - 2.5 * normal
        points = fit_edge_points(
            noisy, centers, np.tile(predicted_normal, (9, 1)), 3.0, 3.0, search_px=4.0
        )
        assert points.ok.sum() >= 8
        assert points.contrast_snr > 6
        distance = points.uv[points.ok] @ normal - offset
        errors.extend(distance)
        z.extend(distance / points.sigma_px[points.ok])
    errors = np.array(errors)
    assert abs(errors.mean()) < 0.05
    # A 6-px strip of a 0.28 step in σ = 0.22 noise: ~0.32 px per point.
    assert np.sqrt(np.mean(errors**2)) < 0.45
    assert 0.7 < np.sqrt(np.mean(np.square(z))) < 1.5


def test_fit_edge_points_reports_nothing_without_an_edge():
    flat = np.full((SIZE, SIZE), 0.5, np.float32) + np.random.default_rng(0).normal(
        0, 0.2, (SIZE, SIZE)
    ).astype(np.float32)
    centers = np.column_stack([np.full(8, 40.0), np.linspace(15, 65, 8)])
    points = fit_edge_points(flat, centers, np.tile([1.0, 0.0], (8, 1)), 3.0, 3.0, search_px=3.0)
    assert abs(points.contrast_snr) < 5


def test_fit_line_robust_ignores_outliers_and_intersects():
    rng = np.random.default_rng(1)
    t = np.linspace(0, 100, 30)
    points = np.column_stack([t, 0.5 * t + 3.0]) + rng.normal(0, 0.2, (30, 2))
    points[[4, 17, 25]] += [0.0, 6.0]
    line = fit_line_robust(points, np.full(30, 0.2))
    assert line is not None
    assert set(np.flatnonzero(~line.inliers)) == {4, 17, 25}
    slope = -line.normal[0] / line.normal[1]
    assert abs(slope - 0.5) < 0.005
    other = fit_line_robust(np.column_stack([np.full(5, 20.0), np.linspace(0, 40, 5)]), np.ones(5))
    assert other is not None
    crossing = intersect(line, other)
    assert crossing is not None and np.allclose(crossing, [20.0, 13.0], atol=0.2)
    assert intersect(line, line) is None
    assert fit_line_robust(points[:2], np.ones(2)) is None


def test_fit_edge_points_is_unbiased_against_black_when_told_the_noise():
    # A 0.35 face against black space, noise σ = 0.22 clipped at 0 as a sensor does: the mean
    # of the black side is lifted to 0.09 and a least-squares step fit puts the edge inside the
    # face; the clipped likelihood puts it back.
    rng = np.random.default_rng(5)
    sigma = math.sqrt(0.05)
    normal = np.array([math.cos(0.3), math.sin(0.3)])
    tangent = np.array([-normal[1], normal[0]])
    offsets = {0.0: [], sigma: []}
    for _ in range(60):
        offset = 40.0 + rng.uniform(0.0, 1.0)  # every sub-pixel phase
        clean = _half_plane_image(normal, offset, 0.35, 0.0)
        noisy = np.clip(clean + rng.normal(0, sigma, clean.shape), 0, 1).astype(np.float32)
        foot = normal * offset + ((np.array([40.0, 40.0]) - normal * offset) @ tangent) * tangent
        centers = foot + np.linspace(-30, 30, 11)[:, None] * tangent
        for model in offsets:
            points = fit_edge_points(
                noisy, centers, np.tile(normal, (11, 1)), 3.0, 3.0, search_px=2.0, noise_sigma=model
            )
            ok = points.ok
            offsets[model].append(float(np.mean((points.uv[ok] - foot) @ normal)))
    plain, modelled = np.mean(offsets[0.0]), np.mean(offsets[sigma])
    assert plain > 0.05  # toward the bright side
    assert abs(modelled) < 0.02


def test_fit_edge_points_follows_a_prediction_tilted_against_the_edge():
    """A rough hypothesis 3.9 px off the edge at one end and 0.6 px at the other: no common
    offset brings every strip within its reach (the end strips stop at their limit, unusable),
    a tilted start does, and the points lie on the edge."""
    offset = 40.3
    clean, normal, tangent, foot = _slanted_edge(30.0, offset, 0.15, 0.05)
    t = np.linspace(-30, 30, 11)
    off = np.linspace(3.9, 0.6, 11)
    centers = foot + t[:, None] * tangent - off[:, None] * normal
    rng = np.random.default_rng(5)
    found = {0.0: [], 4.0: []}
    errors = []
    for _ in range(20):
        noisy = clean + rng.normal(0, 0.03, clean.shape).astype(np.float32)
        for tilt in found:
            points = fit_edge_points(
                noisy,
                centers,
                np.tile(normal, (11, 1)),
                3.0,
                3.0,
                search_px=5.0,
                noise_sigma=0.03,
                tilt_px=tilt,
            )
            found[tilt].append(points.ok.sum())
            if tilt > 0:
                errors.extend(points.uv[points.ok] @ normal - offset)
    assert min(found[4.0]) == 11
    assert np.mean(found[0.0]) < 10  # why the tilt is needed
    errors = np.array(errors)
    assert abs(errors.mean()) < 0.05
    assert np.sqrt(np.mean(errors**2)) < 0.2


def test_an_edge_against_black_is_unbiased_under_high_noise():
    """Under the study's high noise (σ 0.32, clipped) a 0.35 face against black: each strip's
    offset, from its few dozen pixels, lay 0.015 px toward the face on average (the maximum
    likelihood's small-sample bias where the step is clipped on one side), and so did the
    line through them — the face's outline shrank, the line system's range at 3 m came out
    0.8 mm long. Refitted as one line over every strip's pixels, the bias is a tenth."""
    rng = np.random.default_rng(11)
    sigma = math.sqrt(0.1)
    rows, strips = 400, 60
    column = np.arange(16, dtype=float)
    centers = np.column_stack([np.full(strips, 8.0), np.linspace(6.0, rows - 7.0, strips)])
    normals = np.tile([1.0, 0.0], (strips, 1))  # toward the face
    biases = []
    for _ in range(1500):
        x0 = 8.0 + rng.uniform(-0.5, 0.5)
        face = 0.35 * np.clip(column + 0.5 - x0, 0.0, 1.0)  # area-sampled step
        noisy = np.clip(face + rng.normal(0.0, sigma, (rows, len(column))), 0.0, 1.0)
        noisy = (np.round(noisy * 255.0) / 255.0).astype(np.float32)
        points = fit_edge_points(
            noisy, centers, normals, 3.0, 3.0, search_px=1.0, noise_sigma=sigma
        )
        line = fit_line_robust(points.uv[points.ok], points.sigma_px[points.ok])
        assert line is not None
        x_line = (line.offset - line.normal[1] * rows / 2) / line.normal[0]
        biases.append(x_line - x0)
    bias, standard_error = np.mean(biases), np.std(biases) / math.sqrt(len(biases))
    assert standard_error < 0.0025
    assert abs(bias) < 0.006, (bias, standard_error)
