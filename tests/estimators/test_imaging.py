from dataclasses import replace

import numpy as np
import pytest

from configuration.camera import load_camera
from estimators.frame import Frame
from estimators.imaging import (
    ImageStack,
    estimate_noise_sigma,
    gray_frame,
    image_stack,
    percentile,
)

CAMERA = load_camera("reference").camera_info()


@pytest.mark.parametrize("sigma", [0.05, 0.22, 0.32])
def test_estimate_noise_sigma_recovers_additive_noise_on_a_structured_image(sigma):
    rng = np.random.default_rng(0)
    image = np.full((240, 320), 0.5, np.float32)
    image[60:180, 80:240] = 0.7  # edges must not fool it
    noisy = image + rng.normal(0.0, sigma, image.shape).astype(np.float32)
    # As a sensor shows it: clipped at black and white (at σ = 0.32 a fifth of the 0.7 grey is
    # clipped, which hides noise the estimate must account for).
    assert estimate_noise_sigma(np.clip(noisy, 0.0, 1.0)) == pytest.approx(sigma, rel=0.05)


def _structured_frame(seq: int = 0) -> Frame:
    rng = np.random.default_rng(1)
    pixels = np.full(CAMERA.shape, 0.3)
    pixels[100:300, 200:450] = 0.7
    pixels = np.clip(pixels + rng.normal(0, 0.1, CAMERA.shape), 0, 1)
    return Frame((pixels * 255).astype(np.uint8), 0.0, CAMERA, seq)


def test_image_stack_converts_and_measures_noise():
    image = image_stack(_structured_frame())
    assert isinstance(image, ImageStack)
    assert image.pixels.dtype == np.float32 and image.shape == CAMERA.shape
    assert image.noise_sigma == pytest.approx(0.1, rel=0.1)


def test_image_stack_is_prepared_once_per_frame_and_computes_each_product_once():
    frame = _structured_frame()
    stack = image_stack(frame)
    assert image_stack(frame) is stack  # a second system asking for the same frame
    assert image_stack(_structured_frame(1)) is not stack  # another frame: another stack
    assert stack.gradients(2.0) is stack.gradients(2.0)
    assert stack.gradients(2.0).smoothed is stack.smoothed(2.0)
    assert stack.reduced(2) is stack.reduced(2) and stack.reduced(2).shape == (240, 320)
    assert stack.reduced(2)[0, 0] == pytest.approx(stack.pixels[:2, :2].mean())
    assert stack.gradient_field(1.5, (10, 20, 100, 80)) is stack.gradient_field(
        1.5, (10, 20, 100, 80)
    )


def test_a_region_gradient_field_equals_the_whole_images_inside_the_region():
    stack = image_stack(_structured_frame())
    x0, y0, x1, y1 = 180, 90, 260, 140
    region = stack.gradient_field(1.5, (x0, y0, x1, y1))
    whole = ImageStack(stack.pixels, stack.noise_sigma).gradient_field(1.5)
    inside = region.gxy[y0 - region.y0 : y1 - region.y0, x0 - region.x0 : x1 - region.x0]
    assert region.noise == pytest.approx(whole.noise)
    np.testing.assert_allclose(inside, whole.gxy[y0:y1, x0:x1], atol=1e-6)


def test_a_region_a_little_larger_or_shifted_reuses_the_field_filtered_for_the_first():
    # One frame's stages ask for nearly the same region of the ring as the pose moves: each
    # filtering it afresh cost the ellipse system a tenth of its tracking time at 1.2 m.
    stack = image_stack(_structured_frame())
    first = stack.gradient_field(1.5, (200, 100, 400, 300))
    assert stack.gradient_field(1.5, (190, 95, 415, 310)) is first
    assert stack.gradient_field(2.0, (190, 95, 415, 310)) is not first  # another smoothing
    far = stack.gradient_field(1.5, (10, 10, 60, 60))
    assert far is not first and far.shape[0] * far.shape[1] < 0.1 * first.gxy[..., 0].size


@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
def test_a_colour_frame_made_gray_gives_the_same_image_stack(dtype):
    # Channels that differ, so that the luma weights matter.
    mono = _structured_frame().image.astype(float)
    rng = np.random.default_rng(2)
    bgr = np.clip(mono[:, :, None] + rng.integers(-9, 10, (*mono.shape, 3)), 0, 255)
    bgr = bgr.astype(np.uint8) if dtype == np.uint8 else (bgr / 255.0).astype(dtype)
    colour = Frame(bgr, 0.0, replace(CAMERA, channels=3), 0)
    gray = gray_frame(colour)
    assert gray.image.shape == CAMERA.shape and gray.info.channels == 1
    assert gray.info.key[3:] == colour.info.key[3:]  # the same intrinsics
    a, b = image_stack(colour), image_stack(gray)
    np.testing.assert_array_equal(a.pixels, b.pixels)
    assert (a.noise_sigma, a.clip_sigma) == (b.noise_sigma, b.clip_sigma)
    broken = replace(colour, image=colour.image[:, :, :2])
    assert gray_frame(broken) is broken  # its problem is the estimators' to report


def test_a_frame_of_nothing_but_noise_is_blank():
    rng = np.random.default_rng(1)
    pixels = np.clip(0.5 + rng.normal(0, 0.1, CAMERA.shape), 0, 1)
    result = image_stack(Frame((pixels * 255).astype(np.uint8), 0.0, CAMERA, 0))
    assert isinstance(result, str) and "nothing but noise" in result


@pytest.mark.parametrize(
    ("image", "reason"),
    [
        (np.zeros(CAMERA.shape, np.uint8), "no contrast (black"),
        (np.full(CAMERA.shape, 255, np.uint8), "no contrast (saturated"),
        (np.zeros((3, 3), np.uint8), "does not match"),
        (np.full(CAMERA.shape, np.nan, np.float32), "NaN"),
        (np.zeros((*CAMERA.shape, 3), np.uint8), "does not match"),
        (np.zeros(CAMERA.shape, np.int16), "neither uint8 nor float"),
    ],
)
def test_image_stack_names_the_problem_of_a_bad_frame(image, reason):
    result = image_stack(Frame(image, 0.0, CAMERA, 0))
    assert isinstance(result, str) and reason in result


def test_image_stack_rejects_a_tiny_image_of_a_tiny_camera():
    tiny = load_camera("reference").model_copy(update={"width": 16, "height": 16}).camera_info()
    result = image_stack(Frame(np.zeros((16, 16), np.uint8), 0.0, tiny, 0))
    assert isinstance(result, str) and "too small" in result


def test_percentile_is_numpys_to_the_last_bit():
    rng = np.random.default_rng(7)
    for trial in range(400):
        dtype = (np.float32, np.float64)[trial % 2]
        values = (rng.normal(size=int(rng.integers(1, 2000))) * rng.uniform(1e-3, 10)).astype(dtype)
        if trial % 3 == 0:  # ties
            values = np.round(values, 1).astype(dtype)
        for q in (0.0, 1.0, 50.0, 90.0, 99.0, 100.0):
            expected, got = np.percentile(values, q), percentile(values, q)
            assert got == expected and np.asarray(got).dtype == np.asarray(expected).dtype
        expected, got = np.percentile(values, [1.0, 99.0]), percentile(values, [1.0, 99.0])
        assert np.array_equal(got, expected) and got.dtype == expected.dtype
        two_d = values[: len(values) // 4 * 4].reshape(4, -1)
        if two_d.size:
            assert np.array_equal(percentile(two_d, [1.0, 99.0]), np.percentile(two_d, [1.0, 99.0]))
