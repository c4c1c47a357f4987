"""Detection and labeling: prior-based labels, ring hypotheses without a prior (and the
thruster's look-alike annulus), and the roll search for the off-axis circle."""

import math

import numpy as np

from configuration.camera import load_camera
from configuration.mockup import load_mockup
from estimators.circle_pose import CirclePose
from estimators.conics import Ellipse, conic_from_ellipse
from estimators.ellipse_detection import (
    LABEL_GATE,
    label_with_prior,
    labeling_cost,
    pose_with_roll,
    projected_ellipse,
    ring_hypotheses,
    roll_of,
    search_roll,
)
from estimators.ellipse_extraction import ExtractedEllipse
from estimators.geometry import Pose
from estimators.imaging import smoothed_gradient
from estimators.target import Circle3D
from tests.estimators.test_ellipse_extraction import draw_ellipses

CAMERA = load_camera("reference").camera_info()
TARGET = load_mockup("default").target_model()


def extracted(e: Ellipse, brighter_inside: bool, n: int = 60) -> ExtractedEllipse:
    return ExtractedEllipse(e, conic_from_ellipse(e), e.points(n), brighter_inside, 6.0, 0.3, 0.9)


def test_label_with_prior_picks_the_nearest_of_the_right_polarity_within_the_gate():
    predicted = Ellipse(300.0, 200.0, 50.0, 48.0, 0.1)
    near_wrong_polarity = extracted(Ellipse(300.5, 200.0, 50.0, 48.0, 0.1), False)
    near = extracted(Ellipse(302.0, 201.0, 51.0, 48.5, 0.1), True)
    far = extracted(Ellipse(400.0, 300.0, 50.0, 48.0, 0.1), True)
    labels = label_with_prior([near_wrong_polarity, far, near], {"ring_outer": (predicted, -1)})
    assert labels["ring_outer"][0] is near
    assert label_with_prior([far], {"ring_outer": (predicted, -1)}) == {}
    # The gate scales with the size: a 5 % error passes and a 40 % error fails at any size.
    for size in (40.0, 100.0, 250.0):
        e = Ellipse(0.0, 0.0, size, 0.95 * size, 0.0)
        for k, passes in ((0.05, True), (0.4, False)):
            moved = Ellipse(k * size, 0.0, (1 + k) * e.a, (1 + k) * e.b, 0.0)
            assert (labeling_cost(moved, e) <= LABEL_GATE) == passes


def test_ring_hypotheses_prefer_concentric_pairs_and_the_larger_annulus():
    """The ring's two edges (ratio 0.833) and the thruster's lip (ratio 0.867, a bright
    annulus too, much smaller): both are pairs; the ring comes first, lone ellipses last."""
    ring_out = extracted(Ellipse(320, 240, 46.0, 45.5, 0.0), True)
    ring_in = extracted(Ellipse(320.2, 240.1, 38.3, 37.9, 0.0), False)
    lip_out = extracted(Ellipse(400, 150, 9.1, 9.0, 0.0), True)
    lip_in = extracted(Ellipse(400.1, 150, 7.9, 7.8, 0.0), False)
    bolt = extracted(Ellipse(100, 100, 5.0, 4.0, 0.3), False)
    hypotheses = ring_hypotheses(
        [bolt, lip_in, ring_in, lip_out, ring_out],
        TARGET.circle("ring_outer"),
        TARGET.circle("ring_inner"),
    )
    assert hypotheses[0].outer is ring_out and hypotheses[0].inner is ring_in
    assert hypotheses[1].outer is lip_out and hypotheses[1].inner is lip_in
    assert all(not h.concentric for h in hypotheses[2:])


