import itertools

import numpy as np
import pytest
from scipy import stats

from configuration.render import NoiseConfig
from estimators.geometry import Pose, intrinsics_from_fov, project
from sim_backends.sensor import (
    AUTO_EXPOSURE_GAIN_RANGE,
    NoisePool,
    add_noise,
    auto_exposure_gain,
    expose,
    frame_rng,
    image_flow,
    motion_blur,
    to_uint8,
)

K = intrinsics_from_fov(640, 480, 70.0)


def clipped_gaussian_variance(mean: float, sigma: float) -> float:
    """Variance of clip(mean + σ·N(0,1), 0, 1), by numerical integration."""
    x = np.linspace(-12, 12, 200001)
    values = np.clip(mean + sigma * x, 0.0, 1.0)
    w = stats.norm.pdf(x)
    w /= w.sum()
    m = (w * values).sum()
    return float((w * (values - m) ** 2).sum())


@pytest.mark.parametrize(("preset", "variance"), [("low", 0.05), ("high", 0.1)])
def test_noise_presets_reproduce_their_variance(preset, variance):
    noise = NoiseConfig(preset=preset)
    assert noise.gaussian_variance == variance
    # On [0, 1] intensities the noise is clipped: at mid-grey the measured variance must match
    # that of a clipped Gaussian with the preset's σ.
    rng = frame_rng(7, 0)
    level = np.full((480, 640), 0.5, dtype=np.float32)
    noisy = add_noise(level, noise, rng)
    expected_clipped = clipped_gaussian_variance(0.5, np.sqrt(variance))
    assert noisy.var() == pytest.approx(expected_clipped, rel=0.05)
    # Quantised to 8 bits, as a camera delivers it, the variance is unchanged within 5 %.
    assert (to_uint8(noisy) / 255.0).var() == pytest.approx(expected_clipped, rel=0.05)


@pytest.mark.parametrize(("preset", "variance"), [("low", 0.05), ("high", 0.1)])
def test_noise_field_before_clipping_has_the_preset_variance(preset, variance):
    """The additive field is N(0, variance): measured with σ scaled down 10× so that clipping
    cannot bite, and scaled back up."""
    noise = NoiseConfig(preset=preset)
    rng = frame_rng(3, 1)
    sigma = np.sqrt(variance)
    scaled = NoiseConfig(preset=preset, variance=variance / 100.0)
    noisy = add_noise(np.full((480, 640), 0.5, dtype=np.float32), scaled, rng)
    assert (noisy - 0.5).var() * 100.0 == pytest.approx(variance, rel=0.05)
    assert (noisy - 0.5).mean() == pytest.approx(0.0, abs=0.01 * sigma)
    assert noise.preset == preset


def test_noise_none_leaves_the_image_and_sensor_noise_follows_photon_transfer():
    image = np.full((200, 300), 0.4, dtype=np.float32)
    assert np.array_equal(add_noise(image, NoiseConfig(preset="none"), frame_rng(0)), image)
    sensor = NoiseConfig(preset="sensor", full_well_e=5000.0, read_noise_e=10.0)
    noisy = add_noise(image, sensor, frame_rng(1))
    expected = (0.4 * 5000.0 + 10.0**2) / 5000.0**2
    assert noisy.var() == pytest.approx(expected, rel=0.05)
    assert noisy.mean() == pytest.approx(0.4, abs=1e-3)


def test_same_seed_same_frame_and_different_seed_different_frame():
    image = np.random.default_rng(0).uniform(0, 1, (48, 64)).astype(np.float32)
    depth = np.full((48, 64), 2.0, dtype=np.float32)
    noise = NoiseConfig(preset="low")
    a = expose(image, depth, K, noise, frame_rng(5, 3))
    b = expose(image, depth, K, noise, frame_rng(5, 3))
    c = expose(image, depth, K, noise, frame_rng(5, 4))
    d = expose(image, depth, K, noise, frame_rng(6, 3))
    assert a.dtype == np.uint8
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c) and not np.array_equal(a, d)


def test_image_flow_matches_finite_differences_of_projection():
    """The interaction-matrix flow equals the motion of projected points under the twist."""
    rng = np.random.default_rng(2)
    twist = np.array([0.05, -0.03, 0.2, 0.04, -0.06, 0.1])
    depth = np.full((480, 640), 1.7, dtype=np.float32)
    flow_u, flow_v = image_flow(depth, K, twist)
    dt = 1e-5
    # The camera moves by the twist: points in C move by −(v + ω × p) dt.
    X_C1C0 = Pose.from_rotvec(-twist[3:] * dt, -twist[:3] * dt)
    for u, v in rng.integers([0, 0], [640, 480], size=(20, 2)):
        ray = np.array([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], 1.0])
        p0 = ray * 1.7
        uv1 = project(X_C1C0.apply(p0)[None], K)[0]
        numeric = (uv1 - [u, v]) / dt
        assert numeric == pytest.approx([flow_u[v, u], flow_v[v, u]], rel=1e-3, abs=1e-2)


