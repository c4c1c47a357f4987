"""``satgrasp check-rig``: is every device of a configuration there, and ready to run a trial?

One ``DeviceCheck`` per device: what answered and what it reported (the arm's flange pose,
safety and robot modes; a camera frame's size, intrinsics and latency; the track's position,
travel and limits; the gripper's activation, position and fault), or why it is not ready — the
driver's own one-line reason (which port refused or stayed silent, which fault is latched).

Read-only: nothing is activated, so nothing moves (a gripper's activation would move its
fingers; the arm's control script is not uploaded).

Never a hang: each device is checked in a process of its own, forked, and killed when it has
not answered within ``timeout_s`` — ur-rtde's constructors and depthai's device opening cannot
be interrupted from inside their process, so the bound is the parent's, whatever a driver does;
the report then names the step that hung. The checks run side by side.

An emulated configuration starts its emulated world (and its rendering camera) first, as a
trial would, and stops it at the end.
"""

from __future__ import annotations

import contextlib
import logging
import math
import multiprocessing as mp
import time
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from typing import Any

import numpy as np

from configuration.camera import CameraConfig, load_camera
from configuration.devices import (
    ModbusTrackDevice,
    OakCameraDevice,
    RobotiqGripperDevice,
    SimDevice,
    URArmDevice,
)
from configuration.mockup import MockupConfig, load_mockup
from configuration.rig import load_rig
from configuration.simulation import SimulationConfig
from drivers.base import DeviceError, DeviceTimeout
from drivers.gripper_robotiq import RobotiqGripper
from drivers.track_modbus import ModbusTrack
from estimators.frame import CameraInfo, Frame
from hil.runtime.processes import ProcessStartError, stop_process
from hil.runtime.wall import CameraReady, await_ready, start_render_camera, start_world
from sim_backends.remote import RemoteCamera, WorldLink
from sim_backends.start import TrialStart, sample_start

#: Order of the report.
DEVICES = ("arm", "camera", "track", "gripper")

Step = Callable[[str], None]


@dataclass(frozen=True, slots=True)
class DeviceCheck:
    """One device's verdict: ``detail`` says what it reported, or why it is not ready."""

    device: str
    ready: bool
    detail: str

    def line(self) -> str:
        return f"{self.device:<8} {'ready' if self.ready else 'NOT READY':<9}  {self.detail}"


# --- the checks, one per kind of device ------------------------------------------------------


def check_arm(config: URArmDevice, step: Step) -> DeviceCheck:
    """Connect (RTDE handshake, dashboard, state stream), read a state and the controller's
    modes; ready when the arm could move: no stop, no fault, robot RUNNING, no program of
    someone else's running."""
    arm = config.driver()
    step(f"connecting to the UR at {config.host}")
    try:
        arm.connect()
    except DeviceError as exc:
        return DeviceCheck("arm", False, str(exc))
    try:
        step("reading the arm's state")
        state = arm.state()
        modes = arm.controller_modes()
    except DeviceError as exc:
        return DeviceCheck("arm", False, str(exc))
    finally:
        step("closing the UR interfaces")
        arm.close()
    p = state.X_BE.p
    detail = (
        f"UR {config.host}, PolyScope {arm.polyscope_version or '?'}: flange at "
        f"({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}) m in B, "
        + ", ".join(f"{name} {value}" for name, value in modes.items())
    )
    reason = state.fault_reason
    if reason is None and modes["runtime state"] == "PLAYING":
        reason = "a program is running on the controller (stop it on the teach pendant)"
    if reason is not None:
        return DeviceCheck("arm", False, f"{reason} — {detail}")
    return DeviceCheck("arm", True, detail)


