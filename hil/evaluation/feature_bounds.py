"""Cramér–Rao bounds of the corner and line systems' *features* — the best any estimator using
those features can do — and the mean errors they imply, to judge the measured matrix.

The image of a sharp (area-sampled) step edge of contrast Δ under white noise σ carries, per
pixel of edge length, the information Δ²/σ² about the edge's offset along its normal: one
independent offset measurement of standard deviation σ/Δ per pixel of edge. So:

* panel edges (line system): a measured point every pixel along each edge, σ_row = σ/Δ, and
  the pose information is JᵀJ/σ_row² of the point-to-projected-edge residuals;
* the bus face's outline (not used by the line system; shows what more straight edges would
  give): the same, with the face's grey against the black background, for the parts in view;
* a disc of image radius r (corner system): Σ over its rim of Δ²cos²φ/σ² gives information
  π·r·Δ²/σ² about each coordinate of its centre; the pose information sums those over the
  discs in view (panel corners add little and are left out: a lower bound on the
  information, i.e. a slightly pessimistic bound).

Contrasts are those the renderer produces: the model colours' luma under the configured
lighting (ambient + diffuse·n·l for the face-on panel, bus face, ring and fasteners).
Unlike ../shared/LIMITS.md, which bounds the whole image (shading included), these bound what a
geometric feature system can reach. ``python -m hil.evaluation.feature_bounds`` prints the table.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from configuration.camera import load_camera
from configuration.mockup import MockupConfig, gray, load_mockup
from configuration.render import Lighting, NoiseConfig
from estimators.frame import CameraInfo
from estimators.geometry import Pose
from estimators.planar_pose import EdgeObservations, PointObservations, project_ideal
from estimators.target import facing_camera
from hil.evaluation.scenarios import REFERENCE_DISTANCES_M


def lit_gray(color, lighting: Lighting) -> float:
    """Grey level of a face-on (+z) Lambertian surface of ``color``."""
    sun = np.asarray(lighting.sun_direction_T, dtype=float)
    cosine = max(0.0, sun[2] / np.linalg.norm(sun))
    return gray(color) * (lighting.ambient + lighting.diffuse * cosine)


def _edge_information(
    X_CT: Pose,
    camera: CameraInfo,
    ends: np.ndarray,
    points: list[np.ndarray],
    edge: list[np.ndarray],
    sigma_px: float,
) -> np.ndarray:
    """6×6 information JᵀJ of edge points (``points[i]`` on model edge ``edge[i]``, each with
    σ ``sigma_px`` across its edge) about the pose."""
    uv = np.concatenate(points)
    obs = EdgeObservations(ends, np.concatenate(edge), uv, np.full(len(uv), sigma_px))
    _, _, J = obs.linearize(X_CT, camera.K)
    return J.T @ J


def panel_edge_information(
    X_CT: Pose, camera: CameraInfo, mockup: MockupConfig, sigma: float, lighting: Lighting
) -> np.ndarray:
    """6×6 Fisher information of the panel's four edges about [δθ, δp]."""
    target = mockup.target_model()
    contrast = abs(
        lit_gray(mockup.centre_panel.color, lighting) - lit_gray(mockup.bus_face.color, lighting)
    )
    corners = target.panel_corners_T
    ends = np.stack([corners, np.roll(corners, -1, axis=0)], axis=1)
    points, edge = [], []
    for i, (a, b) in enumerate(ends):
        a_uv, b_uv = project_ideal(X_CT, np.array([a, b]), camera.K)
        count = max(2, int(np.linalg.norm(b_uv - a_uv)))
        t = (np.arange(count) + 0.5) / count
        points.append(project_ideal(X_CT, a + t[:, None] * (b - a), camera.K))
        edge.append(np.full(count, i))
    return _edge_information(X_CT, camera, ends, points, edge, sigma / contrast)


def outline_edge_information(
    X_CT: Pose, camera: CameraInfo, mockup: MockupConfig, sigma: float, lighting: Lighting
) -> np.ndarray:
    """6×6 information of the bus face's outline against the dark background (the parts in
    view) — the straight edges the line system fits besides the panel's."""
    face = mockup.bus_face
    contrast = lit_gray(face.color, lighting)  # against space black
    w, h, z = face.width / 2, face.height / 2, mockup.z_bus
    corners = np.array([[w, h, z], [-w, h, z], [-w, -h, z], [w, -h, z]])
    ends = np.stack([corners, np.roll(corners, -1, axis=0)], axis=1)
    points, edge = [], []
    for i, (a, b) in enumerate(ends):
        t = np.linspace(0.0, 1.0, 4000)
        P = a + t[:, None] * (b - a)
        visible = camera.in_view(X_CT.apply(P), margin_px=2.0)
        if visible.sum() < 2:
            continue
        uv = project_ideal(X_CT, P[visible], camera.K)
        step = max(1, int(len(uv) / max(1.0, np.linalg.norm(uv[-1] - uv[0]))))
        points.append(uv[::step])
        edge.append(np.full(len(uv[::step]), i))
    if not points:
        return np.zeros((6, 6))
    return _edge_information(X_CT, camera, ends, points, edge, sigma / contrast)


