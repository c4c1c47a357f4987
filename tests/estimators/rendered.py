"""Test fixture: rendered frames of a mock-up with ground truth, cached per process (a render
costs 50–300 ms), with the reference study's noise added deterministically."""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from drivers.base import CameraInfo, Frame, GroundTruth
from estimators.geometry import Pose
from hil.config import MockupConfig, NoiseConfig, RenderConfig, load_camera, load_mockup
from hil.scenarios import camera_pose_for, target_offset
from sim_backends.renderer import PybulletRenderer
from sim_backends.scene import MockupScene
from sim_backends.sensor import expose, frame_rng

#: A mock-up the estimators were not tuned on: smaller panel, other fastener layout, thruster
#: elsewhere.
OTHER_MOCKUP = MockupConfig.model_validate(
    {
        "name": "other",
        "centre_panel": {"side": 0.24, "color": [0.7, 0.7, 0.7]},
        "fasteners": [
            {
                "name": "ring_hole",
                "surface": "ring",
                "diameter": 0.02,
                "circle_pattern": {"radius": 0.275, "count": 6, "phase_deg": 10},
            },
            {
                "name": "panel_bolt",
                "surface": "panel",
                "diameter": 0.016,
                "color": [0.1, 0.1, 0.1],
                "positions": [[0.08, 0.08], [-0.08, 0.08], [-0.08, -0.08]],
            },
            {
                "name": "bus_head",
                "surface": "bus",
                "diameter": 0.035,
                "color": [0.9, 0.9, 0.9],
                "positions": [[0.55, -0.5], [-0.6, 0.5], [0.0, -0.62]],
            },
        ],
        "thruster": {"center": [-0.5, -0.45]},
    }
)

#: A generic pose offset (no edge on the pixel grid): 3 cm, 2 cm, 2°, −3°, 6°.
GENERIC = (0.03, -0.02, 0.0, np.radians(2.0), np.radians(-3.0), np.radians(6.0))


def _mockup(name: str) -> MockupConfig:
    return OTHER_MOCKUP if name == "other" else load_mockup(name)


@lru_cache(maxsize=32)
def render(
    distance_m: float,
    offset: tuple[float, ...] = GENERIC,
    *,
    camera: str = "reference",
    mockup: str = "default",
    supersample: int = 1,
) -> tuple[np.ndarray, Pose, CameraInfo]:
    """Noise-free image, true X_CT and camera info of one view."""
    info = load_camera(camera).camera_info()
    X_WC, _ = camera_pose_for(distance_m, target_offset(*offset))
    with MockupScene(_mockup(mockup)) as scene:
        rendering = PybulletRenderer(scene, info, RenderConfig(supersample=supersample)).render(
            X_WC
        )
    return rendering.image, rendering.X_CT, info


def frame(
    distance_m: float,
    offset: tuple[float, ...] = GENERIC,
    *,
    noise: str = "low",
    seed: int = 0,
    seq: int = 0,
    camera: str = "reference",
    mockup: str = "default",
    supersample: int = 1,
) -> Frame:
    image, X_CT, info = render(
        distance_m, offset, camera=camera, mockup=mockup, supersample=supersample
    )
    exposed = expose(image, None, info.K, NoiseConfig(preset=noise), frame_rng(seed, seq))
    return Frame(exposed, float(seq) / 30.0, info, seq, GroundTruth(X_CT, X_CT.inverse()))


def target(mockup: str = "default"):
    return _mockup(mockup).target_model()
