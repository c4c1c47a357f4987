"""The Cramér–Rao bound of the pose from one frame, per system's features and for all of them
together, and the mean errors it implies — the physical floor a campaign's measured errors are
divided by (efficiency = measured mean error ÷ bound's mean error; 1 is as good as the rig
allows).

The information of each system's features comes from the existing bound modules: the corner
system's discs and the line system's panel edges and bus-face outline
(``hil.evaluation.feature_bounds``: an edge of contrast Δ under noise σ gives one offset
measurement of σ/Δ per pixel of edge), and the ellipse system's circle edges
(``hil.evaluation.circle_bounds``: the ring's two edges against the bus face, the thruster's
inner rim against its lip, radius free as the estimator fits it) with the same σ/Δ per pixel.
The features are distinct image regions, so their information adds for ``all`` — the bound of
the fused system. Rao (1945); for pose from image features e.g. Kanatani, "Statistical
Optimization for Geometric Computation" (1996), ch. 14. ``../shared/LIMITS.md`` bounds the
whole image (shading included); these bound what the feature systems can reach.

The ellipse system is judged on its circle (centre error, angle between normals), so its mean
errors are those of the ring's centre and normal under the bound's covariance.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from configuration.camera import load_camera
from configuration.mockup import MockupConfig, gray, load_mockup
from configuration.render import Lighting, NoiseConfig
from estimators.frame import CameraInfo
from estimators.geometry import Pose
from estimators.target import facing_camera
from hil.evaluation.circle_bounds import circle_information
from hil.evaluation.feature_bounds import (
    disc_information,
    expected_mean_errors,
    lit_gray,
    outline_edge_information,
    panel_edge_information,
)

SYSTEMS = ("corners", "lines", "ellipses", "all")
#: The open-loop matrix's fused system is bounded by every feature together.
BOUND_OF = {"corners": "corners", "lines": "lines", "ellipses": "ellipses", "fused": "all"}


def ellipse_information(
    X_CT: Pose, camera: CameraInfo, mockup: MockupConfig, sigma: float, lighting: Lighting
) -> np.ndarray:
    """6×6 information of the circles the ellipse system fits: the ring's outer and inner
    edges (ring against the bus face) and, with a thruster, its inner rim (interior against
    the lip; radius free, as the estimator fits it)."""
    target = mockup.target_model()
    ring = abs(
        lit_gray(mockup.marman_ring.color, lighting) - lit_gray(mockup.bus_face.color, lighting)
    )
    sigmas = {"ring_outer": sigma / ring, "ring_inner": sigma / ring}
    free: tuple[str, ...] = ()
    thruster = getattr(mockup, "thruster", None)
    if thruster is not None and target.has_circle("thruster_inner"):
        contrast = abs(lit_gray(thruster.color, lighting) - gray(thruster.interior_color))
        sigmas["thruster_inner"] = sigma / max(contrast, 1e-6)
        free = ("thruster_inner",)
    circles = tuple(name for name in sigmas if target.has_circle(name))
    return circle_information(
        target, camera.K, X_CT, circles, free_radius=free, sigma_px={c: sigmas[c] for c in circles}
    )


def _lines(*args) -> np.ndarray:
    return panel_edge_information(*args) + outline_edge_information(*args)


INFORMATION = {"corners": disc_information, "lines": _lines, "ellipses": ellipse_information}


def information(
    system: str, X_CT: Pose, camera: CameraInfo, mockup: MockupConfig, sigma: float,
    lighting: Lighting,
) -> np.ndarray:  # fmt: skip
    """6×6 Fisher information about [δθ, δp] of ``system``'s features (``all``: every one)."""
    if system == "all":
        return sum(f(X_CT, camera, mockup, sigma, lighting) for f in INFORMATION.values())
    if system not in INFORMATION:
        raise ValueError(f"unknown system {system!r}; known: {', '.join(SYSTEMS)}")
    return INFORMATION[system](X_CT, camera, mockup, sigma, lighting)


@dataclass(frozen=True, slots=True)
class Bound:
    """The bound for one system at one view: 1σ of tilt (per axis, the larger), depth and
    lateral position, and the mean errors an efficient unbiased estimator would show —
    translation (m; the circle centre's for the ellipses) and rotation (deg; the angle between
    normals for the ellipses)."""

    system: str
    covariance: np.ndarray
    tilt_sigma_deg: float
    depth_sigma_m: float
    lateral_sigma_m: float
    translation_mean_m: float
    rotation_mean_deg: float


