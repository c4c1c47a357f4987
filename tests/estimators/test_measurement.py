import numpy as np
import pytest

from estimators.frame import CameraInfo, Frame
from estimators.geometry import Pose, intrinsics_from_fov
from estimators.measurement import Measurement, Tracker

INFO = CameraInfo(640, 480, intrinsics_from_fov(640, 480, 70.0), np.zeros(0), "reference")
FRAME = Frame(np.zeros((480, 640), np.uint8), 1.5, INFO, 7)


def test_lost_measurement_needs_a_reason_and_no_pose():
    m = Measurement.lost("corners", FRAME, "no panel found")
    assert (m.status, m.stamp, m.seq, m.valid) == ("lost", 1.5, 7, False)
    with pytest.raises(ValueError, match="say why"):
        Measurement(system="corners", status="lost", stamp=0.0, seq=0)
    with pytest.raises(ValueError, match="carries no pose"):
        Measurement(
            system="corners",
            status="lost",
            stamp=0.0,
            seq=0,
            reason="x",
            X_CT=Pose.identity(),
            covariance=np.eye(6),
        )


def test_valid_measurement_needs_pose_and_covariance():
    with pytest.raises(ValueError, match="needs X_CT or center_C"):
        Measurement(system="lines", status="tracking", stamp=0.0, seq=0)
    with pytest.raises(ValueError, match="6x6 covariance"):
        Measurement(system="lines", status="tracking", stamp=0.0, seq=0, X_CT=Pose.identity())
    with pytest.raises(ValueError, match="NaN"):
        Measurement(
            system="lines",
            status="tracking",
            stamp=0.0,
            seq=0,
            X_CT=Pose.identity(),
            covariance=np.full((6, 6), np.nan),
        )
    with pytest.raises(ValueError, match="unit vector"):
        Measurement(
            system="ellipses",
            status="acquired",
            stamp=0.0,
            seq=0,
            circle="ring_outer",
            center_C=np.zeros(3),
            normal_C=np.array([0, 0, 2.0]),
            covariance_5dof=np.eye(5),
        )
    with pytest.raises(ValueError, match="status"):
        Measurement(system="lines", status="found", stamp=0.0, seq=0, reason="x")


def test_to_dict_is_json_ready():
    import json

    m = Measurement(
        system="ellipses",
        status="acquired",
        stamp=0.0,
        seq=0,
        circle="ring_outer",
        center_C=np.array([0, 0, 2.0]),
        normal_C=np.array([0, 0, -1.0]),
        covariance_5dof=np.eye(5),
    )
    record = json.loads(json.dumps(m.to_dict()))
    assert (
        record["X_CT"] is None
        and record["center_C"] == [0, 0, 2.0]
        and record["residual_px"] is None
    )


def test_from_dict_inverts_to_dict_through_json():
    import json

    X_CT = Pose.from_rpy(0.1, -0.2, 0.3, np.array([0.01, -0.02, 1.5]))
    m = Measurement(
        system="ellipses",
        status="tracking",
        stamp=2.5,
        seq=9,
        X_CT=X_CT,
        covariance=np.diag([1e-4, 1e-4, 1e-4, 1e-6, 1e-6, 1e-5]),
        circle="ring_outer",
        center_C=np.array([0.01, -0.02, 1.5]),
        normal_C=np.array([0.0, 0.6, -0.8]),
        covariance_5dof=np.eye(5) * 1e-6,
        residual_px=0.31,
        time_ms=4.2,
    )
    back = Measurement.from_dict(json.loads(json.dumps(m.to_dict())))
    assert back.X_CT.is_close(X_CT, atol_m=0.0, atol_rad=1e-15)
    assert np.array_equal(back.covariance, m.covariance)
    assert np.array_equal(back.normal_C, m.normal_C)
    assert (back.system, back.status, back.stamp, back.seq, back.circle) == (
        "ellipses",
        "tracking",
        2.5,
        9,
        "ring_outer",
    )
    assert (back.residual_px, back.time_ms) == (0.31, 4.2)
    lost = Measurement.from_dict(Measurement.lost("lines", FRAME, "no edges").to_dict())
    assert lost.status == "lost" and lost.reason == "no edges" and np.isnan(lost.residual_px)
    with pytest.raises(ValueError, match="carries no pose"):
        Measurement.from_dict({**m.to_dict(), "status": "lost", "reason": "x"})


def test_tracker_carries_the_prior_and_drops_it_on_loss():
    seen = []

    class Scripted:
        system = "scripted"

        def __init__(self):
            self.outcomes = iter([True, True, False, True])

        def estimate(self, frame, prior_X_CT=None):
            seen.append(prior_X_CT)
            if next(self.outcomes):
                return Measurement(
                    system=self.system,
                    status="tracking" if prior_X_CT else "acquired",
                    stamp=frame.stamp,
                    seq=frame.seq,
                    X_CT=Pose(np.eye(3), [0, 0, 2.0 + frame.seq]),
                    covariance=np.eye(6),
                )
            return Measurement.lost(self.system, frame, "gone")

    tracker = Tracker(Scripted())
    statuses = [tracker.update(Frame(FRAME.image, float(i), INFO, i)).status for i in range(4)]
    assert statuses == ["acquired", "tracking", "lost", "acquired"]
    assert seen[0] is None and seen[1].p[2] == 2.0 and seen[2].p[2] == 3.0 and seen[3] is None
