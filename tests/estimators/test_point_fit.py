import math

import cv2
import numpy as np

from estimators.point_fit import fit_corners, fit_discs

SIZE = 64
SUPER = 8


def _area_sampled(inside) -> np.ndarray:
    """An image whose pixels average ``inside(u, v)`` over their area (8×8 sub-samples)."""
    offsets = (np.arange(SIZE * SUPER) + 0.5) / SUPER - 0.5
    v, u = np.meshgrid(offsets, offsets, indexing="ij")
    fine = inside(u, v).astype(np.float32)
    return cv2.resize(fine, (SIZE, SIZE), interpolation=cv2.INTER_AREA)


def _disc_image(center, radius_px, inside_level, outside_level):
    mask = _area_sampled(lambda u, v: (u - center[0]) ** 2 + (v - center[1]) ** 2 <= radius_px**2)
    return outside_level + (inside_level - outside_level) * mask


def test_fit_discs_finds_the_centre_to_its_cramer_rao_precision():
    rng = np.random.default_rng(11)
    sigma_noise = 0.22
    centers = np.array([[20.3, 24.6], [43.7, 38.2]])
    radius_px = np.array([2.5, 4.0])
    clean = (
        _disc_image(centers[0], radius_px[0], 0.1, 0.75)
        + _disc_image(centers[1], radius_px[1], 0.85, 0.37)
        - 0.37
    )
    A = np.tile(np.eye(2) * 100.0, (2, 1, 1))  # 100 px per metre, facing the camera
    errors, z2 = [], []
    for _ in range(60):
        noisy = clean + rng.normal(0.0, sigma_noise, clean.shape).astype(np.float32)
        start = centers + rng.uniform(-1.0, 1.0, centers.shape)
        fits = fit_discs(noisy, start, A, radius_px / 100.0, 2.0 * radius_px / 100.0)
        assert np.all(fits.ok)
        error = fits.uv - centers
        errors.append(error)
        z2.extend(np.einsum("ni,nij,nj->n", error, np.linalg.inv(fits.covariance), error))
        assert fits.contrast[0] < 0 < fits.contrast[1]  # dark hole, bright head
    rms = np.sqrt(np.mean(np.square(errors), axis=0))
    # Cramér–Rao: Var(c_x) ≥ σ² / Σ(∂I/∂c_x)² ≈ σ² / (Δ²·π·r) for a sharp disc of contrast Δ.
    bound = sigma_noise / np.array([0.65, 0.48]) / np.sqrt(math.pi * radius_px)
    assert np.all(rms < 1.6 * bound[:, None])
    assert 1.4 < np.mean(z2) < 3.0  # χ²(2) has mean 2: the covariance is about right


def test_fit_discs_handles_an_oblique_view():
    # A disc 2 mm in radius seen at 60° (its image is an ellipse 2:1).
    center = np.array([30.4, 31.7])
    A = np.array([[[1000.0, 0.0], [0.0, 500.0]]])
    mask = _area_sampled(
        lambda u, v: ((u - center[0]) / 2.0) ** 2 + ((v - center[1]) / 1.0) ** 2 <= 1.0
    )
    image = 0.3 + 0.5 * mask
    fits = fit_discs(image, center[None] + [0.7, -0.4], A, np.array([0.002]), np.array([0.005]))
    assert fits.ok[0]
    assert np.linalg.norm(fits.uv[0] - center) < 0.05  # a 2×1 px ellipse, noise-free
    assert abs(fits.contrast[0] - 0.5) < 0.02


def test_fit_corners_recovers_a_wedge_and_ignores_masked_clutter():
    rng = np.random.default_rng(4)
    corner = np.array([30.35, 28.8])
    a1, a2 = math.radians(5.0), math.radians(100.0)
    e1 = np.array([math.cos(a1), math.sin(a1)])
    e2 = np.array([math.cos(a2), math.sin(a2)])

    def inside(u, v):
        x, y = u - corner[0], v - corner[1]
        n1 = np.array([-e1[1], e1[0]])  # toward e2
        n2 = np.array([e2[1], -e2[0]])  # toward e1
        return (x * n1[0] + y * n1[1] >= 0) & (x * n2[0] + y * n2[1] >= 0)

    clean = 0.35 + 0.28 * _area_sampled(inside)
    clutter = (slice(38, 44), slice(38, 44))  # a dark fastener inside the window
    clean[clutter] = 0.1
    errors = []
    for _ in range(40):
        noisy = clean + rng.normal(0, 0.1, clean.shape).astype(np.float32)
        start = corner + rng.uniform(-1, 1, 2)
        # The start directions are a few degrees off, as a prior's would be.
        dirs = np.array(
            [
                [
                    [math.cos(a1 + 0.05), math.sin(a1 + 0.05)],
                    [math.cos(a2 - 0.05), math.sin(a2 - 0.05)],
                ]
            ]
        )

        def keep(coords):
            return ~(
                (coords[:, 0] >= 36)
                & (coords[:, 0] < 46)
                & (coords[:, 1] >= 36)
                & (coords[:, 1] < 46)
            )

        fits = fit_corners(noisy, start[None], dirs, np.array([12.0]), keep)
        assert fits.ok[0]
        assert fits.contrast_snr[0] > 5
        errors.append(fits.uv[0] - corner)
    errors = np.array(errors)
    assert np.all(np.abs(errors.mean(axis=0)) < 0.1)
    assert np.sqrt(np.mean(errors**2)) < 0.35


