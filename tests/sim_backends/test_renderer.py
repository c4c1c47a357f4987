"""The renderer must agree with geometry.project, measured on rendered pixels (not matrices)."""

import numpy as np
import pytest

from configuration.camera import load_camera
from configuration.mockup import load_mockup
from configuration.render import RenderConfig
from estimators.geometry import Pose
from hil.evaluation.scenarios import camera_pose_for, target_offset
from sim_backends.renderer import PybulletRenderer
from sim_backends.scene import MockupScene, export_mockup_obj
from tests.sim_backends.markers import (
    expected_centroid,
    marker_mockup,
    measured_centroid,
    projection_errors,
)


@pytest.fixture(scope="module")
def marker_scene():
    mockup = marker_mockup()
    with MockupScene(mockup) as scene:
        yield mockup, scene


# A generic offset: no marker centre sits on the pixel grid.
OFFSET = target_offset(0.031, -0.017)


@pytest.mark.parametrize("camera", ["reference", "oak_d_rgb"])
@pytest.mark.parametrize("distance", [1.2, 2.0, 3.0])
def test_render_agrees_with_projection(marker_scene, camera, distance):
    mockup, scene = marker_scene
    info = load_camera(camera).camera_info()
    renderer = PybulletRenderer(scene, info, RenderConfig(supersample=1))
    X_WC, X_CT = camera_pose_for(distance, OFFSET)
    errors = projection_errors(renderer.render(X_WC).image, X_CT, mockup, info.K, info.dist)
    assert len(errors) >= 15, "too few markers measured for a meaningful check"
    assert errors.max() <= 0.3
    assert np.sqrt(np.mean(errors**2)) <= 0.15


def test_supersampled_render_has_no_systematic_offset(marker_scene):
    mockup, scene = marker_scene
    for camera in ("reference", "oak_d_rgb"):
        info = load_camera(camera).camera_info()
        renderer = PybulletRenderer(scene, info, RenderConfig(supersample=2))
        X_WC, X_CT = camera_pose_for(2.0, OFFSET)
        image = renderer.render(X_WC).image
        signed = []
        for feature in mockup.target_model().point_features:
            if feature.kind != "disc" or not info.in_view(X_CT.apply(feature.p_T)[None], 25)[0]:
                continue
            predicted = expected_centroid(
                X_CT, feature.p_T, feature.diameter / 2, info.K, info.dist
            )
            radius_px = info.K[0, 0] * feature.diameter / 2 / X_CT.apply(feature.p_T)[2]
            measured = measured_centroid(image, predicted, radius_px)
            if measured is not None:
                signed.append(measured - predicted)
        signed = np.array(signed)
        assert len(signed) > 30
        # A half-pixel convention slip would show here as a 0.25–0.5 px bias.
        assert np.abs(signed.mean(axis=0)).max() < 0.02, camera
        assert np.abs(signed).max() < 0.15, camera


def test_render_agrees_for_a_tilted_target(marker_scene):
    mockup, scene = marker_scene
    info = load_camera("reference").camera_info()
    renderer = PybulletRenderer(scene, info, RenderConfig(supersample=2))
    X_WC, X_CT = camera_pose_for(
        2.0, target_offset(0.02, 0.01, 0.0, np.radians(12), np.radians(-25), np.radians(5))
    )
    errors = projection_errors(renderer.render(X_WC).image, X_CT, mockup, info.K, info.dist)
    assert len(errors) >= 30
    assert errors.max() <= 0.3


def test_render_background_is_black_and_truth_is_consistent():
    mockup = load_mockup("default")
    info = load_camera("reference").camera_info()
    with MockupScene(mockup) as scene:
        renderer = PybulletRenderer(scene, info)
        X_WC, X_CT = camera_pose_for(3.0, OFFSET)
        rendering = renderer.render(X_WC)
    assert rendering.image.shape == (480, 640) and rendering.image.dtype == np.float32
    assert rendering.image[0, 0] == 0.0 and np.isinf(rendering.depth_m[0, 0])
    assert rendering.X_CT.is_close(X_CT, atol_m=1e-12, atol_rad=1e-12)
    # Depth at the image centre is the distance to the panel (ring face at 3 m, panel behind it).
    centre_depth = rendering.depth_m[240, 320]
    assert centre_depth == pytest.approx(
        3.0 + mockup.marman_ring.protrusion - mockup.centre_panel.thickness, abs=2e-3
    )


def test_render_contrast_is_honest():
    """Mono grey levels seen head-on: panel ≈ 0.3 above the face, ring ≈ 0.4 (LIMITS.md)."""
    mockup = load_mockup("default")
    info = load_camera("reference").camera_info()
    with MockupScene(mockup) as scene:
        X_WC, _X_CT = camera_pose_for(1.2, Pose.identity())
        image = PybulletRenderer(scene, info).render(X_WC).image
    f = info.K[0, 0] / 1.2
    cx, cy = info.K[0, 2], info.K[1, 2]
    panel = image[int(cy) - 20 : int(cy) + 20, int(cx) - 20 : int(cx) + 20].mean()
    ring_px = round(cx + 0.29 * f)  # between the bolt holes on the ring face
    ring = image[int(cy) - 3 : int(cy) + 4, ring_px - 2 : ring_px + 3].mean()
    face_px = round(cx - 0.5 * f)
    face = image[int(cy) - 5 : int(cy) + 5, face_px - 5 : face_px + 5].mean()
    assert 0.25 <= panel - face <= 0.35
    assert 0.33 <= ring - face <= 0.47