def check_track(config: ModbusTrackDevice, step: Step) -> DeviceCheck:
    """Connect (reads the travel and limits), read the status; ready without a fault."""
    track = ModbusTrack.over_tcp(
        config.host, config.port, config.device_id, timeout_s=config.timeout_s
    )
    try:
        step(f"connecting to the track at {config.host}:{config.port}")
        track.connect()
        step("reading the track's status")
        state = track.state()
    except DeviceError as exc:
        return DeviceCheck("track", False, str(exc))
    finally:
        track.close()
    detail = (
        f"{track.link.description}: at {state.position:.4f} m, travel "
        f"{track.travel_min:.3f}…{track.travel_max:.3f} m, max {track.max_speed:.3f} m/s"
        + (", moving" if state.moving else "")
    )
    if state.fault is not None:
        return DeviceCheck("track", False, f"fault: {state.fault} — {detail}")
    return DeviceCheck("track", True, detail)


def check_gripper(config: RobotiqGripperDevice, step: Step) -> DeviceCheck:
    """Connect, read the status; ready without a fault (an inactive gripper is fine: the trial
    activates it — the check does not, the fingers would move)."""
    gripper = RobotiqGripper.over_tcp(
        config.host, config.port, config.device_id, timeout_s=config.timeout_s
    )
    try:
        step(f"connecting to the gripper at {config.host}:{config.port}")
        gripper.connect()
        step("reading the gripper's status")
        state = gripper.state()
    except DeviceError as exc:
        return DeviceCheck("gripper", False, str(exc))
    finally:
        gripper.close()
    detail = (
        f"{gripper.link.description}: "
        + ("activated" if state.activated else "not activated (the trial activates it)")
        + f", position {state.position:.2f}"
        + (", object held" if state.object_detected else "")
    )
    if state.fault is not None:
        return DeviceCheck("gripper", False, f"fault: {state.fault} — {detail}")
    return DeviceCheck("gripper", True, detail)


def check_camera(config: OakCameraDevice, step: Step) -> DeviceCheck:
    """Open the camera (or the replay), take one frame, report its intrinsics and latency."""
    camera = config.build()
    try:
        step("opening the camera")
        camera.connect()
        camera.activate()
        step("waiting for a frame")
        frame = camera.read(timeout_s=2.0)
    except DeviceError as exc:
        return DeviceCheck("camera", False, str(exc))
    finally:
        camera.close()
    return DeviceCheck("camera", True, describe_frame(frame))


def describe_frame(frame: Frame) -> str:
    """A frame's source, size, intrinsics, distortion and latency, in one line."""
    info: CameraInfo = frame.info
    K = np.asarray(info.K)
    latency = frame.latency_s
    return (
        f"{info.model}: {info.width}×{info.height}, fx {K[0, 0]:.1f} fy {K[1, 1]:.1f} "
        f"cx {K[0, 2]:.1f} cy {K[1, 2]:.1f} px, {len(info.dist)} distortion coefficients"
        + (
            ""
            if latency is None or not math.isfinite(latency)
            else f", latency {latency * 1e3:.0f} ms"
        )
    )


CHECKS: dict[str, Callable[[Any, Step], DeviceCheck]] = {
    "arm": check_arm,
    "camera": check_camera,
    "track": check_track,
    "gripper": check_gripper,
}


# --- bounded, side by side -------------------------------------------------------------------


def _child(device: str, config: Any, connection: Connection) -> None:
    # The drivers' errors say what pymodbus would also log, less clearly, on the terminal.
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)

    def step(text: str) -> None:
        connection.send(("step", text))

    try:
        result = CHECKS[device](config, step)
    except Exception as exc:  # a check must answer, whatever went wrong
        result = DeviceCheck(device, False, f"{type(exc).__name__}: {exc}")
    connection.send(("done", result))


