import math

import numpy as np
import pytest

from configuration.rig import load_rig
from drivers.base import Arm, DeviceError, DeviceFault, DeviceTimeout, ServoCommand
from drivers.ur_kinematics import forward_kinematics, ur_model
from sim_backends.arm import SimArm

RIG = load_rig()
PERIOD = 1.0 / RIG.arm.control_rate_hz


def make_arm(**changes) -> SimArm:
    config = RIG.arm.model_copy(update=changes) if changes else RIG.arm
    arm = SimArm(config)
    arm.connect()
    arm.activate()
    return arm


def stream(arm: SimArm, V: np.ndarray, seconds: float, period: float = 0.008) -> None:
    """Send ``V`` every ``period`` (like a 125 Hz host loop) for ``seconds``."""
    for _ in range(round(seconds / period)):
        arm.servo(ServoCommand(arm.time, V))
        arm.step(period)


def test_sim_arm_implements_the_arm_protocol():
    assert isinstance(make_arm(), Arm)


def test_sim_arm_speedl_follows_the_commanded_twist():
    arm = make_arm()
    start = arm.state()
    V = np.array([0.05, -0.08, 0.03, 0.05, -0.1, 0.15])
    stream(arm, V, 1.0)
    state = arm.state()
    # resolved-rate control integrates at 500 Hz: first-order error in the twist only
    twist = state.V_BE
    assert twist == pytest.approx(V, rel=1e-3, abs=1e-5)
    assert arm.limited_by == ()
    # the ramp (1 m/s², 120°/s²) is done within 0.1 s; the displacement is the twist's
    ramp = 0.5 * max(np.linalg.norm(V[:3]) / 1.0, np.linalg.norm(V[3:]) / math.radians(120))
    moved = state.X_BE.p - start.X_BE.p
    assert moved == pytest.approx(V[:3] * (1.0 - ramp), abs=2e-3)
    assert state.stamp == pytest.approx(arm.time)
    # X_BE in the state is the DH forward kinematics of the reported joints
    assert state.X_BE.is_close(forward_kinematics(ur_model("ur10e"), state.q), atol_m=1e-12)


def test_sim_arm_saturated_twist_keeps_its_direction_and_limits():
    arm = make_arm(
        tcp_speed_limit=5.0, tcp_acceleration=20.0, joint_acceleration_limit_deg_s2=200.0
    )
    V = np.array([0.0, 1.5, 0.0, 0.0, 0.0, 0.0])  # far beyond the joint speed limits
    qd_max = np.array(ur_model("ur10e").max_joint_speed)
    accel_max = math.radians(200.0)
    previous = arm.state()
    directions = []
    limits_seen = set()
    for _ in range(300):
        arm.servo(ServoCommand(arm.time, V))
        arm.step(PERIOD)
        limits_seen.update(arm.limited_by)
        state = arm.state()
        qd = (state.q - previous.q) / PERIOD
        assert np.all(np.abs(qd) <= qd_max * (1 + 1e-9))
        v = state.V_BE[:3]
        if np.linalg.norm(v) > 1e-4:
            directions.append(v / np.linalg.norm(v))
        previous = state
    assert "joint speed" in limits_seen
    assert np.linalg.norm(arm.state().V_BE[:3]) < 1.4  # it could not reach 1.5 m/s
    # the flange moves along +y of B the whole time: no sideways drift, no rotation
    directions = np.array(directions)
    assert np.min(directions @ np.array([0.0, 1.0, 0.0])) > 0.999
    assert np.max(np.abs(arm.state().V_BE[3:])) < 1e-3
    # joint accelerations stayed within the limit (second differences of sampled q)
    qs = []
    arm2 = make_arm(
        tcp_speed_limit=5.0, tcp_acceleration=20.0, joint_acceleration_limit_deg_s2=200.0
    )
    for _ in range(50):
        arm2.servo(ServoCommand(arm2.time, V))
        arm2.step(PERIOD)
        qs.append(arm2.q)
    qdd = np.diff(np.array(qs), n=2, axis=0) / PERIOD**2
    assert np.max(np.abs(qdd)) <= accel_max * 1.001


def test_sim_arm_caps_tcp_speed_keeping_direction():
    arm = make_arm()  # rig cap 0.5 m/s
    V = np.array([0.6, 0.8, 0.0, 0.0, 0.0, 0.0])  # 1 m/s
    stream(arm, V, 0.8)  # 0.5 s ramp at 1 m/s², then 0.3 s at the cap
    v = arm.state().V_BE[:3]
    assert np.linalg.norm(v) == pytest.approx(0.5, rel=1e-3)
    assert v / np.linalg.norm(v) == pytest.approx([0.6, 0.8, 0.0], abs=1e-3)


