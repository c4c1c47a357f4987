"""Normalised estimation errors squared of a measurement under its own covariances."""

import numpy as np
import pytest

from configuration.mockup import load_mockup
from estimators.conics import circle_plane_basis
from estimators.geometry import Pose
from estimators.measurement import Measurement
from hil.evaluation.errors import measurement_error

TARGET = load_mockup("default").target_model()


def test_measurement_error_nees_follows_the_covariance_conventions():
    X_true = Pose.from_rpy(np.pi, 0.1, 0.2, np.array([0.05, 0.0, 2.0]))
    # 1 mm off along x and 2 mrad about C's z (rotation applied on the left, in C).
    turn = Pose.from_rotvec(np.array([0.0, 0.0, -0.002]), np.zeros(3)).R
    X_est = Pose(turn @ X_true.R, X_true.p - [0.001, 0.0, 0.0])
    covariance = np.diag([1e-6, 1e-6, 1e-6, 1e-6, 1e-6, 1e-6])  # 1 mrad, 1 mm
    ring = TARGET.circle("ring_outer")
    n_est = X_true.R @ ring.normal_T + 0.003 * circle_plane_basis(X_true.R @ ring.normal_T)[0]
    m = Measurement(
        system="ellipses",
        status="tracking",
        stamp=0.0,
        seq=0,
        X_CT=X_est,
        covariance=covariance,
        circle="ring_outer",
        center_C=X_true.apply(ring.center_T) + [0.0, 0.002, 0.0],
        normal_C=n_est / np.linalg.norm(n_est),
        covariance_5dof=np.diag([1e-6, 1e-6, 1e-6, 1e-6, 1e-6]),
    )
    e = measurement_error(m, X_true, TARGET)
    assert e.nees_pose == pytest.approx(1.0 + 4.0, rel=1e-3)  # (1 mm)² + (2 mrad)²
    assert e.nees_circle == pytest.approx(4.0 + 9.0, rel=1e-2)  # (2 mm)² + (3 mrad)²