def disc_information(
    X_CT: Pose, camera: CameraInfo, mockup: MockupConfig, sigma: float, lighting: Lighting
) -> np.ndarray:
    """6×6 Fisher information of the mock-up's discs (bolt heads/holes) in view."""
    target = mockup.target_model()
    surface = {
        "ring": mockup.marman_ring.color,
        "panel": mockup.centre_panel.color,
        "bus": mockup.bus_face.color,
    }
    info = np.zeros((6, 6))
    features = {f.name: f for f in target.point_features if f.kind == "disc"}
    for group in mockup.fasteners:
        contrast = abs(lit_gray(group.color, lighting) - lit_gray(surface[group.surface], lighting))
        for i in range(len(group.centers_xy())):
            feature = features[f"{group.name}_{i}"]
            P_C = X_CT.apply(feature.p_T)
            if not camera.in_view(P_C[None], margin_px=5.0)[0]:
                continue
            radius_px = feature.diameter / 2 * camera.K[0, 0] / P_C[2]
            variance = sigma**2 / (contrast**2 * math.pi * radius_px)
            obs = PointObservations(
                feature.p_T[None],
                project_ideal(X_CT, feature.p_T[None], camera.K),
                np.eye(2)[None] * variance,
            )
            _, _, J = obs.linearize(X_CT, camera.K)
            info += J.T @ J
    return info


def expected_mean_errors(covariance: np.ndarray, *, samples: int = 20000, seed: int = 0):
    """Mean translation error (m) and mean roll/pitch/yaw-norm rotation error (rad) of an
    unbiased estimator whose errors are N(0, covariance) over [δθ, δp]."""
    rng = np.random.default_rng(seed)
    draws = rng.multivariate_normal(np.zeros(6), covariance, size=samples)
    rotation = np.linalg.norm(Rotation.from_rotvec(draws[:, :3]).as_euler("xyz"), axis=1)
    return float(np.linalg.norm(draws[:, 3:], axis=1).mean()), float(rotation.mean())


def _with_outline(*args) -> np.ndarray:
    return panel_edge_information(*args) + outline_edge_information(*args)


#: system name → its features' information.
INFORMATION = {
    "lines": panel_edge_information,
    "lines + bus-face outline": _with_outline,
    "corners": disc_information,
}


def feature_bound(
    system: str,
    noise: str,
    distance_m: float,
    *,
    camera_name: str = "reference",
    mockup_name: str = "default",
) -> tuple[np.ndarray, float, float]:
    """(Cramér–Rao covariance over [δθ, δp], mean translation error m, mean rotation error
    rad) of ``system``'s features at a generic view ``distance_m`` in front of the face (a few
    degrees off square, as ../shared/LIMITS.md uses; the bound barely depends on it)."""
    camera = load_camera(camera_name).camera_info()
    mockup = load_mockup(mockup_name)
    sigma = math.sqrt(NoiseConfig(preset=noise).gaussian_variance)
    offset = Pose.from_rpy(math.radians(2.0), math.radians(-3.0), math.radians(6.0), np.zeros(3))
    X_CT = facing_camera(distance_m).inverse() @ offset
    covariance = np.linalg.inv(INFORMATION[system](X_CT, camera, mockup, sigma, Lighting()))
    position, rotation = expected_mean_errors(covariance)
    return covariance, position, rotation


def bound_table(camera_name: str = "reference", mockup_name: str = "default") -> str:
    """Markdown: per system, noise and distance, the 1σ bounds and the mean errors they imply."""
    lines = [
        "| features | noise | distance | tilt 1σ (per axis) | depth 1σ | mean translation error "
        "| mean rotation error |",
        "|---|---|---|---|---|---|---|",
    ]
    for system in INFORMATION:
        for noise in ("low", "high"):
            for distance in REFERENCE_DISTANCES_M:
                covariance, position, rotation = feature_bound(
                    system, noise, distance, camera_name=camera_name, mockup_name=mockup_name
                )
                tilt = math.degrees(math.sqrt(max(covariance[0, 0], covariance[1, 1])))
                depth = math.sqrt(covariance[5, 5])
                lines.append(
                    f"| {system} | {noise} | {distance:.1f} m | {tilt:.2f}° | {1000 * depth:.1f} mm "
                    f"| {100 * position:.2f} cm | {math.degrees(rotation):.2f}° |"
                )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    print(bound_table())