def test_sim_arm_watchdog_stops_and_reports_fault():
    arm = make_arm()
    V = np.array([0.1, 0.0, 0.0, 0.0, 0.0, 0.0])
    stream(arm, V, 0.5)
    arm.step(RIG.arm.watchdog_s - 0.01)  # silent, but within the watchdog
    assert arm.state().fault is None
    assert np.linalg.norm(arm.state().V_BE[:3]) == pytest.approx(0.1, rel=1e-3)
    arm.step(0.02)  # the watchdog has expired
    assert arm.state().fault == "watchdog"
    # decelerates at stop_deceleration (2 m/s²): 0.1 m/s → 0 in 0.05 s
    arm.step(0.05 + 2 * PERIOD)
    state = arm.state()
    assert np.linalg.norm(state.V_BE) < 1e-9
    assert state.fault_reason == "watchdog"
    with pytest.raises(DeviceFault, match="watchdog"):
        arm.servo(ServoCommand(arm.time, V))
    arm.reset_fault()
    arm.servo(ServoCommand(arm.time, V))  # accepted again


def test_sim_arm_at_rest_without_commands_does_not_trip_watchdog():
    arm = make_arm()
    arm.step(5.0)
    assert arm.state().fault is None


def test_sim_arm_protective_stop_halts_within_one_period_and_refuses_motion():
    arm = make_arm()
    V = np.array([0.0, 0.1, -0.05, 0.0, 0.0, 0.2])
    stream(arm, V, 0.5)
    arm.inject_protective_stop()
    arm.step(PERIOD)
    state = arm.state()
    assert state.protective_stop and state.fault_reason == "protective stop"
    assert np.all(state.V_BE == 0.0)
    q_held = state.q
    with pytest.raises(DeviceFault, match="protective stop"):
        arm.servo(ServoCommand(arm.time, V))
    arm.stop()  # stopping a stopped arm is harmless
    arm.step(0.5)
    assert np.array_equal(arm.state().q, q_held)
    arm.unlock_protective_stop()
    assert not arm.state().protective_stop
    arm.step(0.1)
    assert np.array_equal(arm.state().q, q_held)  # the old command does not resume
    stream(arm, V, 0.2)
    assert np.linalg.norm(arm.state().V_BE) > 0


def test_sim_arm_injected_fault_halts_within_one_period():
    arm = make_arm()
    stream(arm, np.array([0.1, 0.0, 0.0, 0.0, 0.0, 0.0]), 0.3)
    arm.inject_fault("joint 3 overcurrent")
    arm.step(PERIOD)
    state = arm.state()
    assert state.fault == "joint 3 overcurrent"
    assert np.all(state.V_BE == 0.0)
    with pytest.raises(DeviceFault, match="joint 3 overcurrent"):
        arm.servo(ServoCommand(arm.time, np.zeros(6)))


def test_sim_arm_emergency_stop_reported_and_refuses_motion():
    arm = make_arm()
    arm.inject_emergency_stop()
    assert arm.state().fault_reason == "emergency stop"
    with pytest.raises(DeviceFault, match="emergency stop"):
        arm.servo(ServoCommand(arm.time, np.zeros(6)))
    arm.release_emergency_stop()
    arm.servo(ServoCommand(arm.time, np.zeros(6)))


@pytest.mark.parametrize("deceleration", [0.5, 2.0])
def test_sim_arm_stop_decelerates_to_rest_in_expected_time(deceleration):
    arm = make_arm()
    V = np.array([0.0, 0.0, 0.2, 0.0, 0.0, 0.0])
    stream(arm, V, 0.5)
    arm.stop(deceleration)
    expected = 0.2 / deceleration
    speeds = []
    t0 = arm.time
    while arm.time - t0 < expected + 0.05:
        arm.step(PERIOD)
        speeds.append((arm.time - t0, np.linalg.norm(arm.state().V_BE[:3])))
    t, v = np.array(speeds).T
    # linear ramp: v(t) = 0.2 − a·t until rest; at rest from the expected time on
    assert v[t < expected - PERIOD] == pytest.approx(
        np.clip(0.2 - deceleration * t[t < expected - PERIOD], 0, None), abs=0.2 * 0.02
    )
    assert np.all(v[t >= expected + PERIOD] < 1e-9)
    assert np.all(np.diff(v) <= 1e-9)  # monotone, no overshoot
    arm.step(1.0)
    assert arm.state().fault is None  # an ordered stop disarms the watchdog


def test_sim_arm_halt_command_stops_like_stop():
    arm = make_arm()
    stream(arm, np.array([0.1, 0.0, 0.0, 0.0, 0.0, 0.0]), 0.3)
    arm.servo(ServoCommand.halt(arm.time, "estimate lost"))
    arm.step(0.1)
    assert np.linalg.norm(arm.state().V_BE) < 1e-9


def test_sim_arm_stop_rejects_bad_deceleration():
    arm = make_arm()
    with pytest.raises(ValueError, match="deceleration"):
        arm.stop(0.0)


