"""The vision pipeline's camera checks: a frozen image or a stamp that does not advance is a
camera fault, named, latched, and never processed; a still scene repeating itself is not."""

import re

import numpy as np
import pytest

from configuration.mockup import load_mockup
from configuration.vision import VisionConfig
from estimators.frame import Frame
from estimators.fusion import FusionParams, PoseFusion
from estimators.geometry import Pose
from hil.runtime.history import StateHistory, StateSample
from hil.runtime.vision import VisionPipeline, image_fingerprint
from hil.runtime.workers import InlineWorkers
from tests.hil.runtime.loop_fakes import INFO, rig_geometry

CONFIG = VisionConfig()
PERIOD = 1.0 / 15.0


def pipeline() -> VisionPipeline:
    return VisionPipeline(
        systems=(),
        fusion=PoseFusion(load_mockup("default").target_model(), FusionParams()),
        history=StateHistory(rig_geometry()),
        workers=InlineWorkers({}, CONFIG.processing_s),
        config=CONFIG,
    )


def image(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 255, (48, 64), dtype=np.uint8)


def feed(vision: VisionPipeline, images, speed_m_s: float, stamps=None):
    """Frames at 15 fps while the flange moves along x at ``speed_m_s``; the arm state is
    published every 8 ms as the loop does."""
    stamps = stamps if stamps is not None else [i * PERIOD for i in range(len(images))]
    t = 0.0
    for seq, (picture, stamp) in enumerate(zip(images, stamps, strict=True)):
        while t <= stamp + 1e-9:
            X_BE = Pose(np.eye(3), np.array([0.5 + speed_m_s * t, 0.0, 0.8]))
            vision.publish_state(StateSample(t, X_BE, t, 0.0))
            t += 0.008
        vision.on_frame(Frame(picture, stamp, INFO, seq), stamp + 0.12)
    return vision.latest()


def test_image_fingerprint_tells_images_apart():
    assert image_fingerprint(image(1)) == image_fingerprint(image(1).copy())
    assert image_fingerprint(image(1)) != image_fingerprint(image(2))
    changed = image(1)
    changed[47, 63] ^= 1  # one bit of the last pixel
    assert image_fingerprint(changed) != image_fingerprint(image(1))
    assert image_fingerprint(np.asfortranarray(image(1))) == image_fingerprint(image(1))


def test_vision_frozen_image_while_the_camera_moves_is_a_camera_fault():
    frozen = [image(0)] + [image(1)] * 5
    status = feed(pipeline(), frozen, speed_m_s=0.1)  # 6.7 mm between frames
    assert status.camera_fault is not None
    assert "frozen camera: frame 2 repeats the image of frame 1" in status.camera_fault
    assert re.search(r"moved [67] mm", status.camera_fault)  # 6.7 mm in one frame period
    assert status.frames_received == 2  # the repeats were never taken


def test_vision_slow_motion_is_summed_over_the_repeated_run():
    # 2 mm between frames: under the 5 mm threshold for a pair, over it after three.
    status = feed(pipeline(), [image(1)] * 5, speed_m_s=0.03)
    assert status.camera_fault is not None
    assert "repeats the image of frame 0" in status.camera_fault
    assert feed(pipeline(), [image(1)] * 2, speed_m_s=0.03).camera_fault is None


def test_vision_still_scene_may_repeat_itself():
    status = feed(pipeline(), [image(1)] * 6, speed_m_s=0.0)
    assert status.camera_fault is None and status.frames_received == 6


def test_vision_live_images_while_moving_are_fine():
    status = feed(pipeline(), [image(i) for i in range(6)], speed_m_s=0.25)
    assert status.camera_fault is None and status.frames_received == 6


@pytest.mark.parametrize("step", [0.0, -0.01])
def test_vision_stamp_that_does_not_advance_is_a_camera_fault(step):
    stamps = [0.0, PERIOD, PERIOD + step, 3 * PERIOD]
    status = feed(pipeline(), [image(i) for i in range(4)], 0.1, stamps)
    assert status.camera_fault is not None
    assert "frame 2 stamped" in status.camera_fault and "not after frame 1" in status.camera_fault
    assert status.frames_received == 2  # latched: frame 3 is not taken either
