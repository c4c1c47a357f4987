"""Small helpers for the processes of a wall-clock trial: their peak memory and a bounded stop."""

from __future__ import annotations

import os
from multiprocessing.process import BaseProcess


class ProcessStartError(RuntimeError):
    """A process of the trial did not start (its reason, e.g. an emulator's address in use)."""


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
