"""``hil.runtime.workers.ProcessWorkers``: a process per system, started as the real-time
pipeline starts it."""

from __future__ import annotations

import os
import pickle
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

import hil.runtime.workers as workers_module
from estimators.geometry import translation_error
from estimators.registry import build_estimator
from hil.runtime.workers import WORKER_ENVIRONMENT, ProcessWorkers, VisionJob
from tests.estimators import rendered


def _environment(pid: int) -> dict[str, str]:
    entries = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
    return dict(e.decode().split("=", 1) for e in entries if b"=" in e)


def test_workers_run_their_systems_on_one_frame_pickled_once(monkeypatch):
    """Each worker estimates in a process of its own, with one BLAS thread; the parent's
    environment is left as it was. A frame for several workers is pickled once (1.5 ms for a
    1280×800 colour frame)."""
    frame = rendered.frame(1.2)
    dumps, original = [], pickle.dumps
    monkeypatch.setattr(
        workers_module.pickle, "dumps", lambda *a, **k: dumps.append(1) or original(*a, **k)
    )
    before = dict(os.environ)
    systems = ("corners", "lines")
    workers = ProcessWorkers(systems, rendered.target(), frame.info)
    try:
        for system in systems:
            pid = workers._processes[system].pid
            assert WORKER_ENVIRONMENT.items() <= _environment(pid).items()
        assert dict(os.environ) == before
        for system in systems:
            workers.start(VisionJob(system, frame, frame.truth.X_CT, time.monotonic()))
        deadline = time.monotonic() + 60.0
        done = []
        while len(done) < len(systems) and time.monotonic() < deadline:
            done += workers.finished(time.monotonic())
            time.sleep(0.01)
    finally:
        workers.close()
    assert len(dumps) == 1
    assert sorted(r.job.system for r in done) == sorted(systems)
    for result in done:
        assert result.error is None and result.measurement.valid
        assert translation_error(result.measurement.X_CT, frame.truth.X_CT) < 0.005


def test_a_colour_frame_goes_to_the_workers_as_the_gray_image_they_read(monkeypatch):
    """A third of the bytes through each pipe (at 1280×800 the last of three workers had its
    colour frame 7 ms after the first began to receive it), and the same answer as the colour
    frame estimated in this process."""
    mono = rendered.frame(1.2)
    colour = replace(
        mono,
        image=np.repeat(mono.image[:, :, None], 3, axis=2),
        info=replace(mono.info, channels=3),
    )
    sent, original = [], pickle.dumps
    monkeypatch.setattr(
        workers_module.pickle,
        "dumps",
        lambda *a, **k: sent.append(len(payload := original(*a, **k))) or payload,
    )
    workers = ProcessWorkers(("corners",), rendered.target(), colour.info)
    try:
        workers.start(VisionJob("corners", colour, colour.truth.X_CT, time.monotonic()))
        deadline = time.monotonic() + 60.0
        done = []
        while not done and time.monotonic() < deadline:
            done += workers.finished(time.monotonic())
            time.sleep(0.01)
    finally:
        workers.close()
    assert sent and sent[0] < 0.5 * colour.image.nbytes
    here = build_estimator("corners", rendered.target(), colour.info).estimate(
        colour, colour.truth.X_CT
    )
    (result,) = done
    assert result.error is None and result.measurement.valid
    np.testing.assert_array_equal(result.measurement.X_CT.p, here.X_CT.p)
    np.testing.assert_array_equal(result.measurement.X_CT.R, here.X_CT.R)
