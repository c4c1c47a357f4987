"""``satgrasp emulate ur``: bad input refused in one line; the foreground emulator answers RTDE
and stops on Ctrl-C (the ur-rtde client itself drives it in tests/sim_backends)."""

import signal
import threading
import time

from typer.testing import CliRunner

from drivers.base import DeviceError
from drivers.ur_probe import probe_rtde
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


def test_emulate_ur_serves_in_the_foreground_until_interrupted():
    host = free_loopback_host()
    answered, returned = [], threading.Event()
    main = threading.main_thread().ident
    # Ctrl-C as a terminal sends it: to the main thread, with Python's own handler and SIGINT
    # deliverable — whatever an earlier test in this worker process left behind.
    handler = signal.signal(signal.SIGINT, signal.default_int_handler)
    mask = signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})

    def client() -> None:  # ur-rtde's constructors would hold the GIL: the probe speaks RTDE
        deadline = time.monotonic() + 20.0
        while time.monotonic() < deadline and not returned.is_set():
            try:
                answered.append(probe_rtde(host, timeout_s=1.0).controller_version)
                break
            except DeviceError:  # not listening yet
                time.sleep(0.05)
        if not returned.is_set():
            assert main is not None
            signal.pthread_kill(main, signal.SIGINT)

    thread = threading.Thread(target=client, daemon=True)
    thread.start()
    try:
        result = runner.invoke(app, ["emulate", "ur", "--host", host, "--model", "ur5e"])
    finally:
        returned.set()
        thread.join(25.0)
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        signal.signal(signal.SIGINT, handler)
    assert result.exit_code == 0, result.output
    assert f"listening on {host}" in result.output and "rtde 30004" in result.output
    assert "(ur5e)" in result.output and "UR emulator stopped." in result.output
    assert answered == [(5, 15, 0, 0)]
