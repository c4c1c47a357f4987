import numpy as np
import pytest
import yaml

from configuration.camera import CameraConfig, load_camera
from configuration.files import ConfigError, builtin_names, load_config, parse_yaml_text
from configuration.mockup import MockupConfig, load_mockup
from configuration.simulation import load_simulation


def test_builtin_configs_load_from_any_directory(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert {"reference", "oak_d_rgb"} <= set(builtin_names("cameras"))
    ref = load_camera("reference").camera_info()
    assert (ref.width, ref.height) == (640, 480)
    assert ref.K[0, 0] == pytest.approx(320 / np.tan(np.radians(35)))
    assert not ref.has_distortion
    oak = load_camera("oak_d_rgb").camera_info()
    assert (oak.width, oak.height, oak.channels) == (1280, 800, 3) and oak.has_distortion
    mockup = load_mockup("default")
    assert mockup.marman_ring.outer_diameter == 0.60
    assert mockup.centre_panel.side == 0.30


def test_default_mockup_target_model():
    model = load_mockup("default").target_model()
    assert model.panel_side == pytest.approx(0.30)
    discs = [f for f in model.point_features if f.kind == "disc"]
    assert len(discs) >= 8
    names = [c.name for c in model.circles]
    assert names[:3] == ["ring_outer", "ring_inner", "thruster_exit"]
    exit_circle = model.circle("thruster_exit")
    # Off the ring axis, so circles alone fix roll.
    assert np.hypot(*exit_circle.center_T[:2]) > 0.4
    assert model.circle("ring_outer").radius == pytest.approx(0.30)
    assert model.circle("ring_inner").radius == pytest.approx(0.25)
    with pytest.raises(KeyError, match="no circle"):
        model.circle("antenna")


BOLTS = (
    "fasteners:\n"
    "  - {name: b, surface: ring, diameter: 0.02, circle_pattern: {radius: 0.275, count: 8}}\n"
)


def _write(tmp_path, text):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    return path


def test_wrong_type_names_file_field_and_line(tmp_path):
    path = _write(tmp_path, "name: x\nmarman_ring:\n  outer_diameter: big\n")
    with pytest.raises(ConfigError) as info:
        load_mockup(path)
    message = str(info.value)
    assert str(path) in message
    assert "marman_ring.outer_diameter (line 3)" in message
    assert "valid number" in message and "'big'" in message


def test_unknown_key_is_rejected_with_its_line(tmp_path):
    path = _write(tmp_path, "name: x\ncentre_panel:\n  side: 0.3\n  sidee: 0.3\n")
    with pytest.raises(ConfigError, match=r"centre_panel\.sidee \(line 4\): unknown key"):
        load_mockup(path)


def test_missing_field_is_named(tmp_path):
    path = _write(tmp_path, "width: 640\nheight: 480\nhfov_deg: 70\n")
    with pytest.raises(ConfigError, match=r"name.*required field is missing"):
        load_camera(path)


def test_out_of_range_and_inconsistent_values(tmp_path):
    with pytest.raises(ConfigError, match=r"hfov_deg \(line 4\).*less than 179"):
        load_camera(_write(tmp_path, "name: c\nwidth: 640\nheight: 480\nhfov_deg: 200\n"))
    with pytest.raises(ConfigError, match="either hfov_deg or fx/fy/cx/cy"):
        load_camera(_write(tmp_path, "name: c\nwidth: 640\nheight: 480\nhfov_deg: 70\nfx: 400\n"))
    with pytest.raises(ConfigError, match="distortion must have"):
        load_camera(
            _write(
                tmp_path,
                "name: c\nwidth: 640\nheight: 480\nhfov_deg: 70\ndistortion: [0.1, 0.2, 0.3]\n",
            )
        )
    with pytest.raises(ConfigError, match="panel's corners must lie inside"):
        load_mockup(_write(tmp_path, "name: m\ncentre_panel: {side: 0.4}\n"))
    with pytest.raises(ConfigError, match=r"fasteners.0 \(ring_bolt\): a fastener at"):
        text = (
            "name: m\nfasteners:\n  - {name: ring_bolt, surface: ring, diameter: 0.02, "
            "circle_pattern: {radius: 0.1, count: 8}}\n"
        )
        load_mockup(_write(tmp_path, text))
    with pytest.raises(ConfigError, match="at least 8 point features"):
        load_mockup(_write(tmp_path, "name: m\nfasteners: []\n"))
    with pytest.raises(ConfigError, match="overlaps the marman ring"):
        load_mockup(_write(tmp_path, "name: m\nthruster: {center: [0.3, 0.0]}\n"))


def test_unreadable_inputs_fail_clearly(tmp_path):
    with pytest.raises(ConfigError, match="file not found"):
        load_camera(tmp_path / "missing.yaml")
    with pytest.raises(ConfigError, match=r"no built-in configuration named 'nikon'.*reference"):
        load_camera("nikon")
    with pytest.raises(ConfigError, match="the file is empty"):
        load_camera(_write(tmp_path, ""))
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_camera(_write(tmp_path, "name: [unclosed\n"))
    with pytest.raises(ConfigError, match="mapping at the top level"):
        load_camera(_write(tmp_path, "- a\n- b\n"))


def test_configs_are_frozen():
    camera = load_camera("reference")
    with pytest.raises(Exception, match="frozen"):
        camera.width = 10


def test_parse_yaml_text_validates_any_model():
    camera = parse_yaml_text(
        "name: c\nwidth: 64\nheight: 48\nfx: 50\nfy: 50\ncx: 31.5\ncy: 23.5\n",
        CameraConfig,
        "inline",
    )
    assert camera.camera_info().K[0, 2] == 31.5


def test_model_file_path_is_relative_to_the_yaml(tmp_path):
    (tmp_path / "meshes").mkdir()
    path = _write(tmp_path, "name: m\nmodel_file: {path: meshes/sat.obj, scale: 0.001}\n" + BOLTS)
    mockup = load_mockup(path)
    assert mockup.model_file.path == (tmp_path / "meshes" / "sat.obj").resolve()
    # The feature geometry still comes from the config.
    assert mockup.target_model().panel_side == pytest.approx(0.30)


def test_load_config_with_explicit_model(tmp_path):
    path = _write(tmp_path, "name: m\n" + BOLTS)
    assert isinstance(load_config(path, MockupConfig), MockupConfig)


def test_simulation_names_its_files_relative_to_itself_from_any_directory(tmp_path, monkeypatch):
    folder = tmp_path / "study"
    (folder / "cameras").mkdir(parents=True)
    (folder / "cameras" / "small.yaml").write_text(
        "name: s\nwidth: 160\nheight: 120\nhfov_deg: 70\n"
    )
    mockup = load_mockup("default")
    (folder / "my_mockup.yaml").write_text(yaml.safe_dump(mockup.model_dump(mode="json")))
    (folder / "sim.yaml").write_text(
        "name: s\nmockup: my_mockup.yaml\ncamera: cameras/small.yaml\nrig: rig\n"
    )
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    sim = load_simulation(folder / "sim.yaml")
    assert sim.mockup == str((folder / "my_mockup.yaml").resolve())
    assert sim.camera == str((folder / "cameras" / "small.yaml").resolve())
    assert sim.rig == "rig"  # a built-in name stays one
    assert load_mockup(sim.mockup) == mockup and load_camera(sim.camera).width == 160


def test_simulation_naming_a_missing_file_says_where_it_looked(tmp_path):
    (tmp_path / "sim.yaml").write_text("name: s\nmockup: my_mockup.yaml\n")
    with pytest.raises(ConfigError) as raised:
        load_simulation(tmp_path / "sim.yaml")
    assert raised.value.source == str(tmp_path / "sim.yaml")
    assert raised.value.problems == [
        f"mockup: file not found: {(tmp_path / 'my_mockup.yaml').resolve()} "
        "(a relative path is taken from this file's folder)"
    ]


def test_mockup_allows_markers_inside_the_ring_and_an_off_centre_panel(tmp_path):
    text = (
        "name: m\ncentre_panel: {side: 0.2, center: [0.04, -0.03]}\n"
        + BOLTS
        + "  - {name: marker, "
        "surface: bus, diameter: 0.03, height: 0.0002, positions: [[0.0, -0.205], [0.17, 0.1]]}\n"
    )
    mockup = load_mockup(_write(tmp_path, text))
    model = mockup.target_model()
    assert model.panel_corners_T.mean(axis=0)[:2] == pytest.approx([0.04, -0.03])
    marker = next(f for f in model.point_features if f.name == "marker_0")
    assert marker.p_T[:2] == pytest.approx([0.0, -0.205])
    assert not marker.brighter  # dark (default colour) on the gold-ish face


@pytest.mark.parametrize(
    ("position", "problem"),
    [
        ("[0.0, 0.0]", "under the ring, panel or thruster"),  # under the panel
        ("[0.0, 0.27]", "under the ring, panel or thruster"),  # under the ring
        ("[0.5, 0.42]", "under the ring, panel or thruster"),  # under the thruster
        ("[0.9, 0.0]", "off its bus"),
    ],
)
def test_mockup_refuses_a_bus_fastener_where_another_part_stands(tmp_path, position, problem):
    text = (
        "name: m\n" + BOLTS + "  - {name: marker, surface: bus, diameter: 0.03, "
        f"positions: [{position}]}}\n"
    )
    with pytest.raises(ConfigError, match=rf"fasteners.1 \(marker\).*{problem}"):
        load_mockup(_write(tmp_path, text))


def test_mockup_refuses_overlapping_fasteners_and_a_panel_off_the_ring(tmp_path):
    text = "name: m\n" + BOLTS + "  - {name: extra, surface: ring, diameter: 0.02, positions: "
    text += "[[0.275, 0.005]]}\n"
    with pytest.raises(ConfigError, match=r"fasteners.1 \(extra\).*overlaps one of b"):
        load_mockup(_write(tmp_path, text))
    with pytest.raises(ConfigError, match="panel's corners must lie inside"):
        load_mockup(_write(tmp_path, "name: m\ncentre_panel: {center: [0.1, 0.0]}\n" + BOLTS))


def test_a_simulated_trial_renders_anti_aliased_frames_under_small_noise():
    """``supersample: auto`` (the embedded default): 4 × 4 samples in 4 passes where the noise
    is too small to hide a point-sampled image's staircase edges, 1 under the study's noise; a
    number is kept."""
    from configuration.render import NoiseConfig, RenderConfig
    from configuration.simulation import with_overrides

    sim = load_simulation("sim")
    assert sim.render.supersample == "auto"
    for preset, expected in (
        ("low", (1, 1)),
        ("high", (1, 1)),
        ("sensor", (4, 4)),
        ("none", (4, 4)),
    ):
        resolved = with_overrides(sim, noise={"preset": preset})
        render = resolved.render.for_noise(resolved.noise)
        assert (render.supersample, render.passes) == expected, preset
    small = NoiseConfig(preset="low", variance=0.001)
    assert RenderConfig(supersample="auto").for_noise(small).supersample == 4
    assert RenderConfig(supersample=2).for_noise(NoiseConfig(preset="sensor")).supersample == 2


def test_a_named_light_for_a_closed_loop_approach():
    """``satgrasp approach --light``: a random mock-up gets its own random light (the one the
    matrix and the open-loop path render it under), any other mock-up the seed's."""
    from configuration.random_mockup import random_lighting
    from configuration.render import HARSH_LIGHTING
    from configuration.simulation import with_light, with_settings

    sim = load_simulation("sim")
    on_random = with_settings(sim, ["mockup=random:103"])
    assert with_light(on_random, "random", 1).render.lighting == random_lighting(103)
    assert with_light(sim, "random", 7).render.lighting == random_lighting(7)
    assert with_light(sim, "harsh", 7).render.lighting == HARSH_LIGHTING
    assert with_light(sim, "harsh", 7).render.supersample == sim.render.supersample
    with pytest.raises(ValueError, match="light must be one of default, harsh, random"):
        with_light(sim, "dusk", 1)


def test_config_error_survives_the_trip_back_from_a_worker_process():
    import pickle

    error = ConfigError("mockup.yaml", ["marman_ring.outer_diameter (line 12): too small"])
    back = pickle.loads(pickle.dumps(error))
    assert (type(back), str(back), back.source, back.problems) == (
        ConfigError,
        str(error),
        error.source,
        error.problems,
    )
