"""Sub-pixel edge search and the noise estimate, on synthetic images with known edges."""

import numpy as np
import pytest

from estimators.edge_search import search_edges
from estimators.imaging import estimate_noise_sigma, gradient_noise_gain, smoothed_gradient


def step_image(edge_x: float, shape=(120, 160), low=0.3, high=0.7, noise=0.0, seed=0):
    """A vertical step at sub-pixel ``edge_x`` (pixel-area integrated), plus noise."""
    xs = np.arange(shape[1], dtype=float)
    coverage = np.clip(xs + 0.5 - edge_x, 0.0, 1.0)  # fraction of each pixel right of the edge
    row = low + (high - low) * coverage
    image = np.tile(row, (shape[0], 1))
    rng = np.random.default_rng(seed)
    return np.clip(image + noise * rng.standard_normal(shape), 0, 1).astype(np.float32)


@pytest.mark.parametrize("edge_x", [70.0, 70.25, 70.5, 70.8])
def test_search_edges_locates_a_step_to_subpixel(edge_x):
    image = step_image(edge_x)
    field = smoothed_gradient(image, 1.0, 0.01)
    points = np.column_stack([np.full(20, 68.0), np.arange(50, 70)])
    normals = np.tile([1.0, 0.0], (20, 1))
    hits = search_edges(field, points, normals, +1, 5.0)
    assert hits.found.all()
    # Cubic interpolation of the gradient leaves a periodic error of ≤ 0.05 px (zero mean over
    # sub-pixel phases): far below the edge noise of any real frame.
    assert np.abs(hits.uv[:, 0] - edge_x).max() < 0.06
    # The opposite polarity finds nothing; a window short of the edge finds nothing either.
    assert not search_edges(field, points, normals, -1, 5.0).found.any()
    assert not search_edges(field, points - [6.0, 0.0], normals, +1, 3.0).found.any()


def test_search_edges_rejects_searches_off_the_field_and_gradients_across_the_normal():
    image = step_image(70.0)
    field = smoothed_gradient(image, 1.0, 0.01)
    # Rows 0..1 search past the field's left border; the others lie inside it.
    points = np.array([[2.0, 60.0], [1.0, 61.0], [68.0, 62.0], [68.0, 63.0]])
    normals = np.tile([-1.0, 0.0], (4, 1))
    hits = search_edges(field, points, normals, -1, 5.0)
    assert hits.found.tolist() == [False, False, True, True]
    assert np.isnan(hits.uv[:2]).all() and np.isnan(hits.offset_px[:2]).all()
    assert (hits.snr[:2] == 0).all() and (hits.snr[2:] > 3).all()
    # Along a normal 60° off the gradient the edge is not this curve's (max 50°); 40° is.
    for angle_deg, expected in ((60.0, False), (40.0, True)):
        a = np.radians(angle_deg)
        tilted = search_edges(field, points[2:], np.tile([np.cos(a), np.sin(a)], (2, 1)), +1, 8.0)
        assert tilted.found.tolist() == [expected, expected]


def test_search_edges_prefers_the_edge_nearest_the_prediction():
    """Two edges of the same polarity in the window; the weaker one at the prediction wins
    when a prior width is given (a strong neighbour, like a bolt hole, must not)."""
    xs = np.arange(160, dtype=float)
    row = 0.2 + 0.2 * (xs >= 70) + 0.5 * (xs >= 76)
    image = np.tile(row, (60, 1)).astype(np.float32)
    field = smoothed_gradient(image, 1.0, 0.01)
    points = np.column_stack([np.full(10, 70.0), np.arange(20, 30)])
    normals = np.tile([1.0, 0.0], (10, 1))
    strongest = search_edges(field, points, normals, +1, 8.0)
    nearest = search_edges(field, points, normals, +1, 8.0, prior_sigma_px=2.0)
    assert np.allclose(strongest.uv[:, 0], 75.5, atol=0.2)
    assert np.allclose(nearest.uv[:, 0], 69.5, atol=0.2)


def test_search_edges_precision_under_noise_matches_theory():
    """σ_n / contrast = 0.55 (the reference's low noise on the ring): each edge point's
    scatter ≈ 0.6·σ_n/c (the Gaussian-derivative localisation, with Sobel smoothing), and no
    bias."""
    image = step_image(80.3, shape=(400, 160), noise=0.22)
    field = smoothed_gradient(image, 1.0, estimate_noise_sigma(image))
    points = np.column_stack([np.full(390, 80.0), np.arange(5, 395)])
    hits = search_edges(field, points, np.tile([1.0, 0.0], (390, 1)), +1, 3.0)
    x = hits.uv[hits.found, 0]
    assert hits.found.mean() > 0.8
    assert abs(np.median(x) - 80.3) < 0.05
    assert 0.2 < 1.4826 * np.median(np.abs(x - np.median(x))) < 0.45


def test_estimate_noise_sigma_ignores_clipped_background():
    rng = np.random.default_rng(4)
    image = np.zeros((240, 320), np.float32)
    image[40:200, 60:260] = 0.5
    image = np.clip(image + 0.22 * rng.standard_normal(image.shape), 0, 1).astype(np.float32)
    assert estimate_noise_sigma(image) == pytest.approx(0.22, rel=0.1)
    assert estimate_noise_sigma(np.full((60, 60), 0.4, np.float32)) == pytest.approx(0.0, abs=1e-6)


def test_gradient_noise_gain_matches_measured_noise():
    rng = np.random.default_rng(6)
    noise = rng.standard_normal((300, 300)).astype(np.float32)
    field = smoothed_gradient(noise, 1.5, 1.0)
    measured = field.gxy[20:-20, 20:-20, 0].std()
    assert measured == pytest.approx(gradient_noise_gain(1.5), rel=0.05)
    assert field.noise == pytest.approx(gradient_noise_gain(1.5))
