import math
from dataclasses import replace

import numpy as np
import pytest

from configuration.mockup import load_mockup
from estimators.geometry import Pose
from estimators.measurement import Measurement
from hil.evaluation.errors import measurement_error, roll_error
from hil.evaluation.matrix import (
    MatrixSpec,
    loss_reason,
    loss_table,
    markdown_table,
    run_matrix,
    summarize,
)

ORACLE = "tests.hil.fake_estimators:build_oracle"


def test_matrix_with_an_oracle_measures_exactly_its_offset():
    spec = MatrixSpec(
        systems=(ORACLE,),
        distances_m=(3.0,),
        maneuvers=("none", "turn_y_10deg"),
        noises=("low",),
        frames=4,
        estimator_options={"offset_m": 0.01},
    )
    rows = run_matrix(spec)
    assert len(rows) == 8
    summaries = summarize(rows)
    assert len(summaries) == 2
    for s in summaries:
        assert s.valid == 4 and s.lost == 0
        assert s.position_mean_m == pytest.approx(0.01, abs=1e-12)
        assert s.attitude_mean_rad == pytest.approx(0.0, abs=1e-9)
        assert (s.acquired_ok, s.acquired_tries) == (1, 1)  # first frame had no prior
    table = markdown_table(summaries)
    assert "6.5–9.0 cm" not in table  # the oracle is not a reference system
    assert "1.00 ± 0.00 cm" in table


def test_matrix_counts_losses_and_drops_the_prior_after_one():
    spec = MatrixSpec(
        systems=(ORACLE,),
        distances_m=(2.0,),
        maneuvers=("none",),
        noises=("none",),
        frames=6,
        estimator_options={"lose_every": 3},
    )
    rows = run_matrix(spec)
    assert [r.status for r in rows] == [
        "acquired",
        "tracking",
        "lost",
        "acquired",
        "tracking",
        "lost",
    ]
    s = summarize(rows)[0]
    assert (s.lost, s.longest_loss, s.acquired_tries, s.acquired_ok) == (2, 1, 2, 2)


#: Every frame lost: the estimator raises.
RAISING = MatrixSpec(
    systems=("tests.hil.fake_estimators:build_raising",),
    distances_m=(3.0,),
    maneuvers=("none",),
    noises=("none",),
    frames=2,
)


def test_matrix_turns_an_estimator_exception_into_a_lost_frame():
    rows = run_matrix(RAISING)
    assert all(r.status == "lost" and "boom" in r.reason for r in rows)


def test_matrix_rejects_unknown_names():
    with pytest.raises(ValueError, match="unknown maneuver"):
        run_matrix(MatrixSpec(systems=(ORACLE,), maneuvers=("spin",), frames=2))
    with pytest.raises(ValueError, match="unknown estimator"):
        run_matrix(
            MatrixSpec(
                systems=("sonar",),
                distances_m=(3.0,),
                maneuvers=("none",),
                noises=("none",),
                frames=2,
            )
        )


def test_measurement_error_for_a_circle_pose_and_roll():
    target = load_mockup("default").target_model()
    X_true = Pose.from_rpy(0.1, -0.2, 0.3, np.array([0.05, 0.02, 2.0]))
    # Turned 2° about the target's own z axis — the ring's normal: pure roll.
    X_est = X_true @ Pose.from_rpy(0.0, 0.0, math.radians(2), np.zeros(3))
    ring = target.circle("ring_outer")
    normal = X_true.R @ ring.normal_T
    m = Measurement(
        system="ellipses",
        status="tracking",
        stamp=0.0,
        seq=0,
        X_CT=X_est,
        covariance=np.eye(6),
        circle="ring_outer",
        center_C=X_true.apply(ring.center_T) + [0, 0, 0.01],
        normal_C=normal,
        covariance_5dof=np.eye(5),
    )
    e = measurement_error(m, X_true, target)
    assert e.center_m == pytest.approx(0.01)
    assert e.normal_rad == pytest.approx(0.0, abs=1e-7)
    assert e.roll_rad == pytest.approx(math.radians(2), rel=1e-6)
    assert roll_error(X_true, X_est, np.array([1.0, 0.0, 0.0])) == pytest.approx(0.0, abs=1e-9)


def test_the_loss_table_counts_frames_lost_for_one_reason_together():
    lost = run_matrix(RAISING)[0]
    rows = [
        replace(lost, distance_m=3.0, reason="acquisition failed (no panel-like quadrilateral)"),
        replace(
            lost,
            distance_m=3.0,
            reason="acquisition failed (2 hypotheses rejected: a panel edge has no support (z 2.4))",
        ),
        replace(
            lost,
            distance_m=0.5,
            reason="tracking failed (too few); acquisition failed "
            "(1 hypotheses rejected: a panel edge has no support (z -0.3))",
        ),
        replace(lost, distance_m=0.5, reason="forced", blank=True),
    ]
    assert loss_reason(rows[1].reason) == "a panel edge has no support (z #)"
    assert loss_reason("acquisition failed (edge(s) [1, 3] not found)") == "edge(s) [#…] not found"
    table = loss_table(rows).splitlines()
    assert table[0] == "| system | mode | why lost | 3 m | 0.5 m | all |"
    assert any(line.endswith("| a panel edge has no support (z #) | 1 | 1 | 2 |") for line in table)
    assert any(line.endswith("| no panel-like quadrilateral | 1 | 0 | 1 |") for line in table)
    assert not any("forced" in line for line in table)
    assert len(table) == 4
    assert loss_table(rows[3:]) == ""  # only a forced loss: nothing to explain
