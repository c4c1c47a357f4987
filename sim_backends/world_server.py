"""``--clock wall``: the simulated rig in a process of its own, running in real time.

The world process steps the arm, the track and the gripper on the monotonic clock (every
``step_s``, in the arm controller's periods), applies the commands that arrive on its pipe, and
publishes a ``WorldSnapshot`` after every step — like a UR controller streaming RTDE state. At
each frame instant it asks the camera process to render the scene as it is at that instant
(``sim_backends.camera_server``). The control process reaches it only through the device
proxies of ``sim_backends.remote``, exactly as it would reach a rig.
"""

from __future__ import annotations

import contextlib
import math
import os
import threading
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

from drivers.base import ArmState, DeviceError, GripperState, TrackState
from estimators.geometry import Pose
from sim_backends.camera import Viewpoint
from sim_backends.world import SimRig

#: SCHED_FIFO priority of the world process (the control loop runs at 50).
WORLD_PRIORITY = 45
#: Niceness of the camera process: ahead of the host-side processes (estimators), but not
#: real-time — a renderer that needs more than a core at close range would, at SCHED_FIFO, run
#: into the kernel's real-time throttling and stall the control loop with it.
CAMERA_NICE = -10
#: Device methods the control side may call (anything else is refused by name).
CALLS = {
    "arm": {"connect", "activate", "deactivate", "close", "servo", "stop"},
    "track": {"connect", "activate", "deactivate", "close", "move_velocity", "move_to", "stop"},
    "gripper": {"connect", "activate", "deactivate", "close", "grip", "open"},
}
#: Faults a test or the fault suite may inject (method names of the simulated models).
FAULTS = {
    "arm": {"inject_protective_stop", "inject_emergency_stop", "inject_fault", "drop_link"},
    "track": {"inject_drive_fault"},
}


@dataclass(frozen=True, slots=True, eq=False)
class WorldSnapshot:
    """Every device's state after one step (None and a reason when it could not be read), and
    the ground truth of that instant."""

    stamp: float
    arm: ArmState | None
    track: TrackState | None
    gripper: GripperState | None
    errors: dict[str, str]
    X_WT: Pose
    X_WC: Pose


@dataclass(frozen=True, slots=True, eq=False)
class RenderRequest:
    """What the camera process needs to render frame ``seq`` as the world was at ``stamp``."""

    seq: int
    stamp: float
    view: Viewpoint
    X_WT: Pose


def _read(read: Any, name: str, errors: dict[str, str]) -> Any:
    try:
        return read()
    except DeviceError as exc:
        errors[name] = str(exc)
        return None


def snapshot(world: SimRig, *, states: bool = True) -> WorldSnapshot:
    """The world now: the device states (unless ``states`` is false: a world whose devices
    are read through real drivers elsewhere) and the ground truth."""
    errors: dict[str, str] = {}
    return WorldSnapshot(
        stamp=world.clock.now(),
        arm=_read(world.arm.state, "arm", errors) if states else None,
        track=_read(world.track.state, "track", errors) if states else None,
        gripper=_read(world.gripper.state, "gripper", errors) if states else None,
        errors=errors,
        X_WT=world.track_model.X_WT(),
        X_WC=world.arm.camera_pose_W(),
    )


def simulated_call(world: SimRig, kind: str, device: str, method: str, args: tuple) -> None:
    """A device call (``CALLS``) or an injected fault (``FAULTS``) in the simulated world."""
    allowed = (CALLS if kind == "call" else FAULTS).get(device, set())
    target = {"arm": world.arm, "track": world.track, "gripper": world.gripper}.get(device)
    if kind == "fault":
        target = world.arm if device == "arm" else world.track_model
    if method not in allowed or target is None:
        raise DeviceError(f"{device}.{method} is not available in the simulated world")
    getattr(target, method)(*args)


def apply_message(
    world: Any, message: tuple, replies: LatestSender, carry_out: Any = simulated_call
) -> bool:
    """Carry out one message from the control side with ``carry_out(world, kind, device,
    method, args)``; a failure is sent back (the control side's next call raises it), never
    fatal here. False when told to stop."""
    kind = message[0]
    if kind == "stop":
        return False
    if kind in ("call", "fault"):
        _, device, method, args = message
        try:
            carry_out(world, kind, device, method, args)
        except Exception as exc:  # reported to the caller's next call
            replies.tell(("error", device, method, f"{type(exc).__name__}: {exc}"))
    return True