def test_motion_blur_smears_an_edge_along_the_flow():
    image = np.zeros((100, 200), dtype=np.float32)
    image[:, 100:] = 1.0
    depth = np.full((100, 200), 1.0, dtype=np.float32)
    Kc = np.array([[100.0, 0, 99.5], [0, 100.0, 49.5], [0, 0, 1]])
    twist = np.array([-1.0, 0.0, 0.0, 0.0, 0.0, 0.0])  # flow +100 px/s in u
    blurred = motion_blur(image, depth, Kc, twist, exposure_s=0.1)  # 10 px smear
    row = blurred[50]
    ramp = np.flatnonzero((row > 0.02) & (row < 0.98))
    assert 7 <= len(ramp) <= 12
    assert row[95:105].mean() == pytest.approx(0.5, abs=0.1)
    assert np.array_equal(motion_blur(image, depth, Kc, np.zeros(6), 0.1), image)


def test_auto_exposure_brings_a_dim_targets_highlights_near_full_scale_and_meters_only_it():
    """A dim mock-up (its brightest pixels at 0.2) on black space, and a bright lamp outside the
    target's depth mask: the gain meters the mock-up's pixels alone, and the recorded frame's
    mock-up reaches 0.9 at its 99th percentile; the contrast between its parts scales with it."""
    image = np.zeros((100, 100), dtype=np.float32)
    depth = np.full((100, 100), np.inf, dtype=np.float32)
    image[20:80, 20:80] = 0.1  # the face
    image[40:60, 40:60] = 0.2  # a brighter panel on it
    depth[20:80, 20:80] = 2.0
    image[0:5, 0:5] = 1.0  # a lamp in the background, not the target
    assert auto_exposure_gain(image, depth) == pytest.approx(4.5)
    off = expose(image, depth, K, NoiseConfig(), frame_rng(0))
    on = expose(image, depth, K, NoiseConfig(auto_exposure=True), frame_rng(0))
    assert off[50, 50] == to_uint8(np.float32(0.2))
    assert on[50, 50] == to_uint8(np.float32(0.9))
    assert int(on[50, 50]) - int(on[25, 25]) == pytest.approx(4.5 * (int(off[50, 50]) - 25), abs=2)
    assert on[2, 2] == 255  # the lamp saturates: it is not what was metered
    # Without a depth the non-black pixels are metered; the gain stays in the camera's range.
    assert auto_exposure_gain(image * 0.001, None) == AUTO_EXPOSURE_GAIN_RANGE[1]
    assert auto_exposure_gain(np.zeros((4, 4), np.float32), None) == 1.0


def test_to_uint8_rounds_ties_to_even_and_saturates_as_numpy_would_for_any_shape():
    halves = np.arange(-4, 516) / 510.0  # every tie k + 1/2 of the 8-bit scale, and beyond
    values = np.concatenate([halves, np.nextafter(halves, 2), np.nextafter(halves, -2)])
    values = values.astype(np.float32)
    expected = np.clip(np.rint(values * np.float32(255.0)), 0, 255).astype(np.uint8)
    assert expected[4] == 0 and expected[5] == 0 and expected[7] == 2  # ties to even
    for shape in ((-1,), (-1, 3), (-1, 6, 1)):
        n = len(values) // 6 * 6
        got = to_uint8(values[:n].reshape(shape))
        assert got.dtype == np.uint8 and got.shape == values[:n].reshape(shape).shape
        assert np.array_equal(got.ravel(), expected[:n])
    assert to_uint8(np.float32(1.7)) == 255 and to_uint8(np.float32(-0.3)) == 0


def test_a_noise_pool_gives_each_frame_white_noise_of_its_own():
    pool = NoisePool(seed=3)
    frames = [pool.standard_normal((120, 160, 3)).copy() for _ in range(12)]
    for noise in frames:
        assert noise.dtype == np.float32 and noise.shape == (120, 160, 3)
        assert abs(noise.mean()) < 0.02 and noise.std() == pytest.approx(1.0, rel=0.02)
        # white: neighbouring pixels uncorrelated
        assert abs(np.corrcoef(noise[:, :-1].ravel(), noise[:, 1:].ravel())[0, 1]) < 0.02
    for a, b in itertools.pairwise(frames):  # a pixel's noise differs frame to frame
        assert abs(np.corrcoef(a.ravel(), b.ravel())[0, 1]) < 0.02
    # the sensor model takes it where it takes a frame's generator: the preset's σ at mid-grey
    level = np.full((480, 640), 0.5, dtype=np.float32)
    noisy = add_noise(level, NoiseConfig(preset="low"), NoisePool(seed=1))
    assert noisy.var() == pytest.approx(clipped_gaussian_variance(0.5, np.sqrt(0.05)), rel=0.05)
    with pytest.raises(ValueError, match="float32"):
        pool.standard_normal((4, 4), dtype=np.float64)
