import numpy as np
import pytest

from configuration.files import ConfigError
from configuration.mockup import gray, load_mockup
from configuration.random_mockup import (
    MIN_CONTRAST,
    has_symmetry_breaker,
    mockup_names,
    random_lighting,
    random_mockup,
)


def test_random_mockup_is_a_pure_function_of_its_seed():
    assert random_mockup(7) == random_mockup(7)
    assert random_mockup(7) != random_mockup(8)
    assert load_mockup("random:7") == random_mockup(7)
    assert random_lighting(7) == random_lighting(7)


def test_random_mockups_vary_within_what_a_camera_can_see():
    draws = [random_mockup(seed) for seed in range(40)]
    breakers = [has_symmetry_breaker(m) for m in draws]
    assert 0 < breakers.count(False) < 12  # a few draws have nothing to decide a quarter turn
    assert any(m.thruster is None for m in draws) and any(m.thruster for m in draws)
    darker = [gray(m.centre_panel.color) < gray(m.bus_face.color) for m in draws]
    assert 5 < sum(darker) < 35  # panels of both polarities
    assert any(m.centre_panel.center != (0.0, 0.0) for m in draws)
    assert any(g.name == "marker" for m in draws for g in m.fasteners)
    for m in draws:
        face = gray(m.bus_face.color)
        assert abs(gray(m.marman_ring.color) - face) >= MIN_CONTRAST
        assert abs(gray(m.centre_panel.color) - face) >= MIN_CONTRAST
        assert len(m.target_model().point_features) >= 12  # 4 corners + at least 8 discs


def test_default_mockup_has_a_symmetry_breaker_and_a_symmetric_one_has_none():
    assert has_symmetry_breaker(load_mockup("default"))
    symmetric = next(m for m in map(random_mockup, range(40)) if not has_symmetry_breaker(m))
    assert symmetric.thruster is None and symmetric.centre_panel.center == (0.0, 0.0)


def test_mockup_names_expand_ranges_and_refuse_bad_ones():
    assert mockup_names("random:3-5,default") == ["random:3", "random:4", "random:5", "default"]
    with pytest.raises(ValueError, match="random:A-B"):
        mockup_names("random:3-x")
    with pytest.raises(ValueError, match="random:SEED"):
        load_mockup("random:seven")


def test_random_lighting_ranges_from_soft_to_a_low_side_sun():
    lights = [random_lighting(seed) for seed in range(40)]
    elevation = [np.degrees(np.arcsin(lt.sun_direction_T[2])) for lt in lights]
    assert min(elevation) < 25 and max(elevation) > 60
    assert any(lt.shadows for lt in lights) and not all(lt.shadows for lt in lights)
    assert min(lt.ambient for lt in lights) < 0.15


def test_unknown_builtin_still_fails_as_a_config_error():
    with pytest.raises(ConfigError):
        load_mockup("nosuchmockup")
