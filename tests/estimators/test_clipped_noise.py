import numpy as np
import pytest
from scipy.stats import norm

from estimators.clipped_noise import (
    clipped_likelihood_terms,
    clipped_log_likelihood,
    clipped_moments,
)


def _log_likelihood(value: float, intensity: float, sigma: float) -> float:
    """log p(value | intensity) of Gaussian noise clipped to [0, 1] (a Tobit model)."""
    if value <= 0.5 / 255:
        return norm.logcdf(-intensity / sigma)
    if value >= 1 - 0.5 / 255:
        return norm.logcdf((intensity - 1) / sigma)
    return norm.logpdf(value, intensity, sigma)


@pytest.mark.parametrize("value", [0.0, 0.3, 1.0])
@pytest.mark.parametrize("intensity", [-0.1, 0.05, 0.5, 0.97])
def test_score_and_information_are_the_derivatives_of_the_log_likelihood(value, intensity):
    sigma, h = 0.2, 1e-4
    score, info = clipped_likelihood_terms(np.array([value]), np.array([intensity]), sigma)
    ll = [_log_likelihood(value, intensity + k * h, sigma) for k in (-1, 0, 1)]
    assert score[0] == pytest.approx((ll[2] - ll[0]) / (2 * h), rel=1e-5, abs=1e-6)
    assert info[0] == pytest.approx(-(ll[2] - 2 * ll[1] + ll[0]) / h**2, rel=1e-3, abs=1e-3)


@pytest.mark.parametrize("value", [0.0, 0.3, 1.0])
@pytest.mark.parametrize("intensity", [-0.1, 0.05, 0.5, 0.97])
def test_the_compiled_log_likelihood_differs_from_the_tobit_one_by_a_constant(value, intensity):
    # A line search compares it between intensities: only differences matter.
    sigma = 0.2
    reference = _log_likelihood(value, 0.4, sigma) - clipped_log_likelihood(value, 0.4, sigma)
    assert _log_likelihood(value, intensity, sigma) - clipped_log_likelihood(
        value, intensity, sigma
    ) == pytest.approx(reference, abs=1e-9)


def test_without_noise_the_terms_are_least_squares():
    score, info = clipped_likelihood_terms(np.array([0.2, 0.9]), np.array([0.3, 0.5]), 0.0)
    np.testing.assert_allclose(score, [-0.1, 0.4])
    np.testing.assert_allclose(info, [1.0, 1.0])


def test_clipped_moments_match_a_simulated_sensor():
    rng = np.random.default_rng(0)
    intensity, sigma = np.array([0.02, 0.4, 0.95]), 0.2
    shown = np.clip(intensity[:, None] + rng.normal(0, sigma, (3, 200_000)), 0, 1)
    mean, variance, unclipped = clipped_moments(intensity, sigma)
    np.testing.assert_allclose(mean, shown.mean(axis=1), atol=2e-3)
    np.testing.assert_allclose(variance, shown.var(axis=1), atol=2e-3)
    np.testing.assert_allclose(unclipped, ((shown > 0) & (shown < 1)).mean(axis=1), atol=3e-3)
