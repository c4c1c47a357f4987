"""The dashboard server's line protocol (port 29999): one command per line, one reply per line.

The replies are the ones UR's dashboard server documents (and ur-rtde's ``DashboardClient``
parses): ``PolyscopeVersion``, ``get serial number``, ``is in remote control``, ``stop``,
``play``, ``pause``, ``unlock protective stop`` (refused within the hold time after the stop),
``robotmode``, ``safetymode``, ``safetystatus``, ``programState``, ``running``,
``get robot model``, ``power on``/``off``, ``brake release``, ``close popup``,
``close safety popup``, ``restart safety``, ``quit``. Anything else gets ``could not
understand``.
"""

from __future__ import annotations

from collections.abc import Callable

from drivers.ur_states import RuntimeState
from sim_backends.ur_emulator.command_log import CommandLog
from sim_backends.ur_emulator.controller import EmulatedController

WELCOME = "Connected: Universal Robots Dashboard Server"
POLYSCOPE_VERSION = "URSoftware 5.15.0.0 (emulated by satgrasp)"
SERIAL_NUMBER = "20250000001"


class DashboardSession:
    """Answers dashboard lines for one connection; ``closed`` after ``quit``."""

    def __init__(
        self,
        controller: EmulatedController,
        log: CommandLog,
        *,
        clock: Callable[[], float],
        remote_control: bool = True,
    ):
        self.controller = controller
        self.log = log
        self._clock = clock
        self.remote_control = remote_control
        self.closed = False

    def reply(self, line: str) -> str:
        command = line.strip()
        self.log.add(self._clock(), "dashboard", command)
        c = self.controller
        key = command.lower()
        program = c.program.name if c.program is not None else "<unnamed>"
        answers: dict[str, Callable[[], str]] = {
            "polyscopeversion": lambda: POLYSCOPE_VERSION,
            "version": lambda: "Version: 5.15.0.0",
            "get serial number": lambda: SERIAL_NUMBER,
            "get robot model": lambda: c.model.name.upper().removesuffix("E"),
            "is in remote control": lambda: "true" if self.remote_control else "false",
            "robotmode": lambda: f"Robotmode: {c.robot_mode.name}",
            "safetymode": lambda: f"Safetymode: {c.safety_mode.name}",
            "safetystatus": lambda: f"Safetystatus: {c.safety_mode.name}",
            "programstate": lambda: f"{c.runtime_state.name} {program}",
            "running": lambda: (
                f"Program running: {str(c.runtime_state == RuntimeState.PLAYING).lower()}"
            ),
            "stop": lambda: self._stop(),
            "play": lambda: "Starting program" if c.resume_program() else "Failed to execute: play",
            "pause": lambda: self._pause(),
            "unlock protective stop": c.unlock_protective_stop,
            "power on": lambda: self._then(c.power_on, "Powering on"),
            "power off": lambda: self._then(c.power_off, "Powering off"),
            "brake release": lambda: self._then(c.brake_release, "Brake releasing"),
            "close popup": lambda: "closing popup",
            "close safety popup": lambda: "closing safety popup",
            "restart safety": lambda: "Restarting safety",
            "quit": lambda: self._quit(),
        }
        answer = answers.get(key)
        if answer is None:
            return f"could not understand: '{command}'"
        return answer()

    def _stop(self) -> str:
        self.controller.stop_program("dashboard stop")
        return "Stopped"

    def _pause(self) -> str:
        self.controller.pause_program("dashboard pause")
        return "Pausing program"

    @staticmethod
    def _then(action: Callable[[], None], answer: str) -> str:
        action()
        return answer

    def _quit(self) -> str:
        self.closed = True
        return "Disconnected"