class LatestSender:
    """Sends from a thread of its own, so that the physics never waits for a slow reader:
    ``put`` keeps only the newest state (a reader that fell behind gets the present, not a
    backlog); ``tell`` queues a message that must arrive (a refused command)."""

    def __init__(self, connection: Connection):
        self._connection = connection
        self._item: Any = None
        self._messages: list[Any] = []
        self._ready = threading.Condition()
        self._closed = False
        self._drain = False
        self._sending = False
        self.broken = False
        self._thread = threading.Thread(target=self._run, name="world-sender", daemon=True)
        self._thread.start()

    def put(self, item: Any) -> None:
        with self._ready:
            self._item = item
            self._ready.notify()

    def tell(self, message: Any) -> None:
        with self._ready:
            self._messages.append(message)
            self._ready.notify()

    def wait_sent(self, timeout_s: float) -> bool:
        """Wait until everything put so far has been sent (True) or ``timeout_s`` passed.

        The camera process calls it before it renders again: pybullet holds the GIL while it
        renders, so a frame still waiting for this thread would wait for the whole render."""
        with self._ready:
            return self._ready.wait_for(
                lambda: self.broken or not (self._sending or self._item is not None),
                timeout_s,
            )

    def close(self, *, drain: bool = False) -> None:
        """Stop sending; with ``drain``, what is pending goes out first (a camera's last
        frame), within the 2 s the thread is waited for."""
        with self._ready:
            self._closed = True
            self._drain = drain
            self._ready.notify()
        self._thread.join(timeout=2.0)

    def _run(self) -> None:
        while True:
            with self._ready:
                while self._item is None and not self._messages and not self._closed:
                    self._ready.wait()
                pending = self._item is not None or bool(self._messages)
                if self._closed and not (self._drain and pending):
                    return
                outgoing = [*self._messages, *([self._item] if self._item is not None else [])]
                self._messages, self._item = [], None
                self._sending = True
            try:
                for item in outgoing:
                    self._connection.send(item)
            except (BrokenPipeError, OSError):
                with self._ready:
                    self.broken = True
                    self._ready.notify_all()
                return
            with self._ready:
                self._sending = False
                self._ready.notify_all()


def capture_requests(world: SimRig, camera: Connection | None) -> LatestSender | None:
    """From now on, at each frame instant of ``world``, ask the camera process to render the
    scene as it is then (newest request only: a camera behind the frame rate drops frames)."""
    requests = LatestSender(camera) if camera is not None else None
    seq = 0

    def on_capture(stamp: float) -> None:
        nonlocal seq
        if requests is not None:
            requests.put(RenderRequest(seq, stamp, world.viewpoint(), world.track_model.X_WT()))
        seq += 1

    world.on_capture = on_capture  # type: ignore[method-assign]
    return requests


def run_world(
    world: SimRig,
    control: Connection,
    camera: Connection | None,
    *,
    step_s: float = 0.008,
) -> None:
    """Run ``world`` in real time until the control side says stop (or goes away)."""
    requests = capture_requests(world, camera)
    grid = world.grid_s
    sender = LatestSender(control)
    running = True
    next_step = time.monotonic()
    while running and not sender.broken:
        try:
            while control.poll(0):
                running = apply_message(world, control.recv(), sender) and running
        except (EOFError, OSError):
            break
        # Whole grid steps only: every model's state is then the state of the snapshot's stamp.
        steps = math.floor((time.monotonic() - world.clock.now()) / grid)
        if steps > 0:
            world.advance(steps * grid)
        sender.put(snapshot(world))
        next_step += step_s
        delay = next_step - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        else:
            next_step = time.monotonic()  # fell behind: no burst to catch up
    sender.close()
    if requests is not None:
        requests.close()


def realtime_priority(priority: int) -> str:
    """Ask for ``SCHED_FIFO`` at ``priority`` for this thread; '' when granted, else why not."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (AttributeError, OSError) as exc:
        return f"SCHED_FIFO refused ({exc})"
    return ""


def world_main(
    build: Any, control: Connection, camera: Connection | None, run: Any = run_world
) -> None:
    """The world process: build the rig with ``build(start_time)``, say ready, run it with
    ``run(world, control, camera)`` (``run_world``, or the emulated rig's loop), clean up.

    Like a robot controller it runs at real-time priority when the system allows (below the
    control loop's): on a loaded machine a world that falls behind the wall clock would make
    the trial fail for reasons no rig has."""
    with contextlib.suppress(KeyboardInterrupt):  # Ctrl-C goes to the control process
        # First, so that the threads the rig starts (Modbus servers) inherit the priority.
        priority = realtime_priority(WORLD_PRIORITY)
        # The activation in start() runs on simulated time (about a second): begin that far in
        # the past, then catch up with the present before the control side takes over.
        try:
            world = build(start_time=time.monotonic() - 2.0)
        except Exception as exc:  # e.g. an emulator's address in use: say so, in one line
            with contextlib.suppress(OSError):
                control.send(("failed", f"{type(exc).__name__}: {exc}"))
            return
        try:
            world.start()
            grid = world.grid_s
            world.advance(math.floor((time.monotonic() - world.clock.now()) / grid) * grid)
            control.send(("ready", priority))
            run(world, control, camera)
        except Exception as exc:
            with contextlib.suppress(OSError):
                control.send(("failed", f"{type(exc).__name__}: {exc}"))
        finally:
            world.close()
            if camera is not None:
                with contextlib.suppress(OSError):
                    camera.send(None)
