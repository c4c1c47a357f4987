import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from configuration.approach import ServoConfig
from estimators.geometry import Pose, rotation_error_geodesic
from estimators.so3 import log_so3
from hil.runtime.servo import (
    camera_twist_to_flange,
    flange_twist_to_camera,
    goal_keeping_roll,
    limit_acceleration,
    limit_command,
    pbvs_twist,
    pose_error,
    saturate,
    scheduled_speed,
    speed_limit,
    split_along_track,
)

GOAL = Pose(np.diag([1.0, -1.0, -1.0]), np.array([0.0, 0.0, 0.5]))  # 0.5 m in front, facing


def integrate(X_TC: Pose, twist_C: np.ndarray, dt: float) -> Pose:
    """Move the camera with a twist expressed in its own frame for dt."""
    return X_TC @ Pose.from_rotvec(twist_C[3:] * dt, twist_C[:3] * dt)


def test_pbvs_converges_exponentially_on_a_straight_line():
    start = Pose.from_rpy(np.pi + 0.15, -0.1, 0.2, np.array([0.3, -0.2, 2.5]))
    X = start
    positions = []
    for _ in range(400):
        X = integrate(X, pbvs_twist(X, GOAL, gain=1.0), 0.01)
        positions.append(X.p)
    error = pose_error(X, GOAL)
    assert error.distance_m == pytest.approx(
        np.linalg.norm(start.p - GOAL.p) * np.exp(-4.0), rel=0.02
    )
    assert rotation_error_geodesic(X, GOAL) < 0.3 * np.exp(-4.0) * 1.1
    # Straight line in the goal frame: every position stays on the start→goal segment.
    direction = (start.p - GOAL.p) / np.linalg.norm(start.p - GOAL.p)
    offsets = np.array(positions) - GOAL.p
    off_line = offsets - np.outer(offsets @ direction, direction)
    assert np.abs(off_line).max() < 2e-3


def test_pbvs_at_goal_is_zero():
    assert np.allclose(pbvs_twist(GOAL, GOAL, 2.0), 0.0)


@given(st.lists(st.floats(-5, 5), min_size=6, max_size=6), st.floats(0.01, 2), st.floats(0.01, 2))
def test_saturate_keeps_direction_and_limits(values, max_v, max_w):
    twist = np.array(values)
    out = saturate(twist, max_v, max_w)
    assert np.linalg.norm(out[:3]) <= max_v + 1e-12
    assert np.linalg.norm(out[3:]) <= max_w + 1e-12
    if np.linalg.norm(twist) > 0:
        scale = np.linalg.norm(out) / np.linalg.norm(twist)
        assert np.allclose(out, scale * twist)
        assert scale <= 1.0 + 1e-12


def test_limit_acceleration_ramps_up():
    previous = np.zeros(6)
    target = np.array([0.2, 0.0, 0.0, 0.0, 0.0, 0.1])
    steps = 0
    while not np.allclose(previous, target):
        nxt = limit_acceleration(target, previous, 0.01, max_acc=0.5, max_angular_acc=0.5)
        assert np.linalg.norm(nxt[:3] - previous[:3]) <= 0.5 * 0.01 + 1e-12
        previous, steps = nxt, steps + 1
    assert steps == 40  # 0.2 m/s at 0.5 m/s² takes 0.4 s


def test_scheduled_speed():
    assert scheduled_speed(0.3, near_m=0.5, far_m=2.0, slow=0.02, fast=0.2) == 0.02
    assert scheduled_speed(3.0, near_m=0.5, far_m=2.0, slow=0.02, fast=0.2) == 0.2
    assert scheduled_speed(1.25, near_m=0.5, far_m=2.0, slow=0.02, fast=0.2) == pytest.approx(0.11)
    with pytest.raises(ValueError):
        scheduled_speed(1.0, near_m=2.0, far_m=1.0, slow=0.1, fast=0.2)


