"""The emulator in a process of its own, and the handle tests and tools hold on it.

A separate process, because ur-rtde's constructors hold the GIL while they wait for the
controller: an emulator thread in the client's process would never get to answer them. The
process is started from a fork server (a clean single-threaded parent that has imported the
emulator once, so each start costs a fork, not an interpreter start-up and imports), reports
"ready" — or why it could not bind — over a pipe before ``start()`` returns (no sleeps), takes
fault-injection and inspection requests over the same pipe, and is stopped within a bounded
time: asked first, then terminated, then killed.
"""

from __future__ import annotations

import contextlib
import itertools
import multiprocessing
import os
import threading
from collections.abc import Sequence

import numpy as np

from configuration.rig import ArmConfig, load_rig
from drivers.ur_probe import DASHBOARD_PORT, RTDE_PORT, SCRIPT_PORT
from sim_backends.loopback import bindable, check_loopback
from sim_backends.ur_emulator.command_log import CommandRecord
from sim_backends.ur_emulator.server import EmulatorSettings, EmulatorStatus, serve

_CONTEXT = multiprocessing.get_context("forkserver")
_CONTEXT.set_forkserver_preload(["sim_backends.ur_emulator.server"])
_HOSTS = itertools.count()


class EmulatorError(RuntimeError):
    """The emulator process could not start, answer or stop as asked."""


def arm_config(config: str = "rig", model: str | None = None) -> ArmConfig:
    """The arm of rig ``config`` (a built-in name or a YAML path), optionally another model."""
    arm = load_rig(config).arm
    if model is None:
        return arm
    return ArmConfig.model_validate({**arm.model_dump(), "model": model})


def free_loopback_host() -> str:
    """A loopback address whose dashboard, script and RTDE ports are free now.

    Addresses are 127.a.b.c with (a, b) from this process id — distinct for processes alive
    together, so parallel pytest workers and other sessions on the machine do not collide — and
    c counting up within the process.
    """
    pid = os.getpid()
    block = f"127.{1 + (pid >> 8) % 254}.{pid & 0xFF}"
    for _ in range(253):
        host = f"{block}.{2 + next(_HOSTS) % 253}"
        if all(bindable(host, port) for port in (DASHBOARD_PORT, SCRIPT_PORT, RTDE_PORT)):
            return host
    raise EmulatorError(f"no free loopback address in {block}.0/24")