def test_render_from_exported_obj_matches_builtin(tmp_path):
    """A user's OBJ export of the mock-up renders like the built-in geometry."""
    mockup = load_mockup("default")
    obj = export_mockup_obj(mockup, tmp_path / "mockup.obj")
    from_file = type(mockup).model_validate({**mockup.model_dump(), "model_file": {"path": obj}})
    info = load_camera("reference").camera_info()
    X_WC, _ = camera_pose_for(2.0, target_offset(0.03, 0.02, 0.0, 0.1, -0.15, 0.2))
    with MockupScene(mockup) as scene:
        builtin = PybulletRenderer(scene, info).render(X_WC).image
    with MockupScene(from_file) as scene:
        loaded = PybulletRenderer(scene, info).render(X_WC).image
    differs = np.abs(builtin - loaded) > 0.05
    assert differs.mean() < 0.01  # only a few edge pixels may differ
    assert abs(builtin.mean() - loaded.mean()) < 0.01


def test_scene_rejects_a_missing_model_file(tmp_path):
    mockup = load_mockup("default").model_copy(update={"model_file": None})
    bad = type(mockup).model_validate(
        {**mockup.model_dump(), "model_file": {"path": str(tmp_path / "nope.obj")}}
    )
    with pytest.raises(FileNotFoundError, match="model_file"):
        MockupScene(bad)


def test_scene_moves_the_mockup_with_set_pose():
    mockup = load_mockup("default")
    info = load_camera("reference").camera_info()
    X_WC, _ = camera_pose_for(2.0, Pose.identity())
    shift = Pose.from_rpy(0.0, 0.0, 0.3, np.array([0.1, -0.05, 0.02]))
    with MockupScene(mockup) as scene:
        renderer = PybulletRenderer(scene, info)
        scene.set_pose(shift)
        moved = renderer.render(X_WC)
    with MockupScene(mockup, X_WT=Pose.identity()) as scene:
        # Moving the camera by the inverse shift gives the same image.
        same = PybulletRenderer(scene, info).render(shift.inverse() @ X_WC)
    assert moved.X_CT.is_close(same.X_CT, atol_m=1e-12, atol_rad=1e-12)
    assert np.mean(np.abs(moved.image - same.image) > 0.05) < 0.01


def test_render_from_urdf_places_the_model_at_its_offset(tmp_path):
    urdf = tmp_path / "plate.urdf"
    urdf.write_text(
        """<?xml version="1.0"?>
<robot name="plate">
  <link name="base">
    <visual>
      <geometry><box size="0.3 0.2 0.0002"/></geometry>
      <material name="white"><color rgba="0.9 0.9 0.9 1"/></material>
    </visual>
  </link>
</robot>
"""
    )
    mockup = load_mockup("default")
    with_file = type(mockup).model_validate(
        {**mockup.model_dump(), "model_file": {"path": urdf, "xyz": [0.1, -0.05, -0.0001]}}
    )
    info = load_camera("reference").camera_info()
    # Rotated in-plane so no edge is aligned with the pixel grid (coverage quantisation of an
    # aligned edge would not average out).
    X_WC, X_CT = camera_pose_for(2.0, target_offset(yaw=np.radians(17.0)))
    with MockupScene(with_file) as scene:
        image = PybulletRenderer(scene, info, RenderConfig(supersample=2)).render(X_WC).image
    weights = image / image.max()  # only the plate is lit; edges are anti-aliased
    v, u = np.mgrid[: image.shape[0], : image.shape[1]]
    centroid = np.array([(weights * u).sum(), (weights * v).sum()]) / weights.sum()
    expected = info.project(X_CT.apply(np.array([[0.1, -0.05, 0.0]])))[0]
    assert np.linalg.norm(centroid - expected) < 0.05
    assert weights.sum() == pytest.approx(0.3 * 0.2 * (info.K[0, 0] / 2.0) ** 2, rel=0.01)


def _left_edge_px(image: np.ndarray, row: int, guess: float) -> float:
    """Where the panel's left edge crosses ``row`` (mean of rows row±4), from how much of each
    pixel near ``guess`` the panel covers: exact for a renderer that integrates each pixel's
    area."""
    c0 = int(np.floor(guess)) - 5
    profile = image[row - 4 : row + 5, c0 - 6 : c0 + 17].mean(axis=0)
    outside, inside = profile[:4].mean(), profile[-4:].mean()
    covered = (profile[6:17] - outside) / (inside - outside)
    return c0 - 0.5 + float(np.sum(1.0 - covered))


@pytest.mark.parametrize(("passes", "bound_px"), [(1, 0.13), (4, 0.035)])
def test_an_edge_along_the_pixel_columns_is_placed_to_a_fraction_of_a_sample(passes, bound_px):
    """A camera square on to the panel sees its edges along the pixel columns, where 4 × 4
    samples place an edge only to a quarter of a pixel, the same in every row (the corner
    system refused such frames at the stand-off under the sensor's noise); each pass shifts
    the samples by a fraction of a sample."""
    from sim_backends.renderer import make_renderer

    mockup = load_mockup("default")
    info = load_camera("reference").camera_info()
    corners_T = mockup.target_model().panel_corners_T
    errors = []
    with MockupScene(mockup) as scene:
        renderer = make_renderer(scene, info, RenderConfig(supersample=4, passes=passes))
        for shift_px in np.arange(8) / 8.0:
            X_WC, X_CT = camera_pose_for(1.0, target_offset(shift_px / info.K[0, 0]))
            corners = info.project(X_CT.apply(corners_T))
            left = corners[np.argsort(corners[:, 0])[:2]]
            row = round(float(info.K[1, 2]))
            measured = _left_edge_px(renderer.render(X_WC).image, row, left[:, 0].mean())
            errors.append(measured - left[:, 0].mean())
    errors = np.abs(np.array(errors))
    assert errors.max() <= bound_px, np.round(errors, 3)
    if passes == 1:
        assert errors.max() > 0.06, "the regular grid should show its quarter-pixel steps"
