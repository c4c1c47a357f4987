"""The face outline's edges found from a pose that is degrees off in tilt (as one measured on
the panel's edges alone is), judged against the outline's true projection."""

import math

import numpy as np
import pytest

from estimators.geometry import project_from
from estimators.outline_edges import fit_outline_edges, outline_edge_ends
from estimators.planar_pose import retract
from tests.estimators import rendered

TARGET = rendered.target()


def _distance_to_line(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    direction = (b - a) / np.linalg.norm(b - a)
    normal = np.array([-direction[1], direction[0]])
    return np.abs((points - a) @ normal)


@pytest.mark.parametrize("distance", [3.0, 2.0])
def test_outline_edges_are_found_on_their_true_projection_from_a_tilted_pose(distance):
    frame = rendered.frame(distance, seed=5, supersample=2)
    X_true, K = frame.truth.X_CT, frame.info.K
    tilt = math.radians(2.0)
    X_guess = retract(X_true, np.array([tilt, -tilt, 0.0, 0.0, 0.0, 0.01]))
    covariance = np.diag([math.radians(3.0) ** 2] * 3 + [0.02**2] * 3)
    outline = fit_outline_edges(frame.image, X_guess, covariance, frame.info, TARGET)
    assert outline.found == 4  # all four edges are in view at 2–3 m
    assert outline.polarity == 1.0  # the face is brighter than black space
    for (a_T, b_T), edge in zip(outline_edge_ends(TARGET), outline.edges, strict=True):
        a, b = project_from(X_true, np.stack([a_T, b_T]), K)
        off = _distance_to_line(edge.uv_ideal[edge.used], a, b)
        assert len(off) >= 10
        assert np.median(off) < 0.3 and off.max() < 1.5, (np.median(off), off.max())


def test_no_outline_edges_on_a_black_image():
    frame = rendered.frame(2.0)
    outline = fit_outline_edges(
        np.zeros_like(frame.image), frame.truth.X_CT, np.eye(6) * 1e-4, frame.info, TARGET
    )
    assert outline.found == 0 and outline.points == 0
