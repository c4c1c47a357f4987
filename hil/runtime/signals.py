"""SIGINT (Ctrl-C) and SIGTERM as a request to stop, not as an exception thrown into the control
loop at whatever line it happens to be on.

Python runs signal handlers in the main thread between two bytecodes. An exception raised there
(the default ``KeyboardInterrupt``) can land in the middle of a driver call or a log write, and
SIGTERM by default ends the process at once, without stopping anything. Here a handler does only
one of two things:

* while a control loop runs, it hands the request to ``ControlLoop.request_stop`` (a flag); the
  loop stops the arm and the track before its next tick, ends the trial with the reason, and
  the trial closes its log as on any other ending;
* otherwise (start-up, after the trial) it raises ``Interrupted`` in the main thread, which the
  code in progress cleans up after as after any exception.
"""

from __future__ import annotations

import signal
from collections.abc import Callable
from types import FrameType
from typing import Any

#: The signals that ask a trial to stop: Ctrl-C, and ``kill``'s default (systemd, docker stop).
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Interrupted(KeyboardInterrupt):
    """A stop signal arrived while no control loop was running. ``exit_code``: 128 + its number,
    as a shell reports a process ended by that signal (130 for SIGINT, 143 for SIGTERM)."""

    def __init__(self, signum: int):
        self.signum = signum
        self.name = signal.Signals(signum).name
        super().__init__(f"interrupted by {self.name}")

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


class StopSignals:
    """Handlers for SIGINT and SIGTERM while inside the context (main thread only); the previous
    handlers come back on exit.

    ``route_to``: where a signal goes while a control loop runs (``ControlLoop.request_stop``,
    given ``"interrupted by SIGINT"``); None (the default) raises ``Interrupted``. ``received``:
    the first signal seen, for the exit code.
    """

    def __init__(self, signals: tuple[signal.Signals, ...] = STOP_SIGNALS):
        self.signals = signals
        self.route_to: Callable[[str], None] | None = None
        self.received: signal.Signals | None = None
        self._previous: dict[signal.Signals, Any] = {}

    @property
    def exit_code(self) -> int | None:
        """128 + the number of the first signal received; None if none was."""
        return None if self.received is None else 128 + int(self.received)

    def __enter__(self) -> StopSignals:
        for signum in self.signals:
            self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        for signum, previous in self._previous.items():
            signal.signal(signum, previous)
        self._previous.clear()

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.received is None:
            self.received = signal.Signals(signum)
        route = self.route_to
        if route is None:
            raise Interrupted(signum)
        route(f"interrupted by {signal.Signals(signum).name}")
