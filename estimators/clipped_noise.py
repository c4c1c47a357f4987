"""Gaussian noise clipped by the sensor at black and white: the moments of what a pixel shows,
and the terms of its likelihood (a Tobit model — J. Tobin, "Estimation of relationships for
limited dependent variables", Econometrica 26(1), 1958).

Each formula is written once, for one pixel, and compiled with numba: the per-pixel fits of
edges and discs (``edge_fit``, ``point_fit``) call the scalar forms inside their own compiled
loops, and NumPy callers use the array forms. Compiled because these run on every pixel of
every band at every iteration of a fit: as NumPy expressions their temporaries cost more than
their arithmetic (issue 12's profile: a quarter of the line system's time).
"""

from __future__ import annotations

import math

import numpy as np

from estimators.compiled import compiled, compiled_inline

_SQRT_2PI = math.sqrt(2.0 * math.pi)
_INV_SQRT2 = 1.0 / math.sqrt(2.0)
#: Pixels this close to 0 or 1 are taken as clipped (an 8-bit sensor's 0 and 255).
CLIP_TOLERANCE = 0.5 / 255.0


@compiled_inline
def normal_cdf(z: float) -> float:
    """Φ(z), the standard normal distribution function."""
    return 0.5 * math.erfc(-z * _INV_SQRT2)


@compiled_inline
def normal_pdf(z: float) -> float:
    """φ(z), the standard normal density."""
    return math.exp(-0.5 * z * z) / _SQRT_2PI


#: Beyond this many edge widths from an edge a pixel lies wholly on one side: Φ is 1 to the
#: last bit above it, and Φ and φ below it (10⁻¹⁷ and less) are lost beside the other pixels'
#: terms of a fit.
SATURATED_Z = 8.5


@compiled_inline
def edge_coverage(z: float, s: float) -> tuple[float, float]:
    """Φ(z) and φ(z)/s: the share of a pixel z edge widths s inside a blurred edge, and its
    slope per pixel. Most pixels of a disc's window or a corner's lie beyond ``SATURATED_Z``
    of the edge, where the pair is (1, 0) or (0, 0) and the transcendental functions are
    skipped."""
    if z > SATURATED_Z:
        return 1.0, 0.0
    if z < -SATURATED_Z:
        return 0.0, 0.0
    return normal_cdf(z), normal_pdf(z) / s


@compiled
def clipped_terms(value: float, intensity: float, sigma: float) -> tuple[float, float]:
    """Score ∂ℓ/∂I and information −∂²ℓ/∂I² of one pixel's log-likelihood ℓ given its
    intensity I (see ``clipped_likelihood_terms``)."""
    if sigma <= 0.0:
        return value - intensity, 1.0
    if value <= CLIP_TOLERANCE:
        sign, a = -1.0, -intensity / sigma
    elif value >= 1.0 - CLIP_TOLERANCE:
        sign, a = 1.0, (intensity - 1.0) / sigma
    else:
        return (value - intensity) / (sigma * sigma), 1.0 / (sigma * sigma)
    # ℓ = log Φ(a) with a = −I/σ below black, (I − 1)/σ above white: ∂ℓ/∂I = ∓λ/σ and
    # −∂²ℓ/∂I² = λ(λ + a)/σ², λ = φ(a)/Φ(a).
    ratio = normal_pdf(a) / max(normal_cdf(a), 1e-300)
    return sign * ratio / sigma, ratio * (ratio + a) / (sigma * sigma)


@compiled
def clipped_log_likelihood(value: float, intensity: float, sigma: float) -> float:
    """One pixel's log-likelihood ℓ given its intensity I, up to a constant, whose score and
    information ``clipped_terms`` gives: −(v − I)²/2σ² where the pixel is not clipped,
    log Φ(−I/σ) at black and log Φ((I − 1)/σ) at white; σ = 0: −(v − I)²/2."""
    if sigma <= 0.0:
        return -0.5 * (value - intensity) * (value - intensity)
    if value <= CLIP_TOLERANCE:
        return math.log(max(normal_cdf(-intensity / sigma), 1e-300))
    if value >= 1.0 - CLIP_TOLERANCE:
        return math.log(max(normal_cdf((intensity - 1.0) / sigma), 1e-300))
    r = (value - intensity) / sigma
    return -0.5 * r * r


@compiled
def clipped_moment(intensity: float, sigma: float) -> tuple[float, float, float]:
    """Mean, variance and ∂mean/∂I of clip(I + n, 0, 1) for one intensity I (see
    ``clipped_moments``)."""
    if sigma <= 0.0:
        return intensity, 0.0, 1.0
    alpha = -intensity / sigma
    beta = (1.0 - intensity) / sigma
    # (a grey level far from black and white, the usual case, is not clipped at all)
    below, pdf_a = edge_coverage(alpha, 1.0)
    above, pdf_b = edge_coverage(beta, 1.0)
    inside = above - below
    mean = intensity * inside + sigma * (pdf_a - pdf_b) + (1.0 - above)
    second = (
        intensity * intensity * inside
        + 2.0 * intensity * sigma * (pdf_a - pdf_b)
        + sigma * sigma * (inside + alpha * pdf_a - beta * pdf_b)
        + (1.0 - above)
    )
    return mean, max(second - mean * mean, 0.0), inside


@compiled
def _terms_array(values, intensity, sigma):
    score = np.empty(len(values))
    info = np.empty(len(values))
    for i in range(len(values)):
        score[i], info[i] = clipped_terms(values[i], intensity[i], sigma)
    return score, info


@compiled
def _moments_array(intensity, sigma):
    n = len(intensity)
    mean, variance, inside = np.empty(n), np.empty(n), np.empty(n)
    for i in range(n):
        mean[i], variance[i], inside[i] = clipped_moment(intensity[i], sigma)
    return mean, variance, inside


def clipped_likelihood_terms(
    values: np.ndarray, intensity: np.ndarray, sigma: float
) -> tuple[np.ndarray, np.ndarray]:
    """Score ∂ℓ/∂I and information −∂²ℓ/∂I² of each pixel's log-likelihood ℓ given its
    intensity I, under Gaussian noise σ clipped at black and white (a Tobit model: a clipped
    pixel only says the intensity plus noise fell beyond the clip). The maximum-likelihood fit
    of a model of I is unbiased where least squares on the clipped values is not. σ = 0: the
    least-squares terms (v − I, 1)."""
    values = np.ascontiguousarray(values, dtype=float)
    intensity = np.ascontiguousarray(intensity, dtype=float)
    if values.shape != intensity.shape:
        values, intensity = (
            np.ascontiguousarray(a) for a in np.broadcast_arrays(values, intensity)
        )
    score, info = _terms_array(values.ravel(), intensity.ravel(), float(sigma))
    return score.reshape(values.shape), info.reshape(values.shape)


def clipped_moments(
    intensity: np.ndarray, sigma: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean, variance and ∂mean/∂intensity of clip(I + n, 0, 1) for n ~ N(0, σ²) — what a
    sensor that clips at black and white shows of intensity I (the derivative is the chance
    that the pixel is not clipped). σ = 0: I, 0 and 1."""
    intensity = np.asarray(intensity, dtype=float)
    flat = np.ascontiguousarray(intensity).ravel()
    mean, variance, inside = _moments_array(flat, float(sigma))
    return (
        mean.reshape(intensity.shape),
        variance.reshape(intensity.shape),
        inside.reshape(intensity.shape),
    )
