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


def cpu_seconds(pid: int) -> float:
    """User plus system CPU time (s) a process has used so far; NaN once it is gone."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as stat:
            fields = stat.read().rsplit(")", 1)[1].split()
    except OSError:
        return float("nan")
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def child_pids(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (from /proc)."""
    children = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat", encoding="ascii") as stat:
                parent = int(stat.read().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        if parent == pid:
            children.append(int(entry))
    return children


def stop_process(process: BaseProcess, timeout_s: float = 10.0) -> None:
    """Wait for ``process`` to end by itself, then terminate, then kill: never hang."""
    process.join(timeout=timeout_s)
    if process.is_alive():
        process.terminate()
        process.join(timeout=2.0)
    if process.is_alive():
        process.kill()
        process.join(timeout=2.0)
