import math

import numpy as np
import pytest

from estimators.acquisition import (
    TurnChecker,
    coarse_gradients,
    find_panel_quads,
    pose_hypotheses,
    poses_from_corners,
    quarter_turns,
)
from estimators.geometry import rotation_error_geodesic
from estimators.imaging import GradientImage, image_stack
from estimators.model_support import ModelSupport
from estimators.planar_pose import project_ideal
from tests.estimators import rendered

TARGET = rendered.target()


@pytest.mark.parametrize("distance", [3.0, 1.2])
def test_find_panel_quads_finds_the_panel_among_other_squares(distance):
    f = rendered.frame(distance, noise="high", seed=2)
    image = image_stack(f)
    gradients = GradientImage.of(image.pixels, 2.0, image.noise_sigma)
    quads = find_panel_quads(image, gradients, TARGET)
    truth = f.info.project(f.truth.X_CT.apply(TARGET.panel_corners_T))
    # The bus face is a brighter square too; the panel must be among the candidates.
    gaps = [
        np.linalg.norm(q.corners_uv[:, None, :] - truth[None, :, :], axis=2).min(axis=0).max()
        for q in quads
    ]
    assert min(gaps) < 4.0


def test_poses_from_corners_include_every_quarter_turn_of_the_truth():
    camera = rendered.render(2.0)[2]
    X_true = rendered.render(2.0)[1]
    corners = project_ideal(X_true, TARGET.panel_corners_T, camera.K)
    poses = poses_from_corners(corners, camera, TARGET)
    assert len(poses) == 8  # 4 correspondences × the planar flip
    for turn in quarter_turns(TARGET):
        assert min(rotation_error_geodesic(X_true @ turn, X) for X in poses) < 1e-6


def test_pose_hypotheses_rank_the_true_quarter_turn_first():
    f = rendered.frame(2.0, noise="low", seed=8)
    image = image_stack(f)
    gradients = GradientImage.of(image.pixels, 2.0, image.noise_sigma)
    support = ModelSupport(TARGET, f.info)
    hypotheses = pose_hypotheses(
        image,
        gradients,
        coarse_gradients(image),
        f.info,
        TARGET,
        support,
        TurnChecker(TARGET, support),
    )
    assert hypotheses
    assert rotation_error_geodesic(f.truth.X_CT, hypotheses[0].X_CT) < math.radians(15)
