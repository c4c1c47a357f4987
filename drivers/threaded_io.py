"""Register devices read and commanded from a thread of their own, so that a control tick never
waits on a Modbus round trip.

A Modbus TCP round trip to an axis controller or a gripper's gateway takes milliseconds — on
the emulated rig, 1–10 ms, most of the tick's work — and one to a silent device the link's
whole time-out, while the control tick has 8 ms for everything. So ``ThreadedTrack`` and
``ThreadedGripper`` put a driver (``ModbusTrack``, ``RobotiqGripper``) behind an I/O thread
(``DeviceIo``) that, every ``period_s``,

1. sends the newest command the control loop posted (an older one not yet sent is dropped: only
   the newest velocity or finger target matters), then
2. reads the status, which the driver stamps on the host clock.

``state()`` returns the newest status at once, or raises what went wrong instead: the newest
read failed (the driver's ``DeviceError``: silent device, dropped link), a posted command failed
(raised once, by the next ``state()``), or no read has succeeded for ``stale_after_s`` (the
thread is stuck or starved) — so the control loop's checks see every fault within a period or
two, as they did when it read the device itself.

Stops are never posted: ``stop()`` is sent at once on the caller's thread (after the round trip
in flight) and discards any posted command, so a stop cannot be overwritten by an older move.
The lifecycle calls (connect, activate, deactivate, close) run on the caller's thread too.

A host-side watchdog for the track: while it runs at a non-zero velocity, the control loop must
command it at least every ``command_timeout_s``; otherwise the I/O thread stops it and reports a
``DeviceFault``. The thread's status reads alone would keep the axis controller's own
communication watchdog fed, so without this a hung control loop would leave the mock-up moving.

The thread inherits its creator's scheduling: created under the control loop's ``SCHED_FIFO``
(as ``RealDevices.start`` does), it gets its round trips done on time on a loaded machine.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Generic, TypeVar

from drivers.base import DeviceError, DeviceFault, DeviceTimeout, GripperState, TrackState
from drivers.gripper_robotiq import RobotiqGripper
from drivers.modbus_link import RegisterLink
from drivers.track_modbus import ModbusTrack

StateT = TypeVar("StateT")

#: How long ``close()`` waits for the I/O thread's round trip in flight (s).
_JOIN_S = 2.0

#: The track's host-side watchdog by default (s): a moving track the control loop has not
#: commanded for this long is stopped.
TRACK_COMMAND_TIMEOUT_S = 0.1


class DeviceIo(Generic[StateT]):
    """One device's I/O thread: the newest posted command, then a status read, every
    ``period_s``. ``lock`` is held around every use of the device's driver, by the thread and
    by ``call``; ``check`` (optional) runs each cycle before the read, under the lock, and may
    raise a ``DeviceError`` to report (the track's host-side watchdog)."""

    def __init__(
        self,
        name: str,
        read: Callable[[], StateT],
        *,
        period_s: float,
        stale_after_s: float,
        check: Callable[[], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ):
        if not period_s > 0:
            raise ValueError(f"{name}: the I/O period must be positive; got {period_s}")
        if not stale_after_s > period_s:
            raise ValueError(
                f"{name}: stale_after_s ({stale_after_s}) must exceed the period ({period_s})"
            )
        self.name = name
        self.period_s = period_s
        self.stale_after_s = stale_after_s
        self._read = read
        self._check = check
        self._clock = clock
        self.lock = threading.Lock()  # the driver (its link) serves one thread at a time
        self._shared = threading.Lock()  # the fields below, between the thread and callers
        self._pending: Callable[[], None] | None = None
        self._latest: StateT | None = None
        self._latest_at = -float("inf")
        self._read_error: DeviceError | None = None
        self._reported: DeviceError | None = None  # a command's or check's failure, raised once
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None

    # --- caller's side ------------------------------------------------------------------
    def start(self) -> None:
        """Read once on the caller's thread (so ``latest()`` has a state at once; a device that
        does not answer fails here), then start the thread."""
        with self.lock:
            self._store_read()
        if self._read_error is not None:
            raise self._read_error
        self._stopping.clear()
        self._thread = threading.Thread(target=self._run, name=f"{self.name}-io", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """End the thread (after its round trip in flight); idempotent."""
        self._stopping.set()
        thread, self._thread = self._thread, None
        if thread is not None and thread is not threading.current_thread():
            thread.join(_JOIN_S)

    def latest(self) -> StateT:
        """The newest status; raises a failure to report, the newest read's error, or
        ``DeviceTimeout`` when no read succeeded for ``stale_after_s``."""
        with self._shared:
            reported, self._reported = self._reported, None
            error, latest, latest_at = self._read_error, self._latest, self._latest_at
        if reported is not None:
            raise reported
        if error is not None:
            raise error
        age = self._clock() - latest_at
        if latest is None or age > self.stale_after_s:
            raise DeviceTimeout(
                f"{self.name}: no status for {age:.3f} s (its I/O thread is stuck or starved; "
                f"limit {self.stale_after_s:g} s)"
            )
        return latest

    def post(self, command: Callable[[], None]) -> None:
        """Send ``command`` at the thread's next cycle, replacing one not yet sent."""
        with self._shared:
            self._pending = command

    def call(self, action: Callable[[], None]) -> None:
        """Run ``action`` on the caller's thread now (after the round trip in flight),
        discarding any posted command: what the caller does now supersedes it."""
        with self.lock:
            with self._shared:
                self._pending = None
            action()

    # --- the thread ---------------------------------------------------------------------
    def _run(self) -> None:
        deadline = self._clock()
        while not self._stopping.is_set():
            with self.lock:
                with self._shared:
                    command, self._pending = self._pending, None
                self._guarded(command)
                self._guarded(self._check)
                self._store_read()
            deadline += self.period_s
            wait = deadline - self._clock()
            if wait < 0:  # behind (a slow round trip): start afresh rather than catch up
                deadline, wait = self._clock(), 0.0
            self._stopping.wait(wait)

    def _guarded(self, action: Callable[[], None] | None) -> None:
        if action is None:
            return
        try:
            action()
        except Exception as exc:  # the thread must go on; the control loop reports it
            with self._shared:
                self._reported = _as_device_error(self.name, exc)

    def _store_read(self) -> None:
        try:
            state = self._read()
        except Exception as exc:
            with self._shared:
                self._read_error = _as_device_error(self.name, exc)
            return
        with self._shared:
            self._latest, self._latest_at, self._read_error = state, self._clock(), None


def _as_device_error(name: str, exc: Exception) -> DeviceError:
    if isinstance(exc, DeviceError):
        return exc
    return DeviceError(f"{name}: {type(exc).__name__}: {exc}")


class ThreadedTrack:
    """``drivers.base.Track``: a ``ModbusTrack`` whose status reads and velocity commands run on
    an I/O thread. ``move_velocity`` checks its argument at once (``ValueError`` outside the
    device's limits, ``DeviceError`` when not active) and posts it; an unchanged velocity is
    re-posted only every ``resend_s``."""

    def __init__(
        self,
        track: ModbusTrack,
        *,
        period_s: float,
        stale_after_s: float,
        command_timeout_s: float = TRACK_COMMAND_TIMEOUT_S,
        resend_s: float = 0.05,
        clock: Callable[[], float] = time.monotonic,
    ):
        self._track = track
        self._clock = clock
        self.command_timeout_s = command_timeout_s
        self.resend_s = resend_s
        self._velocity = 0.0  # the newest velocity posted (m/s)
        self._posted_at = -float("inf")
        self._commanded_at = -float("inf")  # the newest move_velocity call
        self._io: DeviceIo[TrackState] = DeviceIo(
            track.link.description,
            track.state,
            period_s=period_s,
            stale_after_s=stale_after_s,
            check=self._watchdog,
            clock=clock,
        )

    # limits read from the device at connect()
    @property
    def travel_min(self) -> float:
        return self._track.travel_min

    @property
    def travel_max(self) -> float:
        return self._track.travel_max

    @property
    def max_speed(self) -> float:
        return self._track.max_speed

    @property
    def max_acceleration(self) -> float:
        return self._track.max_acceleration

    @property
    def link(self) -> RegisterLink:
        return self._track.link

    def connect(self) -> None:
        self._track.connect()
        self._io.start()

    def activate(self) -> None:
        self._io.call(self._track.activate)
        self._velocity = 0.0

    def deactivate(self) -> None:
        self._io.call(self._track.deactivate)
        self._velocity = 0.0

    def close(self) -> None:
        self._io.stop()
        self._track.close()

    def state(self) -> TrackState:
        return self._io.latest()

    def move_velocity(self, velocity: float) -> None:
        self._track.check_velocity(velocity)
        now = self._clock()
        self._commanded_at = now
        if velocity != self._velocity or now - self._posted_at >= self.resend_s:
            self._velocity, self._posted_at = velocity, now
            self._io.post(lambda: self._track.move_velocity(velocity))

    def move_to(self, position: float, speed: float) -> None:
        self._io.call(lambda: self._track.move_to(position, speed))
        self._velocity = 0.0

    def stop(self) -> None:
        self._velocity = 0.0
        self._io.call(self._track.stop)

    def _watchdog(self) -> None:
        """On the I/O thread: stop a track that moves on a command the loop no longer
        repeats."""
        silent_s = self._clock() - self._commanded_at
        if self._velocity != 0.0 and silent_s > self.command_timeout_s:
            self._velocity = 0.0
            self._track.stop()
            raise DeviceFault(
                f"{self._track.link.description}: stopped — no command from the control loop "
                f"for {silent_s:.3f} s while moving (limit {self.command_timeout_s:g} s)"
            )


class ThreadedGripper:
    """``drivers.base.Gripper``: a ``RobotiqGripper`` whose status reads and finger commands
    run on an I/O thread."""

    def __init__(
        self,
        gripper: RobotiqGripper,
        *,
        period_s: float,
        stale_after_s: float,
        clock: Callable[[], float] = time.monotonic,
    ):
        self._gripper = gripper
        self._io: DeviceIo[GripperState] = DeviceIo(
            gripper.link.description,
            gripper.state,
            period_s=period_s,
            stale_after_s=stale_after_s,
            clock=clock,
        )

    @property
    def link(self) -> RegisterLink:
        return self._gripper.link

    def connect(self) -> None:
        self._gripper.connect()
        self._io.start()

    def activate(self) -> None:
        self._io.call(self._gripper.activate)

    def deactivate(self) -> None:
        self._io.call(self._gripper.deactivate)

    def close(self) -> None:
        self._io.stop()
        self._gripper.close()

    def state(self) -> GripperState:
        return self._io.latest()

    def open(self) -> None:
        self._io.post(self._gripper.open)

    def grip(self) -> None:
        self._io.post(self._gripper.grip)


def stale_after(timeout_s: float, period_s: float) -> float:
    """How long without a good read means the I/O thread is stuck or starved: a silent device
    is reported by the cycle's failed request, at most a period and two time-outs (the
    command's and the read's) after the last good read; one more period of slack."""
    return 2 * timeout_s + 2 * period_s
