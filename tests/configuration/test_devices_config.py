"""The devices: section — one coherent rig (simulated, emulated or real), anything mixed refused
with a reason naming the devices — and the shipped trial configurations."""

import pytest
from pydantic import ValidationError

from configuration.devices import (
    DevicesConfig,
    ModbusTrackDevice,
    OakCameraDevice,
    RobotiqGripperDevice,
    SimDevice,
    URArmDevice,
)
from configuration.simulation import load_simulation

UR = {"backend": "ur_rtde", "host": "127.0.0.2"}
TRACK = {"backend": "modbus", "host": "127.0.0.3", "port": 5020}
GRIPPER = {"backend": "modbus", "host": "127.0.0.4", "port": 5021}
OAK = {"backend": "oak"}


def devices(**fields) -> DevicesConfig:
    return DevicesConfig.model_validate(fields)


def emulated(**extra) -> dict:
    return {
        name: {**spec, "emulate": True}
        for name, spec in (("arm", UR), ("track", TRACK), ("gripper", GRIPPER))
    } | extra


def test_devices_config_defaults_to_the_simulated_rig():
    config = DevicesConfig()
    assert config.kind == "sim"
    assert all(isinstance(d, SimDevice) for d in (config.arm, config.camera, config.track))


def test_devices_config_reads_an_emulated_rig_with_a_rendered_camera():
    config = devices(**emulated(camera={"backend": "sim"}))
    assert config.kind == "emulated"
    assert isinstance(config.arm, URArmDevice) and config.arm.emulate
    assert isinstance(config.track, ModbusTrackDevice) and config.track.device_id == 1
    assert isinstance(config.gripper, RobotiqGripperDevice) and config.gripper.device_id == 9
    assert config.track.endpoint().port == 5020 and config.track.timeout_s == 0.1


def test_devices_config_reads_a_real_rig_and_gives_the_arm_driver_its_options():
    config = devices(arm={**UR, "state_timeout_s": 0.2}, camera=OAK, track=TRACK, gripper=GRIPPER)
    assert config.kind == "real"
    assert isinstance(config.camera, OakCameraDevice)
    arm = config.arm.driver()
    assert arm.host == "127.0.0.2" and arm.options.state_timeout_s == 0.2


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"arm": UR}, "track is simulated but arm is ur_rtde"),
        ({"arm": UR, "track": TRACK, "gripper": GRIPPER}, "camera: sim renders the simulated"),
        ({"camera": OAK}, "a real camera needs the real"),
        (
            emulated(gripper={**GRIPPER, "emulate": False}),
            "arm, track emulated but gripper not",
        ),
        ({"arm": {"backend": "ur_rtde"}}, "host"),
        ({"arm": {"backend": "ur-rtde", "host": "x"}}, "tag 'ur-rtde'"),
        ({"track": {**TRACK, "timeout_s": 10}}, "timeout_s"),
        ({"camera": {"backend": "replay"}}, "backend replay needs a replay: block"),
        ({"arm": {**UR, "emulated": True}}, "emulated"),  # the key is emulate
    ],
)
def test_devices_config_refuses_what_would_not_be_one_rig(fields, message):
    with pytest.raises(ValidationError, match=message):
        devices(**fields)


def test_shipped_configs_are_one_rig_each_and_emulated_differs_from_sim_only_in_its_devices():
    sim, emulated_, real = (load_simulation(n) for n in ("sim", "emulated", "real"))
    assert (sim.devices.kind, emulated_.devices.kind, real.devices.kind) == (
        "sim",
        "emulated",
        "real",
    )
    assert emulated_.clock == real.clock == "wall"
    a, b = sim.model_dump(mode="json"), emulated_.model_dump(mode="json")
    assert sorted(k for k in a if a[k] != b[k]) == ["clock", "devices", "name"]
    hosts = {emulated_.devices.arm.host, emulated_.devices.track.host}
    assert len(hosts | {emulated_.devices.gripper.host}) == 3  # an address per emulator
