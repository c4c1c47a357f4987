"""``hil.runtime.workers.ProcessWorkers``: a process per system, started as the real-time
pipeline starts it."""

from __future__ import annotations

import os
import time
from pathlib import Path

from estimators.geometry import translation_error
from hil.runtime.workers import WORKER_ENVIRONMENT, ProcessWorkers, VisionJob
from tests.estimators import rendered


def _environment(pid: int) -> dict[str, str]:
    entries = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
    return dict(e.decode().split("=", 1) for e in entries if b"=" in e)


def test_a_worker_runs_its_system_in_the_environment_it_was_given():
    """Each worker estimates in a process of its own, with one BLAS thread and glibc's
    allocator told to keep freed memory (a frame's images otherwise land on new pages every
    frame: 10 % of a system's time); the parent's environment is left as it was."""
    frame = rendered.frame(1.2)
    before = dict(os.environ)
    workers = ProcessWorkers(("corners",), rendered.target(), frame.info)
    try:
        pid = workers._processes["corners"].pid
        assert WORKER_ENVIRONMENT.items() <= _environment(pid).items()
        assert dict(os.environ) == before
        workers.start(VisionJob("corners", frame, frame.truth.X_CT, time.monotonic()))
        deadline = time.monotonic() + 60.0
        done = []
        while not done and time.monotonic() < deadline:
            done = workers.finished(time.monotonic())
            time.sleep(0.01)
    finally:
        workers.close()
    assert len(done) == 1 and done[0].error is None
    measurement = done[0].measurement
    assert measurement.valid
    assert translation_error(measurement.X_CT, frame.truth.X_CT) < 0.005