def generic_view(distance_m: float) -> Pose:
    """``X_CT`` a few degrees off square at ``distance_m`` (``../shared/LIMITS.md``: no edge
    aligned with the pixel grid), as ``feature_bounds`` uses."""
    offset = Pose.from_rpy(math.radians(2.0), math.radians(-3.0), math.radians(6.0), np.zeros(3))
    return facing_camera(distance_m).inverse() @ offset


def circle_mean_errors(
    covariance: np.ndarray, X_CT: Pose, center_T: np.ndarray, normal_T: np.ndarray,
    *, samples: int = 20000, seed: int = 0,
) -> tuple[float, float]:  # fmt: skip
    """Mean centre error (m) and mean angle between normals (rad) of a circle on the target
    under pose errors N(0, covariance) over [δθ, δp] (left rotation error in C)."""
    rng = np.random.default_rng(seed)
    draws = rng.multivariate_normal(np.zeros(6), covariance, size=samples)
    c = X_CT.R @ center_T
    n = X_CT.R @ normal_T
    centre = np.linalg.norm(draws[:, 3:] + np.cross(draws[:, :3], c), axis=1)
    tilt = np.linalg.norm(np.cross(draws[:, :3], n), axis=1)  # |δθ × n| = sin of the angle
    return float(centre.mean()), float(np.arcsin(np.clip(tilt, 0.0, 1.0)).mean())


def bound(
    system: str, noise: str, distance_m: float, *, camera: str = "reference",
    mockup: str = "default",
) -> Bound:  # fmt: skip
    """The bound of ``system`` (corners, lines, ellipses or all) under the ``noise`` preset at
    a generic view ``distance_m`` in front of the ring face."""
    info = load_camera(camera).camera_info()
    config = load_mockup(mockup)
    sigma = math.sqrt(NoiseConfig(preset=noise).gaussian_variance)
    if sigma <= 0:
        raise ValueError(f"noise {noise!r} has no Gaussian pixel noise: the bound is zero")
    X_CT = generic_view(distance_m)
    covariance = np.linalg.pinv(information(system, X_CT, info, config, sigma, Lighting()))
    if system == "ellipses":
        ring = config.target_model().circle("ring_outer")
        position, rotation = circle_mean_errors(covariance, X_CT, ring.center_T, ring.normal_T)
    else:
        position, rotation = expected_mean_errors(covariance)
    tilt = math.degrees(math.sqrt(max(covariance[0, 0], covariance[1, 1])))
    return Bound(
        system,
        covariance,
        tilt,
        math.sqrt(covariance[5, 5]),
        math.sqrt(max(covariance[3, 3], covariance[4, 4])),
        position,
        math.degrees(rotation),
    )


@functools.lru_cache(maxsize=256)
def mean_error_bound(
    system: str, noise: str, distance_m: float, *, camera: str = "reference",
    mockup: str = "default",
) -> tuple[float, float] | None:  # fmt: skip
    """(mean translation error m, mean rotation error deg) at the bound for a matrix cell, or
    None where there is none (no noise, an unknown system or one the bound cannot judge)."""
    name = BOUND_OF.get(system)
    if name is None or NoiseConfig(preset=noise).gaussian_variance <= 0:
        return None
    try:
        b = bound(name, noise, distance_m, camera=camera, mockup=mockup)
    except (ValueError, np.linalg.LinAlgError):
        return None
    return b.translation_mean_m, b.rotation_mean_deg


def bound_table(
    noise: str, distances_m: tuple[float, ...], *, camera: str = "reference",
    mockup: str = "default",
) -> str:  # fmt: skip
    """Markdown: per distance and system, the 1σ bounds and the mean errors they imply."""
    lines = [
        f"Cramér–Rao bound from one frame: camera {camera}, mock-up {mockup}, noise {noise}",
        "",
        "| distance | features | tilt 1σ (per axis) | depth 1σ | lateral 1σ "
        "| mean translation error | mean rotation error |",
        "|---|---|---|---|---|---|---|",
    ]
    for distance in distances_m:
        for system in SYSTEMS:
            b = bound(system, noise, distance, camera=camera, mockup=mockup)
            lines.append(
                f"| {distance:.2f} m | {system} | {b.tilt_sigma_deg:.3f}° "
                f"| {1000 * b.depth_sigma_m:.2f} mm | {1000 * b.lateral_sigma_m:.2f} mm "
                f"| {1000 * b.translation_mean_m:.2f} mm | {b.rotation_mean_deg:.3f}° |"
            )
    lines.append("")
    lines.append(
        "(ellipses: the ring's centre and the angle between normals, as the system is judged)"
    )
    return "\n".join(lines) + "\n"