def test_camera_and_flange_twists_are_consistent():
    rng = np.random.default_rng(0)
    X_BE = Pose.from_rpy(0.3, -0.5, 1.0, np.array([0.6, -0.2, 0.7]))
    X_EC = Pose.from_rpy(0.0, 0.1, -1.57, np.array([0.05, 0.08, 0.12]))
    twist_C = rng.normal(size=6) * 0.1
    V_BE = camera_twist_to_flange(twist_C, X_BE, X_EC)
    assert np.allclose(flange_twist_to_camera(V_BE, X_BE, X_EC), twist_C)
    # Finite-difference check: move the flange with V_BE for dt; the camera moved with twist_C.
    dt = 1e-6
    X_BE_next = Pose.from_rotvec(V_BE[3:] * dt, np.zeros(3)) @ Pose(X_BE.R, np.zeros(3))
    X_BE_next = Pose(X_BE_next.R, X_BE.p + V_BE[:3] * dt)
    X_BC, X_BC_next = X_BE @ X_EC, X_BE_next @ X_EC
    expected = integrate(X_BC, twist_C, dt)
    assert np.allclose(X_BC_next.p, expected.p, atol=1e-12)
    assert rotation_error_geodesic(X_BC_next, expected) < 1e-12


def test_split_along_track_preserves_the_relative_motion():
    R_WC = Pose.from_rpy(0.2, -1.4, 0.1, np.zeros(3)).R
    axis = np.array([1.0, 0.0, 0.0])
    twist = np.array([0.05, -0.02, 0.3, 0.01, 0.0, -0.02])
    split = split_along_track(twist, R_WC, axis, max_track_speed=1.0)
    # Camera motion relative to target = arm part − track motion of the target.
    relative_W = R_WC @ split.camera_twist_C[:3] - split.track_velocity * axis
    assert np.allclose(relative_W, R_WC @ twist[:3])
    assert abs((R_WC @ split.camera_twist_C[:3]) @ axis) < 1e-12  # the arm does none of it
    slow = split_along_track(twist, R_WC, axis, max_track_speed=0.01)
    assert abs(slow.track_velocity) == pytest.approx(0.01)
    relative_slow = R_WC @ slow.camera_twist_C[:3] - slow.track_velocity * axis
    assert np.allclose(np.cross(relative_slow, R_WC @ twist[:3]), 0.0, atol=1e-12)  # same direction


# --- the limits, exactly ----------------------------------------------------------------------

SERVO = ServoConfig()


def test_speed_limit_is_the_range_schedule_of_the_servo_config():
    servo = ServoConfig(slow_speed=0.02, max_speed=0.2, near_range_m=0.5, far_range_m=2.0)
    assert speed_limit(0.4, servo) == 0.02
    assert speed_limit(0.5, servo) == 0.02
    assert speed_limit(1.25, servo) == pytest.approx(0.11)
    assert speed_limit(2.0, servo) == pytest.approx(0.2)
    assert speed_limit(9.0, servo) == 0.2


def test_scheduled_speed_boundaries_and_refusal():
    kwargs = dict(near_m=0.5, far_m=2.0, slow=0.02, fast=0.2)
    assert scheduled_speed(0.5, **kwargs) == 0.02 and scheduled_speed(2.0, **kwargs) == 0.2
    with pytest.raises(ValueError, match=r"^scheduled_speed needs far_m > near_m$"):
        scheduled_speed(1.0, near_m=1.0, far_m=1.0, slow=0.1, fast=0.2)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_limit_command_caps_each_change_at_one_period_of_acceleration(sign):
    dt = 0.008
    step_v = SERVO.max_acceleration * dt
    step_w = math.radians(SERVO.max_angular_acceleration_deg) * dt
    previous = np.array([0.1, -0.05, 0.02, 0.01, 0.0, -0.02])
    # within the limits: passed through exactly
    small = previous + sign * np.array([0.5 * step_v, 0, 0, 0, 0, 0.5 * step_w])
    twist, track = limit_command(small, 0.1 + sign * 0.5 * step_v, previous, 0.1, dt, SERVO)
    assert np.allclose(twist, small, atol=1e-15) and track == pytest.approx(
        0.1 + sign * 0.5 * step_v
    )
    # beyond: the linear change capped at max_acceleration·dt, direction kept
    far = previous + sign * np.array([3.0, 4.0, 0.0, 0.0, 0.0, 0.0])
    twist, track = limit_command(far, 0.1 + sign * 5.0, previous, 0.1, dt, SERVO)
    assert np.allclose(twist - previous, sign * np.array([0.6, 0.8, 0, 0, 0, 0]) * step_v)
    assert track == pytest.approx(0.1 + sign * step_v)
    # the angular change capped at max_angular_acceleration·dt (converted from degrees)
    turn = previous + sign * np.array([0, 0, 0, 0.0, 2.0, 0.0])
    twist, _ = limit_command(turn, 0.1, previous, 0.1, dt, SERVO)
    assert np.allclose(twist - previous, sign * np.array([0, 0, 0, 0, step_w, 0]))


