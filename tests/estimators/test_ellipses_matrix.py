"""CI: the ellipse estimator on a reduced reference test matrix, bounds asserted.

The bounds are the issue's targets (docs/ellipses.md has the full matrix): centre ≤ 1.0 cm;
normal ≤ 2.0° at 3 m, ≤ 1.5° at 2 m, ≤ 1.0° at 1.2 m at low noise, 1.5× that at high noise;
roll ≤ 3°. Reaching them at 2–3 m needs the ring's holes in the fit (near head-on the edges
barely fix one tilt axis, see the docs' "information limit" section).
"""

import math

import pytest

from hil.evaluation.matrix import MatrixSpec, run_matrix, summarize

#: (distance, noise) → (centre mean m, normal mean deg)
BOUNDS = {
    (3.0, "low"): (0.010, 2.0),
    (3.0, "high"): (0.015, 3.0),
    (2.0, "low"): (0.010, 1.5),
    (2.0, "high"): (0.015, 2.25),
    (1.2, "low"): (0.010, 1.0),
    (1.2, "high"): (0.015, 1.5),
}


@pytest.fixture(scope="module")
def summaries():
    spec = MatrixSpec(
        systems=("ellipses",),
        distances_m=(3.0, 2.0, 1.2),
        maneuvers=("none", "turn_y_10deg"),
        noises=("low", "high"),
        # 16 frames per maneuver period: twice the reference matrix's motion per frame (at 8,
        # 3.75×, tracking at 3 m / high noise once took wrong edges: docs/ellipses.md).
        frames=16,
        seed=3,
        blank_frames=(8, 9),
    )
    return summarize(run_matrix(spec))


def test_ellipses_reduced_matrix_accuracy_bounds(summaries):
    assert len(summaries) == 12
    for s in summaries:
        center_bound, normal_bound = BOUNDS[(s.distance_m, s.noise)]
        case = f"{s.distance_m} m {s.maneuver} {s.noise}"
        assert s.valid == s.frames, case  # every non-blank frame has a pose
        assert s.wrong_locks == 0, case
        assert s.position_mean_m <= center_bound, case
        assert math.degrees(s.normal_mean_rad) <= normal_bound, case
        assert math.degrees(s.roll_mean_rad) <= 3.0, case  # the thruster fixes the roll


def test_ellipses_reduced_matrix_reacquires_after_blank_frames(summaries):
    for s in summaries:
        assert s.blank == 2
        assert s.recovery_max == 0  # the first frame after the blank ones has a pose again
        assert s.acquired_ok == s.acquired_tries == 2  # the start and after the blanks
