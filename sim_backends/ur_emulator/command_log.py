"""What the emulated controller received and did, for tests to assert on.

Sources: ``script`` (a register-protocol command the control script executed, with its
parameters), ``lost`` (a command that arrived on RTDE but was overwritten by a different command
before the script's next 2 ms cycle read the register — what a real controller does too),
``dashboard`` (a dashboard line), ``program`` (a script uploaded or stopped), ``safety``
(protective / emergency stop, watchdog trip), ``fault`` (an injected fault), ``rtde`` (a session
set up, started or closed).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

#: Register-protocol command ids (ur-rtde's RobotCommand::Type) and their names.
COMMAND_NAMES: dict[int, str] = {
    0: "noCommand",
    1: "moveJ",
    2: "moveJ_IK",
    3: "moveL",
    4: "moveL_FK",
    9: "speedJ",
    10: "speedL",
    11: "servoJ",
    15: "speedStop",
    16: "servoStop",
    24: "servoL",
    26: "getStepTime",
    31: "triggerProtectiveStop",
    33: "stopL",
    34: "stopJ",
    35: "setWatchdog",
    40: "getTCPOffset",
    255: "stopScript",
}


def command_name(command_id: int) -> str:
    return COMMAND_NAMES.get(command_id, f"command {command_id}")


@dataclass(frozen=True, slots=True)
class CommandRecord:
    """One event: host ``time.monotonic()`` stamp, source (see the module docstring), name,
    numeric parameters and a free-text detail."""

    stamp: float
    source: str
    name: str
    values: tuple[float, ...] = ()
    detail: str = ""


class CommandLog:
    """A bounded, append-only list of ``CommandRecord``s with a running sequence number."""

    def __init__(self, capacity: int = 200_000):
        self._records: deque[CommandRecord] = deque(maxlen=capacity)
        self._count = 0

    def add(
        self,
        stamp: float,
        source: str,
        name: str,
        values: tuple[float, ...] = (),
        detail: str = "",
    ) -> None:
        self._records.append(CommandRecord(stamp, source, name, tuple(values), detail))
        self._count += 1

    @property
    def count(self) -> int:
        """Records added so far (including any the capacity has dropped)."""
        return self._count

    def since(self, index: int = 0) -> list[CommandRecord]:
        """Records number ``index`` onwards (numbering from the first ever added)."""
        first = self._count - len(self._records)
        start = max(index - first, 0)
        return list(self._records)[start:]
