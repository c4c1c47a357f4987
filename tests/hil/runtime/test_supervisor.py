import math

import numpy as np
import pytest

from configuration.approach import ApproachConfig
from drivers.base import ArmState
from estimators.geometry import Pose
from hil.runtime.supervisor import SafetySnapshot, check

CONFIG = ApproachConfig()
FACING = Pose(np.diag([1.0, -1.0, -1.0]), np.array([0.05, -0.02, 1.2]))
ARM = ArmState(0.0, np.zeros(6), Pose(np.eye(3), np.array([0.5, 0.0, 0.8])), np.zeros(6))


def snapshot(**changes) -> SafetySnapshot:
    base = dict(
        stamp=1.0,
        phase="approach",
        arm=ARM,
        arm_error=None,
        track_fault=None,
        estimate_health="ok",
        estimate_age_s=0.05,
        X_TC_est=FACING,
        frame_age_s=0.03,
        tick_s=0.004,
        commanded_V_BE=np.array([0.05, 0.0, 0.0, 0.0, 0.0, 0.01]),
        commanded_track_velocity=0.1,
    )
    base.update(changes)
    return SafetySnapshot(**base)


def kinds(snap):
    return {
        (v.kind, v.recoverable)
        for v in check(snap, CONFIG.supervisor, CONFIG.servo, max_track_speed=0.3)
    }


def test_supervisor_passes_a_healthy_tick():
    assert kinds(snapshot()) == set()


@pytest.mark.parametrize(
    ("changes", "expected"),
    [
        ({"arm_error": "link down"}, ("arm_link", False)),
        (
            {"arm": ArmState(0.0, np.zeros(6), ARM.X_BE, np.zeros(6), protective_stop=True)},
            ("arm_fault", False),
        ),
        (
            {"arm": ArmState(0.0, np.zeros(6), ARM.X_BE, np.zeros(6), fault="watchdog")},
            ("arm_fault", False),
        ),
        ({"track_fault": "soft limit"}, ("track_fault", False)),
        ({"tick_s": 0.2}, ("deadline", False)),
        ({"commanded_V_BE": np.array([1.0, 0, 0, 0, 0, 0])}, ("speed", False)),
        ({"commanded_V_BE": np.array([0, 0, 0, 0, 0, 1.0])}, ("speed", False)),
        ({"commanded_V_BE": np.array([np.nan, 0, 0, 0, 0, 0])}, ("command", False)),
        ({"commanded_track_velocity": 2.0}, ("speed", False)),
        (
            {
                "arm": ArmState(
                    0.0, np.zeros(6), Pose(np.eye(3), np.array([2.0, 0.0, 0.8])), np.zeros(6)
                )
            },
            ("workspace", False),
        ),
        ({"frame_age_s": 1.0}, ("frames", True)),
        ({"estimate_health": "coasting"}, ("estimate", True)),
        ({"estimate_age_s": 0.5}, ("estimate", True)),
        ({"X_TC_est": None}, ("estimate", True)),
        ({"X_TC_est": Pose(FACING.R, np.array([0.9, 0.0, 1.0]))}, ("cone", False)),
        ({"X_TC_est": Pose(FACING.R, np.array([0.0, 0.0, 0.2]))}, ("too_close", False)),
    ],
)
def test_supervisor_flags_each_rule(changes, expected):
    assert expected in kinds(snapshot(**changes))


def test_supervisor_ignores_the_estimate_when_nothing_moves():
    assert (
        kinds(snapshot(phase="acquire", estimate_health="lost", X_TC_est=None, frame_age_s=5.0))
        == set()
    )
    # …but device faults still count.
    assert ("arm_link", False) in kinds(snapshot(phase="acquire", arm_error="gone"))


def test_grasp_cannot_be_configured_into_the_keep_out_zone():
    with pytest.raises(ValueError, match=r"inside supervisor\.min_range_m"):
        ApproachConfig.model_validate({"grasp": {"advance_m": 0.3}})


def test_approach_cone_is_measured_from_the_ring_axis():
    edge = math.tan(math.radians(CONFIG.supervisor.approach_cone_deg)) * 1.0
    inside = Pose(FACING.R, np.array([0.99 * edge, 0.0, 1.0]))
    outside = Pose(FACING.R, np.array([1.01 * edge, 0.0, 1.0]))
    assert kinds(snapshot(X_TC_est=inside)) == set()
    assert ("cone", False) in kinds(snapshot(X_TC_est=outside))
