"""Test helpers: a short emulated trial — the real drivers (ur-rtde, pymodbus) against the
emulated world on loopback addresses of its own — cheap enough for CI: a 160×120 camera at
10 fps, the oracle estimator (vision is not the subject), a start 0.6 m from the ring (0.1 m
before the stand-off; the track starts that much nearer), a short guarded move, and vision ages
that forgive a loaded machine's late frames."""

from __future__ import annotations

from pathlib import Path

import yaml

from configuration.rig import load_rig
from configuration.simulation import SimulationConfig
from sim_backends.ur_emulator import free_loopback_host

ORACLE = "tests.hil.fake_estimators:build_oracle"


def emulated_devices() -> dict:
    """Emulated arm, track and gripper, each on a loopback address nobody else uses now."""
    modbus = free_loopback_host()
    return {
        "arm": {"backend": "ur_rtde", "emulate": True, "host": free_loopback_host()},
        "camera": {"backend": "sim"},
        "track": {"backend": "modbus", "emulate": True, "host": modbus, "port": 5020},
        "gripper": {"backend": "modbus", "emulate": True, "host": modbus, "port": 5021},
    }


def short_trial(tmp_path: Path, *, distance_m: float = 0.6, devices: dict | None = None, **changes):
    """A short trial configuration (see the module docstring); emulated devices unless
    ``devices`` says otherwise."""
    camera = tmp_path / "small_camera.yaml"
    camera.write_text("name: small\nwidth: 160\nheight: 120\nhfov_deg: 70\n")
    rig = load_rig("rig").model_dump(mode="json")
    rig["track"]["start_position"] = 2.5 - distance_m
    rig_path = tmp_path / "rig_short.yaml"
    rig_path.write_text(yaml.safe_dump(rig))
    data = {
        "name": "emulated-short",
        "camera": str(camera),
        "rig": str(rig_path),
        "systems": [ORACLE],
        "noise": {"preset": "none"},
        "clock": "wall",
        "camera_timing": {"fps": 10, "latency_s": 0.12, "jitter_s": 0.01},
        "vision": {"log_frames_every_s": 0, "max_frame_age_s": 1.0},
        "fusion": {"coast_timeout_s": 1.0},
        "start": {"distance_m": distance_m, "max_offset_m": 0.03, "max_rotation_deg": 2.0},
        "approach": {
            "standoff": {"dwell_s": 0.3},
            "grasp": {"advance_m": 0.04, "speed": 0.04, "hold_s": 0.2},
            "supervisor": {"max_estimate_age_s": 1.0, "max_frame_age_s": 1.0},
        },
        "devices": emulated_devices() if devices is None else devices,
        "max_duration_s": 40.0,
    }
    data.update(changes)
    return SimulationConfig.model_validate(data)
