import numpy as np
import pytest

from configuration.rig import load_rig
from sim_backends.arm import SimArm
from sim_backends.rig_geometry import (
    camera_box,
    camera_pose_W,
    reach_check,
    target_pose_W,
    track_position_at_distance,
    view_of_target,
)
from sim_backends.track import TrackModel

RIG = load_rig()


def test_rig_start_puts_ring_2_5_m_ahead_facing_the_camera():
    view = view_of_target(
        camera_pose_W(RIG.arm), target_pose_W(RIG.track, RIG.track.start_position)
    )
    assert view.distance == pytest.approx(2.5, abs=0.02)
    assert view.off_axis < 0.01
    assert view.tilt_deg < 0.5


def test_rig_track_reaches_the_standoff_within_its_travel():
    standoff = track_position_at_distance(RIG, 0.5)
    assert RIG.track.travel_min <= standoff < RIG.track.travel_max
    view = view_of_target(camera_pose_W(RIG.arm), target_pose_W(RIG.track, RIG.track.travel_max))
    assert view.distance <= 0.5  # the travel goes a little past the stand-off


def test_rig_arm_covers_the_approach_box_with_margin():
    box = camera_box()
    assert len(box) == 243
    check = reach_check(RIG.arm, box)
    assert check.failures == 0
    assert check.sigma_min > 0.2  # far from singular everywhere in the box
    assert check.extension_max < 0.9  # never close to stretched out
    assert check.joint_margin_min_deg > 30


def test_rig_geometry_agrees_with_the_simulated_devices():
    arm = SimArm(RIG.arm)
    track = TrackModel(RIG.track)
    assert arm.camera_pose_W().is_close(camera_pose_W(RIG.arm), atol_m=1e-12, atol_rad=1e-12)
    assert track.X_WT().is_close(
        target_pose_W(RIG.track, RIG.track.start_position), atol_m=1e-12, atol_rad=1e-12
    )
    # the ring's optical-axis distance falls one for one with the track position
    X_WC = camera_pose_W(RIG.arm)
    d = [view_of_target(X_WC, target_pose_W(RIG.track, s)).distance for s in (0.0, 1.0)]
    assert d[0] - d[1] == pytest.approx(np.linalg.norm(RIG.track.axis_W), abs=1e-3)
