"""Test fixture: a mock-up carrying a grid of bright marker discs on a dark face, and the
measurement of where those discs land in a rendered image."""

from __future__ import annotations

import numpy as np

from configuration.mockup import MockupConfig
from estimators.geometry import Pose, in_view, project


def marker_mockup(spacing_m: float = 0.22, diameter_m: float = 0.05) -> MockupConfig:
    """A wide dark face with bright discs on a grid (outside the ring), no thruster."""
    half_w, half_h = 2.2, 1.7
    xs = np.arange(-half_w + 0.1, half_w - 0.05, spacing_m)
    ys = np.arange(-half_h + 0.1, half_h - 0.05, spacing_m)
    positions = [(float(x), float(y)) for x in xs for y in ys if np.hypot(x, y) > 0.45]
    return MockupConfig.model_validate(
        {
            "name": "markers",
            "bus_face": {"width": 2 * half_w, "height": 2 * half_h, "color": [0.1, 0.1, 0.1]},
            "thruster": None,
            "fasteners": [
                {
                    "name": "marker",
                    "surface": "bus",
                    "diameter": diameter_m,
                    "height": 1e-4,
                    "color": [0.9, 0.9, 0.9],
                    "positions": positions,
                },
            ],
        }
    )


def expected_centroid(X_CT: Pose, center_T: np.ndarray, radius: float, K, dist) -> np.ndarray:
    """Area centroid of the projected disc: its outline projected through the full camera
    model (a 720-gon) — exact for any distortion, no small-disc approximation."""
    t = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    rim_T = center_T + radius * np.column_stack([np.cos(t), np.sin(t), np.zeros_like(t)])
    uv = project(X_CT.apply(rim_T), K, dist)
    x, y = uv[:, 0], uv[:, 1]
    x1, y1 = np.roll(x, -1), np.roll(y, -1)
    cross = x * y1 - x1 * y
    area = cross.sum() / 2
    return np.array([((x + x1) * cross).sum(), ((y + y1) * cross).sum()]) / (6 * area)


def measured_centroid(image: np.ndarray, guess: np.ndarray, radius_px: float) -> np.ndarray | None:
    """Background-subtracted intensity centroid of a bright disc in a window around ``guess``;
    None if the window leaves the image."""
    gray = image if image.ndim == 2 else image.mean(axis=2)
    gray = gray.astype(float)
    half = int(np.ceil(radius_px + 4))
    u0, v0 = round(guess[0]), round(guess[1])
    h, w = gray.shape
    if u0 - half < 2 or v0 - half < 2 or u0 + half >= w - 2 or v0 + half >= h - 2:
        return None
    window = gray[v0 - half : v0 + half + 1, u0 - half : u0 + half + 1]
    vv, uu = np.mgrid[v0 - half : v0 + half + 1, u0 - half : u0 + half + 1]
    r = np.hypot(uu - guess[0], vv - guess[1])
    annulus = (r > radius_px + 2.0) & (r < half)
    background = np.median(window[annulus])
    weights = np.clip(window - background, 0, None)
    weights[r > radius_px + 2.0] = 0.0
    total = weights.sum()
    if total <= 0:
        return None
    return np.array([(weights * uu).sum() / total, (weights * vv).sum() / total])


def projection_errors(image, X_CT: Pose, mockup: MockupConfig, K, dist) -> np.ndarray:
    """Distances (px) between measured and predicted centroids of every fully visible marker."""
    model = mockup.target_model()
    errors = []
    for feature in model.point_features:
        if feature.kind != "disc":
            continue
        p_C = X_CT.apply(feature.p_T)
        radius_px = K[0, 0] * feature.diameter / 2 / max(p_C[2], 1e-9)
        if not in_view(p_C[None], K, dist, image.shape[1], image.shape[0], margin_px=radius_px + 6)[
            0
        ]:
            continue
        predicted = expected_centroid(X_CT, feature.p_T, feature.diameter / 2, K, dist)
        measured = measured_centroid(image, predicted, radius_px)
        if measured is not None:
            errors.append(np.linalg.norm(measured - predicted))
    return np.array(errors)
