"""``satgrasp check-rig``: ready against the emulators, not ready — fast, with each driver's
reason — when nothing listens, bounded when a device never answers, one line for a bad file;
and, with SATGRASP_RIG_CONFIG set, the real rig (hardware)."""

import os
import socket
import time
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from hil.analysis.bench_rig import short_trial
from hil.cli import app
from sim_backends.ur_emulator import free_loopback_host

# Wall-clock trials run alone (`make test` runs them after the rest, one at a time): beside
# another test on two cores they starve their own emulators and vision processes.
pytestmark = pytest.mark.wall_clock

runner = CliRunner()


def _write(tmp_path: Path, data: dict) -> Path:
    path = tmp_path / "rig_check.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _nothing_listening(**arm) -> dict:
    """A real rig's devices on loopback addresses where nothing listens."""
    host = free_loopback_host()
    return {
        "name": "nothing-there",
        "clock": "wall",
        "devices": {
            "arm": {"backend": "ur_rtde", "host": free_loopback_host(), **arm},
            "camera": {
                "backend": "replay",
                "replay": {"video": "/nonexistent/video.avi", "calibration": "/nonexistent/c.json"},
            },
            "track": {"backend": "modbus", "host": host, "port": 5020},
            "gripper": {"backend": "modbus", "host": host, "port": 5021},
        },
    }


def _lines(output: str) -> dict[str, str]:
    return {line.split()[0]: line for line in output.splitlines() if line.split()}


def test_check_rig_against_the_emulators_reports_every_device_ready(tmp_path):
    config = short_trial(tmp_path).model_dump(mode="json")
    result = runner.invoke(app, ["check-rig", "--config", str(_write(tmp_path, config))])
    assert result.exit_code == 0, result.output
    lines = _lines(result.output)
    arm_host = config["devices"]["arm"]["host"]
    assert "ready" in lines["arm"] and f"UR {arm_host}" in lines["arm"]
    assert "safety mode NORMAL, robot mode RUNNING" in lines["arm"]
    assert "ready" in lines["camera"] and "160×120" in lines["camera"]
    assert "ready" in lines["track"] and "travel 0.000…2.050 m" in lines["track"]
    assert "ready" in lines["gripper"] and "not activated" in lines["gripper"]
    assert "rig ready" in result.output and "NOT READY" not in result.output


def test_check_rig_with_nothing_listening_is_not_ready_fast_naming_each_reason(tmp_path):
    path = _write(tmp_path, _nothing_listening())
    start = time.monotonic()
    result = runner.invoke(app, ["check-rig", "--config", str(path)])
    elapsed = time.monotonic() - start
    assert result.exit_code == 1, result.output
    lines = _lines(result.output)
    assert "NOT READY" in lines["arm"] and "refused the connection" in lines["arm"]
    assert "NOT READY" in lines["camera"] and "no such file" in lines["camera"]
    for device in ("track", "gripper"):
        assert "NOT READY" in lines[device] and "nothing accepts connections" in lines[device]
    assert "rig NOT ready" in result.output and "Traceback" not in result.output
    assert elapsed < 5.0, elapsed


def test_check_rig_gives_up_on_a_device_that_never_answers(tmp_path):
    # The arm's own time-outs would wait 30 s for this listener, which accepts and never
    # answers; the check is stopped after its 1 s.
    path = _write(tmp_path, _nothing_listening(connect_timeout_s=30.0))
    host = yaml.safe_load(path.read_text())["devices"]["arm"]["host"]
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as silent:
        silent.bind((host, 30004))
        silent.listen(4)
        start = time.monotonic()
        result = runner.invoke(app, ["check-rig", "--config", str(path), "--timeout-s", "1"])
        elapsed = time.monotonic() - start
    assert result.exit_code == 1, result.output
    arm = _lines(result.output)["arm"]
    assert f"no answer within 1 s while connecting to the UR at {host}" in arm, arm
    assert elapsed < 5.0, elapsed


def test_check_rig_refuses_a_mixed_rig_naming_the_file_and_the_field(tmp_path):
    data = _nothing_listening()
    data["devices"]["track"] = {"backend": "sim"}
    path = _write(tmp_path, data)
    result = runner.invoke(app, ["check-rig", "--config", str(path)])
    assert result.exit_code == 2
    assert str(path) in result.output and "devices (line" in result.output
    assert "track is simulated but arm is ur_rtde" in result.output
    assert "Traceback" not in result.output


@pytest.mark.hardware
@pytest.mark.skipif(
    not os.environ.get("SATGRASP_RIG_CONFIG"),
    reason="set SATGRASP_RIG_CONFIG to the real rig's trial configuration (configs/real.yaml)",
)
def test_check_rig_on_the_real_rig_is_ready():
    """Read-only: connects to every device of the configured rig; nothing moves."""
    result = runner.invoke(
        app, ["check-rig", "--config", os.environ["SATGRASP_RIG_CONFIG"], "--timeout-s", "15"]
    )
    assert result.exit_code == 0, result.output
