"""Small helpers for the processes of a wall-clock trial: the cores they share, their peak memory,
how their allocator keeps memory, a bounded stop, and keeping a terminal's Ctrl-C away from
them."""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import os
import signal
from collections.abc import Iterator
from multiprocessing.process import BaseProcess


class ProcessStartError(RuntimeError):
    """A process of the trial did not start (its reason, e.g. an emulator's address in use)."""


def usable_cores() -> int:
    """The cores this process may run on (its affinity mask, where the system has one)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


#: glibc's ``mallopt`` parameters (malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3


def keep_freed_memory() -> bool:
    """Tell glibc's allocator to keep freed memory in this process for reuse: arrays up to
    32 MiB come from the heap, and the heap is trimmed only beyond 512 MiB free. By default it
    maps every array over an adaptive threshold afresh and returns freed memory to the system,
    so a frame's megabyte-sized images land on new pages each frame, a page fault per page:
    50 frames' worth of three VGA float images faulted 43 000 times, none with this (the line
    system's tracking 20.3 → 18.7 ms a frame in a vision worker). Peak memory is the same.
    False (nothing changed) where the C library has no ``mallopt``."""
    try:
        mallopt = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    return bool(mallopt(_M_MMAP_THRESHOLD, 32 << 20)) and bool(
        mallopt(_M_TRIM_THRESHOLD, 512 << 20)
    )


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
    """Wait for ``process`` to end by itself, then terminate, then kill: never hang. A process
    that never started (its ``start`` raised) is left alone: joining it would raise and hide
    the error that stopped it starting."""
    if process.pid is None:
        return
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
