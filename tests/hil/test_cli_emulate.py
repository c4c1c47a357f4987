"""``satgrasp emulate ur``: bad input refused in one line; the foreground emulator serves the
real ur-rtde client and stops on Ctrl-C."""

import signal
import subprocess
import sys

import numpy as np
import rtde_receive
from typer.testing import CliRunner

from hil.cli import app
from sim_backends.ur_emulator import free_loopback_host

runner = CliRunner()


def test_emulate_ur_refuses_a_host_off_loopback_and_an_unknown_model():
    result = runner.invoke(app, ["emulate", "ur", "--host", "10.0.0.7"])
    assert result.exit_code == 2
    assert "--host" in result.output and "loopback only" in result.output
    assert "Traceback" not in result.output
    result = runner.invoke(app, ["emulate", "ur", "--host", "127.0.0.9", "--model", "ur99"])
    assert result.exit_code == 2 and "--model" in result.output and "ur10e" in result.output


def test_emulate_ur_serves_ur_rtde_in_the_foreground_until_interrupted():
    host = free_loopback_host()
    command = [
        sys.executable,
        "-c",
        "from hil.cli import main; main()",
        "emulate",
        "ur",
        "--host",
        host,
        "--model",
        "ur5e",
    ]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        banner = process.stdout.readline()  # printed once the ports are bound
        assert f"listening on {host}" in banner and "rtde 30004" in banner and "ur5e" in banner
        receive = rtde_receive.RTDEReceiveInterface(host, -1.0, ["actual_TCP_pose"])
        try:
            assert np.linalg.norm(receive.getActualTCPPose()[:3]) > 0.1
        finally:
            receive.disconnect()
        process.send_signal(signal.SIGINT)
        out, err = process.communicate(timeout=10)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(5)
    assert process.returncode == 0, err
    assert "UR emulator stopped." in out
