"""The Cramér–Rao bound per system's features and for all of them."""

import math

import numpy as np
import pytest

from hil.evaluation.crb import bound, mean_error_bound


def test_bound_of_all_features_is_below_every_single_system():
    single = [bound(s, "low", 2.0) for s in ("corners", "lines", "ellipses")]
    together = bound("all", "low", 2.0)
    assert together.depth_sigma_m <= min(b.depth_sigma_m for b in single)
    assert together.tilt_sigma_deg <= min(b.tilt_sigma_deg for b in single)


def test_bound_scales_with_the_noise_sigma():
    low, high = bound("lines", "low", 3.0), bound("lines", "high", 3.0)
    assert np.sqrt(high.covariance[5, 5] / low.covariance[5, 5]) == pytest.approx(
        math.sqrt(0.1 / 0.05), rel=1e-6
    )


def test_mean_error_bound_has_none_without_noise_and_maps_fused_to_all():
    assert mean_error_bound("corners", "none", 2.0) is None
    assert mean_error_bound("fused", "low", 2.0) == pytest.approx(
        (bound("all", "low", 2.0).translation_mean_m, bound("all", "low", 2.0).rotation_mean_deg)
    )