def test_sim_arm_dropped_link_raises_timeout_and_watchdog_stops_arm():
    arm = make_arm()
    V = np.array([0.1, 0.0, 0.0, 0.0, 0.0, 0.0])
    stream(arm, V, 0.3)
    arm.drop_link()
    with pytest.raises(DeviceTimeout, match="link dropped"):
        arm.state()
    with pytest.raises(DeviceTimeout):
        arm.servo(ServoCommand(arm.time, V))
    with pytest.raises(DeviceTimeout):
        arm.stop()
    arm.step(0.5)  # nobody reaches the controller: its watchdog stops the arm
    arm.restore_link()
    state = arm.state()
    assert state.fault == "watchdog" and np.linalg.norm(state.V_BE) < 1e-9


def test_sim_arm_requires_connect():
    arm = SimArm(RIG.arm)
    with pytest.raises(DeviceError, match="not connected"):
        arm.state()


def test_sim_arm_streams_only_while_active_and_stops_on_deactivate():
    arm = SimArm(RIG.arm)
    arm.connect()
    twist = ServoCommand(0.0, np.array([0.1, 0.0, 0.0, 0.0, 0.0, 0.0]))
    with pytest.raises(DeviceError, match="not active"):
        arm.servo(twist)
    arm.activate()
    arm.servo(twist)
    arm.step(0.08)  # within the 0.1 s watchdog
    assert np.linalg.norm(arm.state().V_BE[:3]) > 0.05
    arm.deactivate()
    arm.step(0.5)
    assert np.linalg.norm(arm.state().V_BE) < 1e-9  # stopped, and the state is still readable
    with pytest.raises(DeviceError, match="not active"):
        arm.servo(twist)
    arm.inject_protective_stop()
    with pytest.raises(DeviceFault, match="protective stop"):
        arm.activate()


def test_sim_arm_ramps_at_the_commands_own_acceleration():
    arm = make_arm()
    arm.servo(ServoCommand(0.0, np.array([0.2, 0.0, 0.0, 0.0, 0.0, 0.0]), acceleration=0.1))
    arm.step(0.08)  # within the 0.1 s watchdog; the configured ramp would reach 0.08 m/s
    assert np.linalg.norm(arm.state().V_BE[:3]) == pytest.approx(0.008, abs=0.001)


def test_sim_arm_moves_only_when_stepped_and_stamps_with_injected_clock():
    now = [100.0]
    arm = SimArm(RIG.arm, clock=lambda: now[0])
    arm.connect()
    arm.activate()
    arm.servo(ServoCommand(0.0, np.array([0.1, 0.0, 0.0, 0.0, 0.0, 0.0])))
    q = arm.state().q
    assert np.array_equal(arm.state().q, q)  # no wall-clock motion
    arm.step(0.003)  # one 2 ms period runs, 1 ms is kept for the next step
    assert arm.time == pytest.approx(0.003)
    assert not np.array_equal(arm.state().q, q)
    assert arm.state().stamp == 100.0


def test_sim_arm_stops_at_joint_range_margin():
    # wrist 3 near its +360° limit, turned further about the flange's own axis
    q0 = [164.04, -55.73, 118.22, 117.52, -74.04, 345.0]
    arm = make_arm(q0_deg=q0, joint_limit_margin_deg=5.0, tcp_angular_acceleration_deg_s2=500.0)
    axis_B = arm.state().X_BE.R[:, 2]
    V = np.concatenate([np.zeros(3), 0.5 * axis_B])  # about the flange's z: wrist 3 positive
    stream(arm, V, 2.0)
    q6 = math.degrees(arm.state().q[5])
    assert q6 <= 355.0 + 1e-3
    assert q6 > 354.0  # it got there, and stopped
    assert np.linalg.norm(arm.state().V_BE) < 1e-6
    assert any("joint 6 range" in r for r in arm.limited_by)


def test_sim_arm_camera_pose_composes_hand_eye():
    arm = make_arm()
    state = arm.state()
    X_WC = arm.camera_pose_W()
    expected = RIG.arm.X_WB.pose @ state.X_BE @ RIG.arm.X_EC.pose
    assert X_WC.is_close(expected, atol_m=1e-12, atol_rad=1e-12)
    # camera twist: finite difference of the camera pose under a pure rotation
    V = np.array([0.0, 0.0, 0.0, 0.0, 0.3, 0.0])
    stream(arm, V, 0.5)
    twist_C = arm.camera_twist_C()
    X0 = arm.camera_pose_W()
    arm.servo(ServoCommand(arm.time, V))
    arm.step(PERIOD)
    X1 = arm.camera_pose_W()
    v_W = (X1.p - X0.p) / PERIOD
    assert X0.R.T @ v_W == pytest.approx(twist_C[:3], abs=2e-3)


def test_sim_arm_rejects_speed_limits_above_the_model():
    config = RIG.arm.model_copy(update={"joint_speed_limit_deg_s": (130, 120, 180, 180, 180, 180)})
    with pytest.raises(ValueError, match=r"joint_speed_limit_deg_s\[0\].*120"):
        SimArm(config)
