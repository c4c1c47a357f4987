import pickle

import numpy as np
import pytest

from configuration.files import ConfigError, parse_yaml_text
from configuration.rig import ArmConfig, GripperConfig, RigConfig, TrackConfig, load_rig
from configuration.simulation import load_simulation


def test_builtin_rig_loads_with_frames():
    rig = load_rig()
    assert rig.arm.model == "ur10e"
    assert rig.arm.control_rate_hz == 500
    assert rig.track.axis_unit_W == pytest.approx([-1.0, 0.0, 0.0])
    assert rig.gripper.modbus.device_id == 9
    # the mock-up's ring face looks back along the track, toward the arm
    z_T_W = (rig.track.X_WM0.pose @ rig.track.X_MT.pose).R[:, 2]
    assert z_T_W == pytest.approx([-1.0, 0.0, 0.0], abs=1e-12)


def test_rig_config_errors_name_the_field():
    text = (
        "name: bad\narm:\n  q0_deg: [0, -90, 200, 0, 0, 0]\n"
        "track:\n  travel_min: 1.0\n  travel_max: 0.5\n"
        "gripper:\n  object_width: 0.1\n  speed: 3\n"
    )
    with pytest.raises(ConfigError) as error:
        parse_yaml_text(text, RigConfig, "rig.yaml")
    message = str(error.value)
    assert "arm (line 2): q0_deg[2] = 200.0° is outside the joint range ±180.0°" in message
    assert "travel_min (1.0 m) must be less than travel_max (0.5 m)" in message
    assert "gripper.speed (line 9): unknown key" in message


def test_rig_config_validators():
    with pytest.raises(ValueError, match=r"object_width 0\.1 m does not fit"):
        GripperConfig(object_width=0.1)
    with pytest.raises(ValueError, match="axis_W must be a non-zero"):
        TrackConfig(axis_W=(0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match=r"start_position 3\.0 m is outside"):
        TrackConfig(start_position=3.0)
    with pytest.raises(ValueError, match=r"q0_deg\[5\] = 358.0° .* less the 5.0° margin"):
        ArmConfig(q0_deg=(0, -90, 0, -90, 0, 358))
    rig = load_rig()
    with pytest.raises(ValueError, match="same device"):
        RigConfig(
            name="x",
            arm=rig.arm,
            track=rig.track,
            gripper=rig.gripper.model_copy(update={"modbus": rig.track.modbus}),
        )


def test_pose_config_uses_fixed_axis_rpy():
    rig = load_rig()
    rotation = rig.track.X_MT.pose.R
    assert rotation == pytest.approx(np.array([[0, 0, -1], [-1, 0, 0], [0, 1, 0]]), abs=1e-12)


def test_simulation_config_survives_pickling_for_campaign_processes():
    sim = load_simulation("sim")
    again = pickle.loads(pickle.dumps(sim))
    assert again == sim
    assert dict(again.fusion.covariance_scale) == dict(sim.fusion.covariance_scale)
    assert again.fusion.floor_for("lines") == sim.fusion.floor_for("lines")
