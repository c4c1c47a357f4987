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
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

from drivers.base import ArmState, DeviceError, GripperState, TrackState
from estimators.geometry import Pose
from sim_backends.camera import Viewpoint
from sim_backends.world import SimRig

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


def snapshot(world: SimRig) -> WorldSnapshot:
    errors: dict[str, str] = {}
    return WorldSnapshot(
        stamp=world.clock.now(),
        arm=_read(world.arm.state, "arm", errors),
        track=_read(world.track.state, "track", errors),
        gripper=_read(world.gripper.state, "gripper", errors),
        errors=errors,
        X_WT=world.track_model.X_WT(),
        X_WC=world.arm.camera_pose_W(),
    )


def _apply(world: SimRig, message: tuple, control: Connection) -> bool:
    """Carry out one message from the control side; False when told to stop."""
    kind = message[0]
    if kind == "stop":
        return False
    if kind in ("call", "fault"):
        _, device, method, args = message
        allowed = (CALLS if kind == "call" else FAULTS).get(device, set())
        target = {"arm": world.arm, "track": world.track, "gripper": world.gripper}.get(device)
        if kind == "fault":
            target = world.arm if device == "arm" else world.track_model
        try:
            if method not in allowed or target is None:
                raise DeviceError(f"{device}.{method} is not available in the simulated world")
            getattr(target, method)(*args)
        except Exception as exc:  # reported to the caller's next call, never fatal here
            control.send(("error", device, method, f"{type(exc).__name__}: {exc}"))
    return True


def run_world(
    world: SimRig,
    control: Connection,
    camera: Connection | None,
    *,
    step_s: float = 0.004,
) -> None:
    """Run ``world`` in real time until the control side says stop (or goes away)."""
    seq = 0

    def on_capture(stamp: float) -> None:
        nonlocal seq
        if camera is not None:
            camera.send(RenderRequest(seq, stamp, world.viewpoint(), world.track_model.X_WT()))
        seq += 1

    world.on_capture = on_capture  # type: ignore[method-assign]
    running = True
    next_step = time.monotonic()
    while running:
        try:
            while control.poll(0):
                running = _apply(world, control.recv(), control) and running
        except (EOFError, OSError):
            break
        lag = time.monotonic() - world.clock.now()
        if lag > 0:
            world.advance(lag)
        try:
            control.send(snapshot(world))
        except (BrokenPipeError, OSError):
            break
        next_step += step_s
        delay = next_step - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        else:
            next_step = time.monotonic()  # fell behind: no burst to catch up


def world_main(build: Any, control: Connection, camera: Connection | None) -> None:
    """The world process: build the rig with ``build(start_time)``, say ready, run, clean up."""
    with contextlib.suppress(KeyboardInterrupt):  # Ctrl-C goes to the control process
        # The activation in start() runs on simulated time (about a second): begin that far in
        # the past, then catch up with the present before the control side takes over.
        world = build(start_time=time.monotonic() - 2.0)
        try:
            world.start()
            world.advance(max(0.0, time.monotonic() - world.clock.now()))
            control.send(("ready", None))
            run_world(world, control, camera)
        except Exception as exc:
            with contextlib.suppress(OSError):
                control.send(("failed", f"{type(exc).__name__}: {exc}"))
        finally:
            world.close()
            if camera is not None:
                with contextlib.suppress(OSError):
                    camera.send(None)
