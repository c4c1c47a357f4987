"""Small helpers for the processes of a wall-clock trial: their peak memory, a bounded stop, and
keeping a terminal's Ctrl-C away from them."""

from __future__ import annotations

import contextlib
import os
import signal
from collections.abc import Iterator
from multiprocessing.process import BaseProcess


def peak_rss_mib(pid: int | None = None) -> float:
    """Peak resident memory (VmHWM) of a process, MiB; NaN where /proc does not say."""
    try:
        with open(f"/proc/{pid or os.getpid()}/status", encoding="ascii") as status:
            lines = status.read().splitlines()
    except OSError:
        return float("nan")
    for line in lines:
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def stop_process(process: BaseProcess, timeout_s: float = 10.0) -> None:
    """Wait for ``process`` to end by itself, then terminate, then kill: never hang."""
    process.join(timeout=timeout_s)
    if process.is_alive():
        process.terminate()
        process.join(timeout=2.0)
    if process.is_alive():
        process.kill()
        process.join(timeout=2.0)


@contextlib.contextmanager
def sigint_blocked_in_children() -> Iterator[None]:
    """Processes started inside (and theirs) never see SIGINT: a Ctrl-C in a terminal reaches
    the whole process group, and the simulated world must keep running until the control
    process has stopped the arm and the track; the control process then ends each one. SIGINT
    is blocked, not ignored, while they start: the mask is inherited, and a Ctrl-C that comes
    meanwhile is delivered to this process when it is unblocked, not lost."""
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)
