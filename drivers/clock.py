"""Time for the control loop: real (monotonic, sleeping) or simulated (advanced explicitly).

The loop reads time only through a ``Clock``, so the same code runs on hardware at the control
rate and in simulation faster than real time.
"""

from __future__ import annotations

import time
from typing import Protocol


class Clock(Protocol):
    """``now`` and ``sleep_until`` keep the control schedule; ``work_time`` is the stopwatch a
    tick's own work is measured with against the real control period. ``real_time``: whether
    that work delays the devices (a rig) or only the computer running a simulation."""

    real_time: bool

    def now(self) -> float: ...

    def sleep_until(self, t: float) -> None: ...

    def work_time(self) -> float: ...


class RealClock:
    """``time.monotonic`` (the same clock depthai stamps host frames with)."""

    real_time = True

    def now(self) -> float:
        return time.monotonic()

    def sleep_until(self, t: float) -> None:
        remaining = t - time.monotonic()
        if remaining > 0:
            time.sleep(remaining)

    def work_time(self) -> float:
        """Wall time: on a rig, everything that delays a tick counts against its deadline."""
        return time.perf_counter()


class SimClock:
    """Simulated time: stands still while the loop computes, jumps when advanced."""

    real_time = False

    def __init__(self, start: float = 0.0):
        self._t = float(start)

    def now(self) -> float:
        return self._t

    def advance(self, dt: float) -> None:
        if dt < 0:
            raise ValueError(f"SimClock cannot go back in time (dt={dt})")
        self._t += dt

    def sleep_until(self, t: float) -> None:
        if t > self._t:
            self._t = t

    def work_time(self) -> float:
        """CPU time of this thread: a simulation shares the machine with other runs, and what
        must fit the real control period is the work the tick does, not its waits for a core."""
        return time.thread_time()
