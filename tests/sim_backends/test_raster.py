"""The raster renderer must draw pybullet's TinyRenderer image: same pixels, same depth, on
every mock-up, camera and pose the simulator uses, and refuse what it cannot draw."""

import numpy as np
import pytest

from configuration.camera import load_camera
from configuration.mockup import load_mockup
from configuration.render import HARSH_LIGHTING, Lighting, RenderConfig
from hil.evaluation.scenarios import camera_pose_for, target_offset
from sim_backends.renderer import PybulletRenderer, RasterRenderer, make_renderer
from sim_backends.scene import MockupScene, export_mockup_obj

# Distances from beyond the approach's start to inside the grasp; offsets up to 10 cm and 25°,
# so the ring and thruster walls and the box's sides are seen from the side.
POSES = [
    (3.0, target_offset(0.05, -0.04, 0.0, 0.10, -0.20, 0.3)),
    (2.0, target_offset(-0.08, 0.03, 0.02, -0.25, 0.15, -1.2)),
    (1.2, target_offset(0.10, 0.10, -0.05, 0.30, 0.40, 0.7)),
    (0.5, target_offset(0.02, -0.03, 0.0, -0.10, 0.05, 0.05)),
    (0.35, target_offset(0.0, 0.06, 0.0, 0.35, -0.30, 2.0)),
]


def _compare(scene, info, config, X_WC):
    reference = PybulletRenderer(scene, info, config).render(X_WC)
    raster = RasterRenderer(scene, info, config).render(X_WC)
    return reference, raster


def _assert_same(reference, raster):
    assert raster.image.shape == reference.image.shape
    differs = np.abs(raster.image - reference.image) > 1.5 / 255.0
    # Only a pixel centre lying on an edge to rounding may go either way.
    assert differs.mean() < 2e-4, f"{differs.sum()} pixels differ"
    hit = np.isfinite(reference.depth_m)
    assert np.mean(hit != np.isfinite(raster.depth_m)) < 2e-4
    both = hit & np.isfinite(raster.depth_m)
    relative = np.abs(raster.depth_m[both] - reference.depth_m[both]) / reference.depth_m[both]
    assert np.percentile(relative, 99.9) < 1e-4
    assert raster.X_CT.matrix == pytest.approx(reference.X_CT.matrix)


@pytest.mark.parametrize(
    "mockup_name", ["default", "mockup_other", "mockup_large_ring", "random:3", "random:11"]
)
@pytest.mark.parametrize("distance,offset", POSES)
def test_raster_draws_the_tinyrenderer_image(mockup_name, distance, offset):
    info = load_camera("reference").camera_info()
    with MockupScene(load_mockup(mockup_name)) as scene:
        X_WC, _ = camera_pose_for(distance, offset)
        _assert_same(*_compare(scene, info, RenderConfig(engine="pybullet"), X_WC))


@pytest.mark.parametrize("camera", ["oak_d_rgb", "small"])
def test_raster_matches_with_lens_distortion_colour_and_supersampling(camera):
    info = load_camera(camera).camera_info()
    with MockupScene(load_mockup("default")) as scene:
        for distance, offset in POSES[1:4]:
            X_WC, _ = camera_pose_for(distance, offset)
            _assert_same(*_compare(scene, info, RenderConfig(supersample=2), X_WC))


def test_raster_matches_an_obj_model_and_a_moved_mockup(tmp_path):
    mockup = load_mockup("default")
    obj = export_mockup_obj(mockup, tmp_path / "mockup.obj")
    from_file = type(mockup).model_validate(
        {**mockup.model_dump(), "model_file": {"path": obj, "xyz": [0.02, -0.01, 0.0]}}
    )
    info = load_camera("reference").camera_info()
    with MockupScene(from_file) as scene:
        X_WC, _ = camera_pose_for(1.2, POSES[2][1])
        scene.set_pose(target_offset(0.1, 0.0, 0.05, 0.0, 0.1, 0.0))
        _assert_same(*_compare(scene, info, RenderConfig(), X_WC))


def test_raster_clips_triangles_at_the_near_plane():
    """A camera 8 cm from the face, turned 60°: the bus face crosses the near plane."""
    info = load_camera("reference").camera_info()
    with MockupScene(load_mockup("default")) as scene:
        X_WC, _ = camera_pose_for(0.08, target_offset(0.0, 0.0, 0.0, 0.0, np.radians(60), 0.0))
        reference, raster = _compare(scene, info, RenderConfig(), X_WC)
        assert np.isfinite(reference.depth_m).mean() > 0.2  # the face is in the picture
        _assert_same(reference, raster)


def test_auto_engine_takes_the_raster_renderer_only_where_it_draws_the_same_image(tmp_path):
    info = load_camera("reference").camera_info()
    with MockupScene(load_mockup("default")) as scene:
        assert isinstance(make_renderer(scene, info, RenderConfig()), RasterRenderer)
        harsh = RenderConfig(lighting=HARSH_LIGHTING)
        assert isinstance(make_renderer(scene, info, harsh), PybulletRenderer)
        with pytest.raises(ValueError, match=r"render\.engine: raster draws no shadows"):
            RasterRenderer(scene, info, harsh)
        raster = RasterRenderer(scene, info, RenderConfig())
        with pytest.raises(ValueError, match="specular"):
            raster.render(camera_pose_for(2.0, POSES[0][1])[0], lighting=Lighting(specular=0.3))
    urdf = tmp_path / "plate.urdf"
    urdf.write_text(
        '<?xml version="1.0"?><robot name="plate"><link name="base"><visual><geometry>'
        '<box size="0.3 0.2 0.01"/></geometry></visual></link></robot>'
    )
    mockup = load_mockup("default")
    with_urdf = type(mockup).model_validate({**mockup.model_dump(), "model_file": {"path": urdf}})
    with MockupScene(with_urdf) as scene:
        assert scene.mesh is None
        assert isinstance(make_renderer(scene, info, RenderConfig()), PybulletRenderer)
        with pytest.raises(ValueError, match="not URDF"):
            RasterRenderer(scene, info, RenderConfig())
