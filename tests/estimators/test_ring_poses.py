import math

import numpy as np
import pytest

from estimators.acquisition import TILT_MARGIN, judge_tilt_and_range
from estimators.geometry import Pose, rotation_error_geodesic
from estimators.imaging import image_stack
from estimators.model_support import ModelSupport
from estimators.ring_poses import ring_poses_near
from tests.estimators import rendered

TARGET = rendered.target()


def _tilted_and_short(X_CT: Pose, tilt_deg: float, shortening: float) -> Pose:
    """``X_CT`` turned by ``tilt_deg`` about an axis across the line of sight through the
    panel's centre, then brought ``shortening`` (a fraction) nearer along the line of sight."""
    centre = X_CT.apply(TARGET.panel_corners_T.mean(axis=0)[None])[0]
    axis = np.cross(centre, [0.0, 1.0, 0.0])
    axis /= np.linalg.norm(axis)
    turn = Pose.from_rotvec(math.radians(tilt_deg) * axis, np.zeros(3))
    R = turn.R @ X_CT.R
    p = centre + turn.R @ (X_CT.p - centre)
    return Pose(R, (1.0 - shortening) * p)


@pytest.mark.parametrize("distance", [3.0, 2.0])
def test_the_rings_image_gives_the_pose_back_from_one_tens_of_degrees_and_centimetres_off(distance):
    """A pose 30° off in tilt and 6 % short (held-out random:115 at 2 m was 34° and 6 %): one
    of the poses the ring's edges give, searched around where that pose puts the ring, is
    within 8° and 1.5 % of the truth — a start to measure the pose afresh from (the ring's
    normal near head-on is fixed to a few degrees only)."""
    f = rendered.frame(distance, noise="high", seed=3)
    X_true = f.truth.X_CT
    X_wrong = _tilted_and_short(X_true, 30.0, 0.06)
    poses = ring_poses_near(image_stack(f), X_wrong, TARGET, f.info)
    assert poses
    best = min(poses, key=lambda X: rotation_error_geodesic(X, X_true))
    assert math.degrees(rotation_error_geodesic(best, X_true)) < 8.0
    assert np.linalg.norm(best.p - X_true.p) < 0.015 * distance


def test_the_tilt_judge_refutes_a_pose_wrong_in_tilt_and_range_beyond_its_searches():
    """A pose 34° off in tilt and 6 % short, claiming 2.5° and a centimetre: no tilt within the
    search about the panel's centre and no move along the line of sight alone mends it; a pose
    the ring's image gives does, and the judge says so. The truth itself is left be."""
    f = rendered.frame(2.0, noise="high", seed=3)
    image = image_stack(f)
    support = ModelSupport(TARGET, f.info)
    X_true = f.truth.X_CT
    claimed = np.diag([math.radians(2.5) ** 2] * 3 + [0.01**2] * 3)
    judged = judge_tilt_and_range(
        support, image, _tilted_and_short(X_true, 34.0, 0.06), TARGET, claimed
    )
    assert judged.X_CT is not None and judged.gain >= TILT_MARGIN
    assert math.degrees(rotation_error_geodesic(judged.X_CT, X_true)) < 8.0
    assert judge_tilt_and_range(support, image, X_true, TARGET, claimed).X_CT is None