def test_fit_discs_with_no_features_returns_empty():
    fits = fit_discs(
        np.zeros((10, 10), np.float32),
        np.zeros((0, 2)),
        np.zeros((0, 2, 2)),
        np.zeros(0),
        np.zeros(0),
    )
    assert fits.uv.shape == (0, 2) and fits.ok.shape == (0,)


def test_fit_discs_finds_a_raised_head_from_its_top_whatever_its_wall_shows():
    # A head whose wall shows 0.8 px beside its top (the base's image is the top's shifted by
    # the extrusion), the wall darker than the top: a plain disc fit centres between top and
    # base; given the extrusion, the fit finds the top's centre.
    top = np.array([31.3, 30.6])
    extrusion = np.array([-0.6, 0.53])
    radius = 4.0
    base = top + extrusion

    def on_segment_distance(u, v):
        d = np.stack([u - top[0], v - top[1]], axis=-1)
        t = np.clip(d @ extrusion / (extrusion @ extrusion), 0.0, 1.0)
        return np.hypot(d[..., 0] - t * extrusion[0], d[..., 1] - t * extrusion[1])

    disc = _area_sampled(lambda u, v: (u - top[0]) ** 2 + (v - top[1]) ** 2 <= radius**2)
    stadium = _area_sampled(lambda u, v: on_segment_distance(u, v) <= radius)
    image = 0.35 + (0.8 - 0.35) * disc + (0.6 - 0.35) * (stadium - disc)
    A = np.eye(2)[None] * 200.0
    plain = fit_discs(image, top[None], A, np.array([radius / 200.0]), np.array([0.04]))
    raised = fit_discs(
        image, top[None], A, np.array([radius / 200.0]), np.array([0.04]), extrusion_px=[extrusion]
    )
    assert plain.ok[0] and raised.ok[0]
    assert np.linalg.norm(plain.uv[0] - top) > 0.1  # pulled toward the base
    assert np.linalg.norm(raised.uv[0] - top) < 0.02
    assert np.linalg.norm(raised.uv[0] - top) < 0.2 * np.linalg.norm(plain.uv[0] - top)
    assert np.linalg.norm(base - top) > 0.7


def test_fit_corners_settles_on_a_wedge_along_the_pixel_rows_under_clipped_noise():
    # A panel's corner seen square-on (edges along the pixel rows and columns) under the
    # study's low noise, which clips many pixels at black and white: Fisher scoring alone
    # swung about the optimum with a growing step and left 8 of these 60 fits unconverged.
    rng = np.random.default_rng(7)
    corner = np.array([32.4, 30.5])
    clean = 0.54 + 0.36 * _area_sampled(lambda u, v: (u <= corner[0]) & (v >= corner[1]))
    sigma = 0.23
    errors = []
    for _ in range(60):
        noisy = np.clip(clean + rng.normal(0.0, sigma, clean.shape), 0.0, 1.0)
        noisy = (np.round(noisy * 255.0) / 255.0).astype(np.float32)  # an 8-bit sensor
        start = corner + rng.uniform(-1.5, 1.5, 2)
        dirs = np.array([[[0.0, 1.0], [-1.0, 0.0]]]) + rng.normal(0.0, 0.02, (1, 2, 2))
        dirs /= np.linalg.norm(dirs, axis=2, keepdims=True)
        fits = fit_corners(noisy, start[None], dirs, np.array([12.0]), noise_sigma=sigma)
        assert fits.ok[0]
        errors.append(fits.uv[0] - corner)
    assert np.sqrt(np.mean(np.square(errors))) < 0.6