def test_ring_hypotheses_take_a_deep_bores_rim_and_foot_for_what_they_are():
    """A bore 8.8 cm deep seen from 0.5 m: its rim and foot are a concentric pair of opposite
    polarity whose ratio (0.851) is near the ring's own (0.870). Where the bore's ratio at the
    distance the rim implies fits better, the pair is also tried as rim and foot — a ring
    larger by r_outer / r_inner, first; where the ring's own ratio fits better, it is not."""
    z = np.array([0.0, 0.0, 1.0])
    outer, inner = Circle3D("o", np.zeros(3), z, 0.338), Circle3D("i", np.zeros(3), z, 0.294)
    focal = 460.0
    rim = extracted(Ellipse(296, 240, 270.1, 267.9, 0.0), False)
    foot = extracted(Ellipse(292, 240, 229.6, 228.5, 0.0), True)
    hypotheses = ring_hypotheses([foot, rim], outer, inner, bore_depth_m=0.088, focal_px=focal)
    assert hypotheses[0].outer is None and hypotheses[0].inner is rim
    assert hypotheses[0].bore_foot is foot
    assert hypotheses[1].outer is rim and hypotheses[1].inner is foot
    # The ring's own two edges (ratio 0.870): no bore reading.
    ring_in = extracted(Ellipse(296, 240, 0.870 * 270.1, 0.870 * 267.9, 0.0), True)
    hypotheses = ring_hypotheses([ring_in, rim], outer, inner, bore_depth_m=0.088, focal_px=focal)
    assert hypotheses[0].outer is rim and hypotheses[0].inner is ring_in
    assert all(h.bore_foot is None for h in hypotheses if h.inner is not None)


def test_ring_hypotheses_take_a_lone_ellipse_for_a_deep_bores_foot_too():
    """A bore's wall as dark as the ring's front shows no rim: close up, the foot (wall against
    the face seen through the bore) may be the only ellipse in the image. A lone ellipse is
    then tried as the outer edge, the inner edge and the foot — the last only with a bore."""
    z = np.array([0.0, 0.0, 1.0])
    outer, inner = Circle3D("o", np.zeros(3), z, 0.407), Circle3D("i", np.zeros(3), z, 0.342)
    foot = extracted(Ellipse(320, 240, 266.9, 266.7, 0.0), True)
    hypotheses = ring_hypotheses([foot], outer, inner, bore_depth_m=0.086, focal_px=460.0)
    readings = [(h.outer is foot, h.inner is foot, h.bore_foot is foot) for h in hypotheses]
    assert readings == [(True, False, False), (False, True, False), (False, False, True)]
    shallow = ring_hypotheses([foot], outer, inner)
    assert [h.bore_foot for h in shallow] == [None, None]


def test_pose_with_roll_and_roll_of_are_inverse():
    ring = TARGET.circle("ring_outer")
    circle_pose = CirclePose(np.array([0.1, -0.05, 2.0]), np.array([0.1, 0.2, -1.0]))
    for roll in (-2.5, -0.3, 0.0, 1.0, 3.0):
        X = pose_with_roll(circle_pose, ring, roll)
        np.testing.assert_allclose(X.apply(ring.center_T), circle_pose.center_C, atol=1e-12)
        np.testing.assert_allclose(X.R @ ring.normal_T, circle_pose.normal_C, atol=1e-12)
        back = roll_of(X, circle_pose, ring)
        assert abs(math.remainder(back - roll, 2 * math.pi)) < 1e-9


def test_search_roll_finds_the_thruster_along_its_locus():
    """A synthetic image of the thruster's dark bore where the true roll puts it: the 1-D
    search over the roll about the ring's axis finds that roll from any start."""
    X_true = Pose.from_rpy(math.pi + 0.05, -0.04, 0.7, np.array([0.02, -0.01, 2.0]))
    ring = TARGET.circle("ring_outer")
    thruster = TARGET.circle("thruster_inner")
    circle_pose = CirclePose(X_true.apply(ring.center_T), X_true.R @ ring.normal_T)
    bore = projected_ellipse(
        X_true.apply(thruster.center_T), X_true.R @ thruster.normal_T, thruster.radius, CAMERA
    )
    image = draw_ellipses((480, 640), [(bore, 0.05)], background=0.5, noise=0.1, seed=3)
    field = smoothed_gradient(image, 1.5, 0.1)
    found = search_roll(field, circle_pose, ring, thruster, CAMERA, polarity=None)
    true_roll = roll_of(X_true, circle_pose, ring)
    assert found is not None and found.polarity == 1  # darker inside
    assert abs(math.remainder(found.roll - true_roll, 2 * math.pi)) < math.radians(1.0)
    assert found.score > 4.0 * max(found.median_score, 0.5)
