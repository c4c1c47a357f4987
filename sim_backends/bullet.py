"""pybullet, imported and connected without its "pybullet build time" banner.

pybullet's C code prints the banner (without a newline, so it surfaces at exit) and would
interleave with our progress output and machine-readable lines. Import pybullet from here and
connect through ``connect_direct``.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import sys
from collections.abc import Iterator


@contextlib.contextmanager
def silenced_fds() -> Iterator[None]:
    """Send file descriptors 1 and 2 to /dev/null, including C-buffered text."""
    sys.stdout.flush()
    sys.stderr.flush()
    libc = ctypes.CDLL(None)
    libc.fflush(None)
    saved = {fd: os.dup(fd) for fd in (1, 2)}
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        for fd in saved:
            os.dup2(devnull, fd)
        yield
        libc.fflush(None)
    finally:
        for fd, copy in saved.items():
            os.dup2(copy, fd)
            os.close(copy)
        os.close(devnull)


with silenced_fds():
    import pybullet


def connect_direct() -> int:
    """A new pybullet DIRECT client id."""
    with silenced_fds():
        client = pybullet.connect(pybullet.DIRECT)
    if client < 0:
        raise RuntimeError("pybullet: could not start a DIRECT client")
    return client


__all__ = ["connect_direct", "pybullet", "silenced_fds"]