def run_bounded(configs: dict[str, Any], timeout_s: float) -> dict[str, DeviceCheck]:
    """Check every device of ``configs`` (name → its configuration) in a forked process of
    its own, all at once; a check still running after ``timeout_s`` is killed and reported
    with the step it hung in."""
    context = mp.get_context("fork")
    running: dict[Connection, tuple[str, mp.process.BaseProcess]] = {}
    steps: dict[str, str] = {}
    results: dict[str, DeviceCheck] = {}
    try:
        for device, config in configs.items():
            ours, theirs = context.Pipe(duplex=False)
            process = context.Process(target=_child, args=(device, config, theirs), daemon=True)
            process.start()
            theirs.close()
            running[ours] = (device, process)
        deadline = time.monotonic() + timeout_s
        while running and (left := deadline - time.monotonic()) > 0:
            for connection in wait(list(running), timeout=left):
                device, process = running[connection]
                try:
                    kind, payload = connection.recv()
                except (EOFError, OSError):
                    kind, payload = (
                        "done",
                        DeviceCheck(
                            device,
                            False,
                            f"the check ended without an answer ({steps.get(device)})",
                        ),
                    )
                if kind == "step":
                    steps[device] = payload
                    continue
                results[device] = payload
                del running[connection]
                connection.close()
                stop_process(process, timeout_s=2.0)
    finally:
        for connection, (device, process) in running.items():
            results[device] = DeviceCheck(
                device,
                False,
                f"no answer within {timeout_s:g} s while {steps.get(device, 'starting')}",
            )
            process.kill()
            process.join(1.0)
            connection.close()
    return results


# --- a configuration's rig ---------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class _Setup:
    """What the emulated world and its camera are built from (``hil.runtime.wall.RigSetup``)."""

    config: SimulationConfig
    mockup: MockupConfig
    camera: CameraConfig
    start: TrialStart
    seed: int = 0


def _rendered_frame(frames: Connection, info: CameraInfo, timeout_s: float) -> DeviceCheck:
    camera = RemoteCamera(frames, info)
    camera.activate()
    try:
        frame = camera.read(timeout_s=timeout_s)
    except DeviceTimeout as exc:
        return DeviceCheck("camera", False, f"rendered camera: {exc}")
    return DeviceCheck("camera", True, "rendered from the emulated world, " + describe_frame(frame))


def check_rig(config: SimulationConfig, *, timeout_s: float = 10.0) -> list[DeviceCheck]:
    """Every device of ``config``, in ``DEVICES`` order (see the module docstring)."""
    devices = config.devices
    if devices.kind == "sim":
        return [
            DeviceCheck(name, True, "simulated (backend sim): nothing to connect to")
            for name in DEVICES
        ]
    configs = {
        name: getattr(devices, name)
        for name in DEVICES
        if not isinstance(getattr(devices, name), SimDevice)
    }
    if devices.kind == "real":
        results = run_bounded(configs, timeout_s)
        return [results[name] for name in DEVICES]
    return _check_emulated(config, configs, timeout_s)


def _check_emulated(
    config: SimulationConfig, configs: dict[str, Any], timeout_s: float
) -> list[DeviceCheck]:
    """Start the emulated world (and its rendering camera, when the camera is rendered), check
    its devices through their real drivers, stop it."""
    setup = _Setup(
        config,
        load_mockup(config.mockup),
        load_camera(config.camera),
        sample_start(config.start, load_rig(config.rig), np.random.default_rng(0)),
    )
    context = mp.get_context("spawn")
    processes: dict[str, mp.process.BaseProcess] = {}
    frames = camera_ready = None
    link = None
    try:
        if "camera" not in configs:
            frames, camera_ready = start_render_camera(setup, context, processes)
        world = start_world(setup, context, processes, camera_ready)
        try:
            await_ready(world, "emulated world", processes["world"])
            if isinstance(camera_ready, CameraReady):
                await_ready(camera_ready, "camera", processes["camera"])
        except ProcessStartError as exc:
            return [DeviceCheck(name, False, str(exc)) for name in DEVICES]
        link = WorldLink(world)
        results = run_bounded(configs, timeout_s)
        if frames is not None:
            results["camera"] = _rendered_frame(frames, setup.camera.camera_info(), timeout_s)
        return [results[name] for name in DEVICES]
    finally:
        if link is not None:
            link.close()
        for connection in (frames,):
            if connection is not None:
                with contextlib.suppress(OSError):
                    connection.close()
        for process in processes.values():
            stop_process(process, timeout_s=5.0)
