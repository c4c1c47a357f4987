"""Devices from configuration: the real drivers built with the configured addresses and options,
and a real camera's process (here replaying a recording through depthai) handing frames with the
camera's own calibration to the vision side. Bringing the drivers up and down is exercised by
the emulated trials (test_emulated_trial.py)."""

from __future__ import annotations

import multiprocessing as mp

import numpy as np
import pytest

from configuration.devices import DevicesConfig, OakCameraDevice
from configuration.rig import load_rig
from drivers.base import DeviceTimeout
from drivers.oak import write_calibration
from hil.analysis.bench_rig import short_trial
from hil.runtime.devices import RealDevices, device_camera_main
from hil.runtime.processes import stop_process
from sim_backends.remote import RemoteCamera
from tests.drivers.test_oak import SMALL, _write_video


def test_real_devices_from_config_carry_addresses_and_options():
    devices = DevicesConfig.model_validate(
        {
            "arm": {"backend": "ur_rtde", "host": "192.168.1.10", "state_timeout_s": 0.2},
            "camera": {"backend": "oak"},
            "track": {
                "backend": "modbus",
                "host": "192.168.1.20",
                "timeout_s": 0.05,
                "command_timeout_s": 0.2,
            },
            "gripper": {"backend": "modbus", "host": "192.168.1.21", "activation_timeout_s": 4},
        }
    )
    rig = load_rig("rig")
    real = RealDevices.from_config(devices, rig)
    assert real.arm.host == "192.168.1.10" and real.arm.options.state_timeout_s == 0.2
    assert real.track.command_timeout_s == 0.2
    track, gripper = real.track.link, real.gripper.link
    assert (track.host, track.port, track.device_id, track.timeout_s) == (
        "192.168.1.20",
        502,
        1,
        0.05,
    )
    assert (gripper.host, gripper.device_id, real.gripper_activation_s) == ("192.168.1.21", 9, 4)
    with pytest.raises(ValueError, match="real devices need"):
        RealDevices.from_config(DevicesConfig(), rig)


def test_the_short_trials_track_forgives_the_stall_its_tick_deadline_forgives(tmp_path):
    # A control loop late by less than its tick deadline must not stop the track either (CI
    # once saw the short trial end on the track's 0.1 s command watchdog, 0.104 s late).
    sim = short_trial(tmp_path)
    track = RealDevices.from_config(sim.devices, load_rig("rig")).track
    assert track.command_timeout_s >= sim.approach.supervisor.max_tick_s
    assert RealDevices.from_config(
        DevicesConfig.model_validate(
            {
                "arm": {"backend": "ur_rtde", "host": "192.168.1.10"},
                "camera": {"backend": "oak"},
                "track": {"backend": "modbus", "host": "192.168.1.20"},
                "gripper": {"backend": "modbus", "host": "192.168.1.21"},
            }
        ),
        load_rig("rig"),
    ).track.command_timeout_s == pytest.approx(0.1)


def test_device_camera_process_hands_over_replayed_frames_with_their_calibration(tmp_path):
    _write_video(tmp_path / "video.avi", 12, fps=30.0)
    write_calibration(SMALL, tmp_path / "calibration.json")
    config = OakCameraDevice.model_validate(
        {
            "backend": "replay",
            "channels": 1,
            "replay": {
                "realtime": False,  # every frame, in order: the last one is there to hand over
                "video": tmp_path / "video.avi",
                "calibration": tmp_path / "calibration.json",
            },
        }
    )
    context = mp.get_context("spawn")
    frames_in, frames_out = context.Pipe(duplex=False)
    ours, theirs = context.Pipe()
    process = context.Process(target=device_camera_main, args=(config, frames_out, theirs))
    process.start()
    frames_out.close()
    theirs.close()
    try:
        assert ours.poll(60.0), "the camera process did not report"
        kind, info = ours.recv()
        assert kind == "ready", info
        assert np.allclose(info.K, SMALL.K, atol=1e-4) and (info.width, info.height) == (160, 120)
        camera = RemoteCamera(frames_in, info)
        camera.activate()
        received = []
        with pytest.raises(DeviceTimeout, match="the camera process stopped"):
            while True:  # until the replay ends (the process hands the newest: some skipped)
                received.append(camera.read(timeout_s=10.0))
        assert received and all(np.allclose(f.info.K, SMALL.K, atol=1e-4) for f in received)
        seqs = [f.seq for f in received]
        assert seqs == sorted(seqs) and seqs[-1] == 11
        process.join(10.0)
        assert process.exitcode == 0
    finally:
        stop_process(process, timeout_s=5.0)
