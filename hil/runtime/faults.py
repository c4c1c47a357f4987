"""Fault injection into a simulated trial (``faults:`` in the simulation config).

The injector belongs to the composition root: it watches the loop's tick records (an observer,
like the stand-off judge), and when a fault's time or phase comes it breaks the simulated
device, the vision side or the trial log — never the loop, which must find out by itself. Each
injection is recorded (``Injection``: when, and what of it the loop could first observe) and
written to the log as an ``inject`` event while the log can take one.
"""

from __future__ import annotations

import errno
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from configuration.simulation import FaultConfig
from estimators.frame import Frame
from estimators.geometry import Pose
from estimators.measurement import Measurement
from hil.logs.records import TickRecord
from hil.logs.triallog import TrialLogWriter
from hil.runtime.workers import InlineWorkers
from sim_backends.world import SimWorld


@dataclass(frozen=True, slots=True)
class Injection:
    """A fault that was injected at trial time ``t`` (s), after the tick of that time."""

    kind: str
    t: float


class NonFiniteEstimator:
    """Wraps an estimator: for frames captured at or after ``since`` (the clock's stamps) it
    returns the measurement with a NaN in its position, as a broken estimator would."""

    def __init__(self, estimator, since: float):
        self.estimator, self.since = estimator, since

    def estimate(self, frame: Frame, prior_X_CT: Pose | None = None) -> Measurement:
        m = self.estimator.estimate(frame, prior_X_CT)
        if frame.stamp < self.since or m.X_CT is None:
            return m
        p = m.X_CT.p.copy()
        p[0] = float("nan")
        # Measurement validates its pose: the injected NaN goes in as a broken estimator's would.
        object.__setattr__(m, "X_CT", Pose.unchecked(m.X_CT.R, p))
        return m


class FaultInjector:
    """Injects ``faults`` into ``world`` (and the vision workers, the log) at their time.

    Call it with every tick record (``ControlLoop.observers``)."""

    def __init__(
        self,
        faults: Sequence[FaultConfig],
        *,
        world: SimWorld,
        workers: InlineWorkers,
        log: TrialLogWriter,
        t0: Callable[[], float],
    ):
        self.pending = list(faults)
        self.world, self.workers, self.log, self._t0 = world, workers, log, t0
        self.injected: list[Injection] = []
        self._entered: dict[str, float] = {}

    def __call__(self, record: TickRecord) -> None:
        self._entered.setdefault(record.phase, record.t)
        for fault in list(self.pending):
            if fault.at_s is not None:
                due = record.t >= fault.at_s
            else:
                entered = self._entered.get(str(fault.phase))
                due = entered is not None and record.t - entered >= fault.after_s
            if due:
                self.pending.remove(fault)
                self.inject(fault, record.t)

    def inject(self, fault: FaultConfig, t: float) -> None:
        """Break what ``fault`` names, now (trial time ``t``)."""
        world, kind = self.world, fault.kind
        self.log.write_event(t, "inject", f"fault injected: {kind}", kind=kind)
        if kind == "camera_dropout":
            world.camera.inject_dropout()
        elif kind == "frozen_camera":
            world.camera.inject_freeze()
        elif kind == "corrupt_frame":
            world.camera.inject_corrupt_frame()
        elif kind == "nan_estimate":
            since = self._t0() + t
            for system, estimator in list(self.workers.estimators.items()):
                self.workers.estimators[system] = NonFiniteEstimator(estimator, since)
        elif kind == "protective_stop":
            world.arm.inject_protective_stop()
        elif kind == "emergency_stop":
            world.arm.inject_emergency_stop()
        elif kind == "link_drop":
            world.arm.drop_link()
        elif kind == "modbus_silent":
            world.silence_track()  # requests go unanswered; the device's watchdog trips
        elif kind == "track_fault":
            world.track_model.inject_drive_fault()
        elif kind == "tumbling_target":
            world.track_model.start_tumble(fault.rate_deg_s)
        elif kind == "disk_full":
            # What the writer does when a chunk cannot be written: the same failure path.
            self.log._fail(OSError(errno.ENOSPC, os.strerror(errno.ENOSPC) + " (injected)"))
        else:  # pragma: no cover - the config's Literal keeps this out
            raise ValueError(f"unknown fault kind {kind!r}")
        self.injected.append(Injection(kind, t))