class UREmulator:
    """A UR controller emulator on ``host`` (127.x.y.z) at ports 29999, 30003 and 30004.

    Use as a context manager (``with UREmulator(host) as emulator:``) or call ``start()`` and
    ``stop()``; ``stop()`` always leaves no process behind. ``arm`` is the modelled arm (default:
    ``configs/rig.yaml``'s). The other methods inject faults and read what happened; each
    waits for the emulator's answer for at most ``request_timeout_s``.
    """

    def __init__(
        self,
        host: str,
        *,
        arm: ArmConfig | None = None,
        unlock_delay_s: float = 5.0,
        remote_control: bool = True,
        seed: int = 0,
        start_timeout_s: float = 20.0,
        stop_timeout_s: float = 3.0,
        request_timeout_s: float = 5.0,
    ):
        check_loopback(host, ipv4_only=True)
        self.host = host
        self.settings = EmulatorSettings(
            host=host,
            arm=arm if arm is not None else arm_config(),
            unlock_delay_s=unlock_delay_s,
            remote_control=remote_control,
            seed=seed,
        )
        self.start_timeout_s = start_timeout_s
        self.stop_timeout_s = stop_timeout_s
        self.request_timeout_s = request_timeout_s
        self._process: multiprocessing.process.BaseProcess | None = None
        self._pipe = None
        self._lock = threading.Lock()

    # --- lifecycle ------------------------------------------------------------------------------
    def start(self) -> UREmulator:
        if self._process is not None:
            raise EmulatorError(f"the emulator on {self.host} is already running")
        parent, child = _CONTEXT.Pipe()
        process = _CONTEXT.Process(
            target=serve, args=(self.settings, child), name=f"ur-emulator-{self.host}", daemon=True
        )
        process.start()
        child.close()
        self._process, self._pipe = process, parent
        try:
            if not parent.poll(self.start_timeout_s):
                raise EmulatorError(
                    f"the emulator on {self.host} did not report ready within {self.start_timeout_s:g} s"
                )
            kind, detail = parent.recv()
        except (EOFError, OSError):
            kind, detail = "error", f"the emulator process exited (code {process.exitcode})"
        except EmulatorError:
            self.stop()
            raise
        if kind != "ready":
            self.stop()
            raise EmulatorError(f"UR emulator on {self.host}: {detail}")
        return self

    def stop(self) -> None:
        """Ask the process to stop; terminate, then kill it if it does not within the time-out."""
        process, pipe = self._process, self._pipe
        self._process, self._pipe = None, None
        if process is None:
            return
        try:
            if process.is_alive():
                with contextlib.suppress(OSError, ValueError):
                    pipe.send(("stop", (), {}))
                process.join(self.stop_timeout_s)
            if process.is_alive():
                process.terminate()
                process.join(1.0)
            if process.is_alive():
                process.kill()
                process.join(1.0)
        finally:
            pipe.close()
            if not process.is_alive():
                process.close()

    @property
    def pid(self) -> int | None:
        return None if self._process is None else self._process.pid

    @property
    def running(self) -> bool:
        return self._process is not None and self._process.is_alive()

    def __enter__(self) -> UREmulator:
        return self.start()

    def __exit__(self, *exc_info) -> None:
        self.stop()

    # --- requests -----------------------------------------------------------------------------
    def _request(self, name: str, *args, **kwargs):
        with self._lock:
            if self._process is None:
                raise EmulatorError(f"the emulator on {self.host} is not running")
            try:
                self._pipe.send((name, args, kwargs))
                if not self._pipe.poll(self.request_timeout_s):
                    raise EmulatorError(
                        f"the emulator on {self.host} did not answer {name!r} within "
                        f"{self.request_timeout_s:g} s"
                    )
                kind, value = self._pipe.recv()
            except (EOFError, OSError) as exc:
                raise EmulatorError(f"the emulator on {self.host} is gone ({exc})") from None
        if kind != "ok":
            raise ValueError(value)
        return value

    def status(self) -> EmulatorStatus:
        return self._request("status")

    def commands(self, since: int = 0) -> list[CommandRecord]:
        """The command log from record number ``since`` (see ``command_log``)."""
        return self._request("commands", since)

    def drop_link(self) -> None:
        """Close every connection and stop listening until ``restore_link()``."""
        self._request("drop_link")

    def restore_link(self) -> None:
        self._request("restore_link")

    def stall_outputs(self, stalled: bool = True) -> None:
        """Send nothing (no data, no replies) while ``stalled``; inputs still arrive."""
        self._request("stall_outputs", stalled)

    def set_jitter(self, jitter_s: float, seed: int | None = None) -> None:
        """Delay each data package by a uniform random 0…``jitter_s`` seconds."""
        self._request("set_jitter", jitter_s, seed)

    def protective_stop(self, *, program_keeps_running: bool = False) -> None:
        """Raise a protective stop (the joints stop at the next period)."""
        self._request("protective_stop", program_keeps_running=program_keeps_running)

    def unlock_protective_stop(self) -> str:
        """The dashboard's answer to unlocking (refused within ``unlock_delay_s``)."""
        return self._request("unlock_protective_stop")

    def emergency_stop(self) -> None:
        self._request("emergency_stop")

    def release_emergency_stop(self) -> None:
        """Release the e-stop; the robot then needs ``power on`` and ``brake release``."""
        self._request("release_emergency_stop")

    def set_tcp_force(self, wrench_B: Sequence[float]) -> None:
        """What ``actual_TCP_force`` reports from now on: [f (N), τ (N·m)] in B."""
        self._request("set_tcp_force", [float(v) for v in wrench_B])

    def set_tcp_offset(self, offset: Sequence[float]) -> None:
        """Set the controller's TCP offset [x, y, z, rx, ry, rz] (m, rad) in the flange frame;
        the TCP pose and speed then refer to that point, as on a UR."""
        self._request("set_tcp_offset", [float(v) for v in offset])

    def set_joint_positions(self, q: Sequence[float]) -> None:
        """Place the resting arm at ``q`` (rad)."""
        self._request("set_joint_positions", np.asarray(q, dtype=float).tolist())

    def claim_inputs(self, names: Sequence[str]) -> None:
        """A fieldbus owns these RTDE inputs: clients setting them up get ``IN_USE``."""
        self._request("claim_inputs", list(names))

    def release_inputs(self) -> None:
        self._request("release_inputs")
