import numpy as np
import pytest

from configuration.camera import load_camera
from estimators.frame import Frame
from estimators.imaging import GrayImage, estimate_noise_sigma, gray_image

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


def test_gray_image_converts_and_measures_noise():
    rng = np.random.default_rng(1)
    pixels = np.clip(0.5 + rng.normal(0, 0.1, CAMERA.shape), 0, 1)
    frame = Frame((pixels * 255).astype(np.uint8), 0.0, CAMERA, 0)
    image = gray_image(frame)
    assert isinstance(image, GrayImage)
    assert image.pixels.dtype == np.float32 and image.shape == CAMERA.shape
    assert image.noise_sigma == pytest.approx(0.1, rel=0.1)


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
def test_gray_image_names_the_problem_of_a_bad_frame(image, reason):
    result = gray_image(Frame(image, 0.0, CAMERA, 0))
    assert isinstance(result, str) and reason in result


def test_gray_image_rejects_a_tiny_image_of_a_tiny_camera():
    tiny = load_camera("reference").model_copy(update={"width": 16, "height": 16}).camera_info()
    result = gray_image(Frame(np.zeros((16, 16), np.uint8), 0.0, tiny, 0))
    assert isinstance(result, str) and "too small" in result