def test_limit_acceleration_moves_from_the_previous_toward_the_target():
    previous = np.array([0.2, 0.0, 0.0, 0.0, 0.1, 0.0])
    target = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    out = limit_acceleration(target, previous, 0.1, max_acc=0.5, max_angular_acc=0.5)
    # the linear part sets the scale: 0.05 of a 0.2 change, both parts scaled together
    assert np.allclose(out, previous - 0.25 * previous)
    out = limit_acceleration(target, previous, 1.0, max_acc=0.5, max_angular_acc=0.5)
    assert np.allclose(out, target)  # within one step: reached exactly
    out = limit_acceleration(target, previous, 0.1, max_acc=5.0, max_angular_acc=0.5)
    assert np.allclose(out, 0.5 * previous)  # now the angular part sets it: 0.05 of 0.1


def test_saturate_passes_a_twist_within_limits_and_scales_by_the_tighter_limit():
    twist = np.array([0.1, 0.0, 0.0, 0.0, 0.0, 0.2])
    assert np.array_equal(saturate(twist, 0.1, 0.2), twist)
    assert np.allclose(saturate(twist, 0.05, 1.0), 0.5 * twist)
    assert np.allclose(saturate(twist, 1.0, 0.05), 0.25 * twist)
    assert np.allclose(saturate(twist, 0.05, 0.05), 0.25 * twist)


def test_split_along_track_with_a_scaled_axis_and_the_track_at_its_limit():
    R_WC = np.eye(3)
    twist = np.array([0.3, 0.1, 0.0, 0.01, 0.02, 0.03])
    split = split_along_track(twist, R_WC, np.array([2.0, 0.0, 0.0]), max_track_speed=1.0)
    assert split.track_velocity == pytest.approx(-0.3)  # the axis is normalised
    assert np.allclose(split.camera_twist_C, [0.0, 0.1, 0.0, 0.01, 0.02, 0.03])
    at_limit = split_along_track(twist, R_WC, np.array([1.0, 0.0, 0.0]), max_track_speed=0.3)
    assert at_limit.track_velocity == pytest.approx(-0.3)
    assert np.allclose(at_limit.camera_twist_C, [0.0, 0.1, 0.0, 0.01, 0.02, 0.03])
    slower = split_along_track(-twist, R_WC, np.array([1.0, 0.0, 0.0]), max_track_speed=0.15)
    assert slower.track_velocity == pytest.approx(0.15)
    assert np.allclose(slower.camera_twist_C, -0.5 * np.array([0.0, 0.1, 0.0, 0.01, 0.02, 0.03]))


@given(
    st.floats(-math.pi, math.pi),
    st.floats(-0.3, 0.3),
    st.floats(-0.3, 0.3),
    st.floats(0.5, 2.5),
)
def test_goal_keeping_roll_leaves_the_turn_about_the_rings_axis_alone(roll, tx, ty, distance):
    """Toward the roll-kept goal the camera still goes onto the axis and faces along it, but
    the rotation left to do has no part about the ring's axis (z_T) beyond the second-order
    coupling of a tilt: a guessed roll is never chased."""
    tilt = Pose.from_rotvec(np.array([tx, ty, 0.0]), np.zeros(3))
    turn = Pose.from_rotvec(np.array([0.0, 0.0, roll]), np.zeros(3))
    X_TC = Pose((turn @ tilt).R @ GOAL.R, np.array([0.1, -0.2, distance]))
    kept = goal_keeping_roll(X_TC, GOAL)
    assert np.allclose(kept.p, GOAL.p)  # on the axis: the place is the same
    assert np.allclose(kept.R[:, 2], GOAL.R[:, 2])  # optical axis along −z_T, as the goal's
    left_T = log_so3(kept.R @ X_TC.R.T)  # the turn still to do, in T
    assert abs(left_T[2]) <= 0.5 * (abs(tx) + abs(ty)) ** 2 + 1e-9
    if tx == ty == 0.0:
        assert np.allclose(kept.R, X_TC.R)  # nothing to turn at all
