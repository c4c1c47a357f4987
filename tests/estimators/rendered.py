"""Test fixture: rendered frames of a mock-up with ground truth, cached per process (a render
costs 50–300 ms), with the reference study's noise added deterministically."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np

from configuration.camera import load_camera
from configuration.mockup import MockupConfig, load_mockup
from configuration.render import NoiseConfig, RenderConfig
from estimators.frame import CameraInfo, Frame, GroundTruth
from estimators.geometry import Pose
from hil.evaluation.scenarios import camera_pose_for, target_offset
from sim_backends.renderer import PybulletRenderer
from sim_backends.scene import MockupScene
from sim_backends.sensor import expose, frame_rng

#: A mock-up the estimators were not tuned on (configs/mockup_other.yaml): smaller panel, other
#: fastener layout without four-fold symmetry, thruster elsewhere.
OTHER_MOCKUP = load_mockup(Path(__file__).resolve().parents[2] / "configs" / "mockup_other.yaml")

#: A deep, dark ring (8.5 cm proud of a lighter face, no thruster): seen 10° off its axis, its
#: bore wall shifts the inner edge by pixels and, lit, shows an edge of the outer edge's
#: polarity a ring's width inside it.
DEEP_RING_MOCKUP = MockupConfig.model_validate(
    {
        "name": "deep_ring",
        "bus_face": {"width": 1.7, "height": 1.3, "color": [0.45, 0.45, 0.45]},
        "marman_ring": {
            "outer_diameter": 0.8,
            "radial_width": 0.065,
            "protrusion": 0.085,
            "color": [0.1, 0.1, 0.1],
        },
        "centre_panel": {"side": 0.3, "color": [0.8, 0.8, 0.8]},
        "thruster": None,
        "fasteners": [
            {
                "name": "hole",
                "surface": "ring",
                "diameter": 0.014,
                "color": [0.3, 0.3, 0.3],
                "circle_pattern": {"radius": 0.375, "count": 8, "phase_deg": 9.0},
            }
        ],
    }
)

#: A small ring with a deep, narrow bore (6.8 cm deep, 3 cm wide; no thruster): close up its
#: rim and foot form a concentric pair much like the ring's own two edges, and its wall in
#: shade gives the rim the outer edge's polarity.
DEEP_BORE_MOCKUP = MockupConfig.model_validate(
    {
        "name": "deep_bore",
        "bus_face": {"width": 1.2, "height": 1.0, "color": [0.55, 0.55, 0.55]},
        "marman_ring": {
            "outer_diameter": 0.5,
            "radial_width": 0.03,
            "protrusion": 0.068,
            "color": [0.35, 0.35, 0.35],
        },
        "centre_panel": {"side": 0.2, "thickness": 0.004, "color": [0.85, 0.85, 0.85]},
        "thruster": None,
        "fasteners": [
            {
                "name": "hole",
                "surface": "ring",
                "diameter": 0.008,
                "color": [0.2, 0.2, 0.2],
                "circle_pattern": {"radius": 0.235, "count": 8, "phase_deg": 9.0},
            }
        ],
    }
)

#: A generic pose offset (no edge on the pixel grid): 3 cm, 2 cm, 2°, −3°, 6°.
GENERIC = (0.03, -0.02, 0.0, np.radians(2.0), np.radians(-3.0), np.radians(6.0))


def _mockup(name: str) -> MockupConfig:
    named = {"other": OTHER_MOCKUP, "deep_ring": DEEP_RING_MOCKUP, "deep_bore": DEEP_BORE_MOCKUP}
    return named[name] if name in named else load_mockup(name)


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
