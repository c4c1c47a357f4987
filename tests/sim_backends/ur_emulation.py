"""Test helpers: a UR emulator on a loopback address of its own, and ur-rtde clients that are
always released (their destructors sleep 0.5 s each; a leaked one also holds its sockets)."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator

from sim_backends.ur_emulator import UREmulator, free_loopback_host


@contextlib.contextmanager
def running_emulator(**options) -> Iterator[UREmulator]:
    """A started emulator (stopped on exit, whatever happens) on a free 127.x.y.z address."""
    with UREmulator(free_loopback_host(), **options) as emulator:
        yield emulator


@contextlib.contextmanager
def released(client) -> Iterator:
    """Disconnect a ur-rtde interface on exit."""
    try:
        yield client
    finally:
        with contextlib.suppress(RuntimeError):
            client.disconnect()


def wait_until(condition: Callable[[], bool], timeout_s: float, poll_s: float = 0.002) -> float:
    """Seconds until ``condition()`` held; ``TimeoutError`` after ``timeout_s``."""
    start = time.monotonic()
    while not condition():
        if time.monotonic() - start > timeout_s:
            raise TimeoutError(f"condition not met within {timeout_s} s")
        time.sleep(poll_s)
    return time.monotonic() - start
