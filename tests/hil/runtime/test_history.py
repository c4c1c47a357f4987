"""Where the camera was at a frame's capture: the arm/track history and the shared state ring."""

import math

import numpy as np
import pytest

from estimators.geometry import Pose
from hil.runtime.history import (
    StampedSeries,
    StateHistory,
    StateRing,
    StateSample,
    interpolate_pose,
)
from hil.runtime.rig import RigGeometry

GEOMETRY = RigGeometry(
    X_WB=Pose.identity(),
    X_EC=Pose.from_rpy(0.0, 0.0, math.pi / 2, np.array([0.0, 0.05, 0.08])),
    track_axis_W=np.array([1.0, 0.0, 0.0]),
    X_WM0=Pose.from_rpy(0.0, -math.pi / 2, 0.0, np.array([3.0, 0.0, 1.0])),
    max_track_speed=0.3,
)


def test_interpolate_pose_moves_linearly_and_turns_at_a_constant_rate():
    X0 = Pose.identity()
    X1 = Pose.from_rotvec(np.array([0.0, 0.0, 0.4]), np.array([1.0, -2.0, 0.5]))
    X = interpolate_pose(X0, X1, 0.25)
    assert np.allclose(X.p, [0.25, -0.5, 0.125])
    assert np.allclose(X.rotvec, [0.0, 0.0, 0.1])


def test_stamped_series_interpolates_inside_and_refuses_outside():
    series = StampedSeries(lambda a, b, s: (1 - s) * a + s * b, horizon_s=1.0)
    for k in range(30):
        series.add(k / 10, float(k))
    assert series.at(2.05) == pytest.approx(20.5)
    assert series.at(1.5) is None  # older than the 1 s history
    assert series.at(2.9 + 0.04) == 29.0  # just after the newest: the newest
    assert series.at(2.9 + 0.06) is None  # too far ahead to extrapolate
    series.add(2.9, 99.0)  # the same stamp again replaces
    assert series.at(2.9) == 99.0
    with pytest.raises(ValueError, match="increase"):
        series.add(2.0, 0.0)


def test_state_history_gives_the_camera_to_carriage_pose_of_a_past_instant():
    """An arm turning and a track moving at constant rates: X_CM halfway between two samples is
    the one of the halfway instant, not the newest."""
    history = StateHistory(GEOMETRY)
    X_BE0 = Pose.from_rpy(0.1, 0.2, 0.3, np.array([0.5, 0.1, 0.6]))

    def X_BE(t: float) -> Pose:
        return (
            Pose.from_rotvec(np.array([0.0, 0.3 * t, 0.0]), np.array([0.2 * t, 0.0, 0.0])) @ X_BE0
        )

    for k in range(11):
        t = 0.008 * k
        history.add(StateSample(t, X_BE(t), t + 0.001, 0.25 * t))
    stamp = 0.044  # between samples; the track's stamps run 1 ms behind the arm's
    expected = GEOMETRY.X_CM(X_BE(stamp), 0.25 * (stamp - 0.001))
    assert history.X_CM_at(stamp).is_close(expected, atol_m=2e-6, atol_rad=2e-6)
    assert not history.X_CM_at(stamp).is_close(history.X_CM_at(0.08), atol_m=1e-3)
    assert history.X_CM_at(-1.0) is None


def test_state_ring_delivers_every_sample_once_and_the_newest_when_behind():
    writer = StateRing(capacity=8)
    reader = StateRing(writer.name, capacity=8)
    try:
        X = Pose.from_rpy(0.1, -0.2, 0.3, np.array([1.0, 2.0, 3.0]))
        for k in range(3):
            writer.write(StateSample(float(k), X, k + 0.5, 0.1 * k))
        got = reader.read_new()
        assert [s.arm_stamp for s in got] == [0.0, 1.0, 2.0]
        assert got[1].X_BE.is_close(X, atol_m=0, atol_rad=1e-15) and got[2].track_position == 0.2
        assert reader.read_new() == []
        for k in range(3, 23):  # the reader falls 20 samples behind an 8-slot ring
            writer.write(StateSample(float(k), X, k + 0.5, 0.1 * k))
        assert [s.arm_stamp for s in reader.read_new()] == [float(k) for k in range(16, 23)]
    finally:
        reader.close()
        writer.close()
