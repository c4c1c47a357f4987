"""Who runs the estimators for the vision pipeline: one worker per system, each busy with at most
one frame at a time.

``InlineWorkers`` (``--clock sim``) runs an estimator as soon as its job starts and hands the
result over only once the modelled processing time has passed on the simulated clock — the
control loop sees results as late as the rig would, and the run is deterministic.
``ProcessWorkers`` (``--clock wall``) runs each system in a process of its own: the estimators
are Python and NumPy and hold the GIL for much of their time, so threads would take turns on
one core where processes use both (``satgrasp bench loop`` measures the difference).
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import pickle
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Protocol

import numpy as np

from estimators.deadline import search_deadline
from estimators.frame import CameraInfo, Frame
from estimators.geometry import Pose
from estimators.imaging import gray_frame
from estimators.measurement import Estimator, Measurement
from estimators.registry import build_estimator
from estimators.target import TargetModel
from estimators.warmup import compile_kernels
from hil.runtime.processes import keep_freed_memory, peak_rss_mib, stop_process


@dataclass(frozen=True, slots=True, eq=False)
class VisionJob:
    """A frame for one system, with fusion's prior at the frame's capture stamp.

    ``search_deadline``: on the wall clock, the ``time.monotonic`` instant after which the
    estimator must not fall back from a failed track to a search (``estimators.deadline``);
    None: no limit."""

    system: str
    frame: Frame
    prior_X_CT: Pose | None
    started: float
    search_deadline: float | None = None


@dataclass(frozen=True, slots=True, eq=False)
class VisionResult:
    """A finished job: the measurement, when it was done and how long it took (modelled under
    ``--clock sim``, measured under ``--clock wall``). ``error`` says how the estimator
    malfunctioned (it raised, or returned non-finite numbers); the measurement is then ``lost``."""

    job: VisionJob
    measurement: Measurement
    finished: float
    processing_s: float
    error: str | None = None


class Workers(Protocol):
    def idle(self) -> list[str]: ...

    def start(self, job: VisionJob) -> None: ...

    def finished(self, now: float) -> list[VisionResult]: ...

    def close(self) -> None: ...


def measurement_problem(m: Measurement) -> str | None:
    """Why a measurement must not be trusted (non-finite numbers), or None."""
    for name in ("covariance", "center_C", "normal_C", "covariance_5dof"):
        value = getattr(m, name)
        if value is not None and not np.all(np.isfinite(value)):
            return f"{m.system} returned non-finite {name}"
    if m.X_CT is not None and not (np.all(np.isfinite(m.X_CT.R)) and np.all(np.isfinite(m.X_CT.p))):
        return f"{m.system} returned a non-finite pose"
    return None


def run_estimator(
    estimator: Estimator, frame: Frame, prior: Pose | None
) -> tuple[Measurement, str | None]:
    """``estimator`` on ``frame``, and how it malfunctioned (None when it did not): a bug in
    vision becomes a ``lost`` measurement that says so, never an exception in the pipeline."""
    system = getattr(estimator, "system", "?")
    try:
        m = estimator.estimate(frame, prior)
    except Exception as exc:
        error = f"{system} raised {type(exc).__name__}: {exc}"
        return Measurement.lost(system, frame, error), error
    error = measurement_problem(m)
    if error is not None:
        return Measurement.lost(system, frame, error), error
    return m, None


class InlineWorkers:
    """Estimators run in this process, one after the other. Each result is released
    ``processing_s(system, acquiring=…)`` after its job started on the caller's clock
    (``--clock sim``; acquiring: the job has no prior), or,
    with ``processing_s`` None, as soon as the estimator returns, on ``clock`` (on the wall
    clock: the serial pipeline that ``satgrasp bench loop`` compares with ``ProcessWorkers``).
    A job's ``search_deadline`` is not applied: under modelled times the estimator's own
    duration means nothing, and the same frames must give the same results on any machine."""

    def __init__(
        self,
        estimators: Mapping[str, Estimator],
        processing_s: Callable[..., float] | None,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        #: The estimator of each system (replaceable, e.g. to inject a fault).
        self.estimators = dict(estimators)
        self._processing_s = processing_s
        self._clock = clock
        self._busy: dict[str, VisionResult] = {}

    def idle(self) -> list[str]:
        return [s for s in self.estimators if s not in self._busy]

    def start(self, job: VisionJob) -> None:
        if job.system in self._busy:
            raise RuntimeError(f"the {job.system} worker is busy")
        started = time.perf_counter()
        m, error = run_estimator(self.estimators[job.system], job.frame, job.prior_X_CT)
        if self._processing_s is None:
            result = VisionResult(job, m, self._clock(), time.perf_counter() - started, error)
        else:
            duration = self._processing_s(job.system, acquiring=job.prior_X_CT is None)
            result = VisionResult(job, m, job.started + duration, duration, error)
        self._busy[job.system] = result

    def finished(self, now: float) -> list[VisionResult]:
        done = sorted(
            (r for r in self._busy.values() if r.finished <= now + 1e-12),
            key=lambda r: (r.finished, r.job.system),
        )
        for r in done:
            del self._busy[r.job.system]
        return done

    def close(self) -> None:
        self._busy.clear()


# --- one process per system ------------------------------------------------------------------

#: The environment a worker starts with (read when numpy loads): one core per worker — the
#: workers are the parallelism, and threaded BLAS on the small matrices of a pose fit only makes
#: them contend.
WORKER_ENVIRONMENT = dict.fromkeys(
    ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"), "1"
)


def _worker_main(
    system: str, target: TargetModel, info: CameraInfo, jobs: Connection, ready: Connection
) -> None:
    """A worker process: build the estimator once, then answer jobs until told to stop."""
    import cv2

    keep_freed_memory()  # each frame's images on pages already mapped
    cv2.setNumThreads(1)  # one core per worker: the workers themselves are the parallelism
    try:
        estimator = build_estimator(system, target, info)
        compile_kernels()  # before "ready": a cold numba cache would delay the first frame
    except Exception as exc:
        ready.send(f"{type(exc).__name__}: {exc}")
        return
    ready.send("ready")
    while True:
        try:
            message = jobs.recv()
        except (EOFError, OSError):
            return
        if message is None:
            return
        frame_bytes, prior, deadline = message
        frame = pickle.loads(frame_bytes)
        started = time.perf_counter()
        with search_deadline(deadline):
            m, error = run_estimator(estimator, frame, prior)
        jobs.send((m, time.perf_counter() - started, error))


class ProcessWorkers:
    """One process per system (``spawn`` start method: safe beside threads and pybullet)."""

    def __init__(
        self,
        systems: Sequence[str],
        target: TargetModel,
        info: CameraInfo,
        *,
        clock: Callable[[], float] = time.monotonic,
        start_timeout_s: float = 120.0,
    ) -> None:
        context = mp.get_context("spawn")
        self._clock = clock
        self._connections: dict[str, Connection] = {}
        self._processes: dict[str, mp.process.BaseProcess] = {}
        self._busy: dict[str, VisionJob] = {}
        self._pickled: tuple[Frame, bytes] | None = None  # the last frame sent, pickled
        try:
            readies = {}
            saved = {name: os.environ.get(name) for name in WORKER_ENVIRONMENT}
            os.environ.update(WORKER_ENVIRONMENT)
            for system in systems:
                ours, theirs = context.Pipe()
                ready_ours, ready_theirs = context.Pipe(duplex=False)
                # (built for the frames it gets: gray, ``start``)
                process = context.Process(
                    target=_worker_main,
                    args=(system, target, info.as_mono(), theirs, ready_theirs),
                    name=f"satgrasp-{system}",
                    daemon=True,
                )
                process.start()
                theirs.close()
                ready_theirs.close()
                self._connections[system], self._processes[system] = ours, process
                readies[system] = ready_ours
            for name, value in saved.items():
                if value is None:
                    os.environ.pop(name, None)
                else:
                    os.environ[name] = value
            for system, ready in readies.items():
                if not ready.poll(start_timeout_s):
                    raise RuntimeError(f"the {system} worker did not start in {start_timeout_s} s")
                answer = ready.recv()
                if answer != "ready":
                    raise RuntimeError(f"the {system} worker failed to start: {answer}")
        except BaseException:
            self.close()
            raise

    def idle(self) -> list[str]:
        return [s for s in self._connections if s not in self._busy]

    def start(self, job: VisionJob) -> None:
        if job.system in self._busy:
            raise RuntimeError(f"the {job.system} worker is busy")
        # A frame goes to every worker: pickled once (a 1280×800 colour frame took 1.5 ms), as
        # the gray image the systems read — in colour, the three pipes carried 9 MB a frame at
        # 1280×800, and the last worker had its frame 7 ms after the first began to receive.
        if self._pickled is None or self._pickled[0] is not job.frame:
            sent = pickle.dumps(gray_frame(job.frame), pickle.HIGHEST_PROTOCOL)
            self._pickled = (job.frame, sent)
        message = (self._pickled[1], job.prior_X_CT, job.search_deadline)
        self._connections[job.system].send(message)
        self._busy[job.system] = job

    def finished(self, now: float) -> list[VisionResult]:
        done = []
        for system, job in list(self._busy.items()):
            connection = self._connections[system]
            try:
                if not connection.poll(0):
                    if not self._processes[system].is_alive():
                        raise EOFError
                    continue
                m, seconds, error = connection.recv()
            except (EOFError, OSError):
                error = f"the {system} worker process died"
                m = Measurement.lost(system, job.frame, error)
                seconds = now - job.started
            del self._busy[system]
            done.append(VisionResult(job, m, self._clock(), seconds, error))
        return done

    def peak_rss_mib(self) -> dict[str, float]:
        """Peak resident memory of each worker process (MiB)."""
        return {s: peak_rss_mib(p.pid) for s, p in self._processes.items() if p.is_alive()}

    def connections(self) -> list[Connection]:
        """The busy workers' connections (to wait on)."""
        return [self._connections[s] for s in self._busy]

    def close(self) -> None:
        for connection in self._connections.values():
            with contextlib.suppress(OSError, ValueError):
                connection.send(None)
        for process in self._processes.values():
            stop_process(process, timeout_s=2.0)
        for connection in self._connections.values():
            connection.close()
        self._connections.clear()
        self._processes.clear()
        self._busy.clear()
        self._pickled = None
