"""``--clock wall``: the trial on the wall clock, with the simulated world in processes of its own.

Processes (docs/architecture.md):

* **control** (this one): the ``ControlLoop`` at the control rate on the monotonic clock, under
  ``SCHED_FIFO`` when the system allows it; the devices are proxies (``sim_backends.remote``);
  writes the trial log.
* **world**: arm, track and gripper models stepped in real time (``sim_backends.world_server``).
* **camera**: renders each frame at its capture instant and delivers it after the camera's
  latency (``sim_backends.camera_server``).
* **vision**: the ``VisionPipeline`` (fusion included) fed by the camera, with one worker process
  per estimator (``ProcessWorkers``); it streams ``VisionStatus`` and records to the control
  process, which never waits for it.

Nothing in the loop knows that the devices are simulated: a rig differs only in the device
objects built here.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import multiprocessing as mp
import os
import queue
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from multiprocessing.connection import Connection, wait
from typing import TYPE_CHECKING, Any, Protocol

from configuration.devices import SimDevice
from configuration.vision import VisionConfig
from drivers.base import DeviceTimeout
from drivers.clock import RealClock
from estimators.frame import CameraInfo
from estimators.fusion import FusionParams, PoseFusion
from estimators.registry import build_estimator
from estimators.target import TargetModel
from hil.logs.foxglove import bounded_features
from hil.logs.records import TruthRecord, VisionRecord
from hil.runtime.devices import RealDevices, device_camera_main, emulated_endpoints
from hil.runtime.history import StateHistory, StateRing, StateSample
from hil.runtime.judge import truth_record
from hil.runtime.loop import ControlLoop
from hil.runtime.processes import (
    ProcessStartError,
    peak_rss_mib,
    sigint_blocked_in_children,
    stop_process,
    usable_cores,
)
from hil.runtime.rig import RigGeometry
from hil.runtime.vision import LoggedImage, VisionPipeline, VisionStatus
from hil.runtime.workers import InlineWorkers, ProcessWorkers
from sim_backends.camera_server import camera_main
from sim_backends.emulated_world import EmulatedRig, run_emulated_world
from sim_backends.remote import RemoteArm, RemoteCamera, RemoteGripper, RemoteTrack, WorldLink
from sim_backends.world import SimRig
from sim_backends.world_server import run_world, world_main

if TYPE_CHECKING:
    from configuration.camera import CameraConfig
    from configuration.mockup import MockupConfig
    from configuration.simulation import SimulationConfig
    from hil.runtime.compose import Trial
    from sim_backends.start import TrialStart

log = logging.getLogger(__name__)
START_TIMEOUT_S = 120.0


# --- the vision process ----------------------------------------------------------------------


@dataclass(frozen=True, slots=True, eq=False)
class VisionSpec:
    """What the vision process needs to build its pipeline."""

    systems: tuple[str, ...]
    target: TargetModel
    info: CameraInfo
    fusion: FusionParams
    geometry: RigGeometry
    config: VisionConfig
    #: The shared-memory ring the control process writes its ``StateSample``s into.
    state_ring: str = ""


def vision_main(spec: VisionSpec, control: Connection, frames: Connection) -> None:
    """The vision process: frames in, fused state and records out, until told to stop."""
    with contextlib.suppress(KeyboardInterrupt):  # Ctrl-C is the control process's business
        camera = RemoteCamera(frames, spec.info)
        camera.activate()
        try:
            workers = make_workers(spec)
        except Exception as exc:
            control.send(("failed", f"{type(exc).__name__}: {exc}"))
            return
        pipeline = VisionPipeline(
            systems=spec.systems,
            fusion=PoseFusion(spec.target, spec.fusion),
            history=StateHistory(spec.geometry),
            workers=workers,
            config=spec.config,
            slots=spec.config.estimator_slots(len(spec.systems), usable_cores()),
        )
        states = StateRing(spec.state_ring)
        try:
            control.send(("ready", None))
            _serve(pipeline, workers, camera, control, frames, states)
        finally:
            states.close()
            with contextlib.suppress(OSError):
                peaks = workers.peak_rss_mib() if isinstance(workers, ProcessWorkers) else {}
                control.send(("peak_rss_mib", peaks | {"vision": peak_rss_mib()}))
            pipeline.close()


def make_workers(spec: VisionSpec) -> ProcessWorkers | InlineWorkers:
    """One process per system, or all of them inline one after the other (to compare)."""
    if spec.config.workers == "process":
        return ProcessWorkers(spec.systems, spec.target, spec.info)
    estimators = {s: build_estimator(s, spec.target, spec.info) for s in spec.systems}
    return InlineWorkers(estimators, None)


def _serve(
    pipeline: VisionPipeline,
    workers: ProcessWorkers | InlineWorkers,
    camera: RemoteCamera,
    control: Connection,
    frames: Connection,
    states: StateRing,
) -> None:
    sent: VisionStatus | None = None
    while True:
        busy = workers.connections() if isinstance(workers, ProcessWorkers) else []
        wait([control, frames, *busy], timeout=0.01)
        now = time.monotonic()
        for sample in states.read_new():
            pipeline.publish_state(sample)
        try:
            while control.poll(0):
                message = control.recv()
                if message[0] == "begin":
                    pipeline.begin(message[1])
                elif message[0] == "stop":
                    return
        except (EOFError, OSError):
            return
        with contextlib.suppress(DeviceTimeout):
            pipeline.on_frame(camera.read(timeout_s=0.0), now)
        pipeline.step(now)
        status = pipeline.latest()
        items = pipeline.drain()
        try:
            if status is not sent:
                control.send(("status", status))
                sent = status
            if items:
                control.send(("records", [_lean(item) for item in items]))
        except (BrokenPipeError, OSError):
            return


def _lean(item: VisionRecord | LoggedImage) -> VisionRecord | LoggedImage:
    """A record with only the feature points the log draws, thinned (``bounded_features``):
    what crosses into the control process stays small."""
    if isinstance(item, VisionRecord) and item.measurement.features:
        features = bounded_features(item.measurement.features)
        return replace(item, measurement=replace(item.measurement, features=features))
    return item


def start_vision(
    spec: VisionSpec,
    frames: Connection,
    context: Any = None,
    *,
    meanwhile: Callable[[], None] | None = None,
) -> tuple[mp.process.BaseProcess, VisionClient]:
    """Start the vision process on the reading end ``frames`` of a camera's pipe; returns it
    and the control side's link once it is ready (its workers built). ``meanwhile`` runs while
    it starts (waiting for the other processes: one that fails is reported at once, not after
    the estimators' start-up). The caller closes the link (``VisionClient.stop``), which also
    frees the shared state ring."""
    context = context or mp.get_context("spawn")
    states = StateRing()
    spec = replace(spec, state_ring=states.name)
    ours, theirs = context.Pipe()
    process = context.Process(
        target=vision_main, args=(spec, theirs, frames), name="satgrasp-vision"
    )
    with sigint_blocked_in_children():
        process.start()
    theirs.close()
    try:
        if meanwhile is not None:
            meanwhile()
        await_ready(ours, "vision", process)
    except BaseException:
        stop_process(process, timeout_s=0.0)
        states.close()
        raise
    return process, VisionClient(ours, states)


#: SCHED_FIFO priority of the thread that receives from the vision process (control: 50).
RECEIVER_PRIORITY = 49


class VisionClient:
    """The control loop's ``VisionLink`` to the vision process: the state goes through shared
    memory (never blocks); what the vision process sends is received on a thread of its own
    and taken from there, so a tick never waits on the pipe. (``Connection.recv`` blocks until
    a whole message is in, and a message with a camera image for the log is a few hundred kB
    that the vision process, at normal priority, writes in pieces: read in the tick, it held
    the control thread 10–14 ms.)"""

    def __init__(self, connection: Connection, states: StateRing):
        self._connection = connection
        self._states = states
        self._status = VisionStatus(fusion=None)
        self._items: list[VisionRecord | LoggedImage] = []
        self._inbox: queue.SimpleQueue[tuple[str, Any]] = queue.SimpleQueue()
        self.peak_rss: dict[str, float] = {}
        self._receiver = threading.Thread(
            target=self._receive_all, name="vision-receiver", daemon=True
        )
        self._receiver.start()

    def begin(self, t0: float) -> None:
        self._connection.send(("begin", t0))

    def publish_state(self, sample: StateSample) -> None:
        self._states.write(sample)

    def latest(self) -> VisionStatus:
        self._take()
        return self._status

    def drain(self) -> list[VisionRecord | LoggedImage]:
        self._take()
        items, self._items = self._items, []
        return items

    def stop(self, timeout_s: float = 10.0) -> None:
        if self._states is None:
            return
        with contextlib.suppress(BrokenPipeError, OSError):
            self._connection.send(("stop",))
        deadline = time.monotonic() + timeout_s
        while not self.peak_rss and time.monotonic() < deadline:
            self._take()
            if not self.peak_rss:
                time.sleep(0.02)
        self._states.close()
        self._states = None

    def _receive_all(self) -> None:
        """The receiving thread: every message, whole, into the inbox, until the pipe ends. It
        runs just below the control thread's real-time priority when the system allows: at
        normal priority it could be preempted while holding the GIL, which the tick needs."""
        with contextlib.suppress(AttributeError, OSError):
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(RECEIVER_PRIORITY))
        try:
            while True:
                self._inbox.put(self._connection.recv())
        except (EOFError, OSError):
            return

    def _take(self) -> None:
        while True:
            try:
                kind, payload = self._inbox.get_nowait()
            except queue.Empty:
                return
            if kind == "status":
                self._status = payload
            elif kind == "records":
                self._items.extend(payload)
            elif kind == "peak_rss_mib":
                self.peak_rss = payload


def await_ready(connection: Connection, what: str, process: mp.process.BaseProcess) -> None:
    deadline = time.monotonic() + START_TIMEOUT_S
    while time.monotonic() < deadline:
        if connection.poll(0.1):
            kind, detail = connection.recv()
            if kind == "ready":
                return
            raise ProcessStartError(f"the {what} process failed to start: {detail}")
        if not process.is_alive():
            raise ProcessStartError(
                f"the {what} process exited during start-up ({process.exitcode})"
            )
    raise ProcessStartError(f"the {what} process did not start within {START_TIMEOUT_S:.0f} s")


class RealtimePriority:
    """``SCHED_FIFO`` for the control thread while it runs (with a logged warning when the
    system refuses it: a rig needs CAP_SYS_NICE or an rtprio limit for its user).

    The interpreter's switch interval drops from 5 ms to ``SWITCH_INTERVAL_S`` meanwhile: the
    control thread, woken for its tick, waits for the GIL until whichever other thread holds it
    (the status display's refresh) lets go, and that thread lets go only when its interval is
    up — 5 ms of a tick that must start within 4 ms."""

    SWITCH_INTERVAL_S = 0.0005

    def __init__(self, priority: int = 50):
        self.priority = priority
        self.granted = False
        self.reason = ""

    def __enter__(self) -> RealtimePriority:
        self._previous_interval = sys.getswitchinterval()
        sys.setswitchinterval(self.SWITCH_INTERVAL_S)
        try:
            self._previous = os.sched_getscheduler(0), os.sched_getparam(0)
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.priority))
            self.granted = True
        except (AttributeError, OSError) as exc:
            self.reason = f"SCHED_FIFO refused ({exc}); the control loop runs at normal priority"
            log.warning(self.reason)
        return self

    def __exit__(self, *exc: object) -> None:
        sys.setswitchinterval(self._previous_interval)
        if self.granted:
            with contextlib.suppress(OSError):
                os.sched_setscheduler(0, self._previous[0], self._previous[1])


class RigSetup(Protocol):
    """What the world and camera processes are built from (a ``Trial`` has it all)."""

    config: SimulationConfig
    mockup: MockupConfig
    camera: CameraConfig
    start: TrialStart
    seed: int


def build_wall(trial: Trial) -> None:
    """Start the processes of ``trial`` — world (simulated, or emulated behind the real devices'
    protocols) and camera, or a real camera alone; vision — build its devices and its loop."""
    config, stack = trial.config, trial._stack
    kind = config.devices.kind
    context = mp.get_context("spawn")
    processes: dict[str, mp.process.BaseProcess] = {}

    def stop_all() -> None:
        for process in processes.values():
            stop_process(process)

    stack.callback(stop_all)
    info = trial.camera.camera_info()
    world_ours = None
    if kind == "real" or not isinstance(config.devices.camera, SimDevice):
        frames_in, camera_ready = _start_device_camera(
            config.devices.camera, context, processes, stack
        )
    else:
        frames_in, camera_ready = start_render_camera(trial, context, processes)
    if kind != "real":
        world_ours = start_world(trial, context, processes, camera_ready)
    spec = VisionSpec(
        tuple(config.systems),
        trial.mockup.target_model(),
        info,
        config.fusion,
        trial.geometry,
        config.vision,
    )
    if isinstance(camera_ready, _DeviceCamera):
        spec = replace(spec, info=camera_ready.await_info(processes["camera"]))

    def others_ready() -> None:
        if world_ours is not None:
            await_ready(world_ours, "world", processes["world"])
        if isinstance(camera_ready, CameraReady):
            await_ready(camera_ready, "camera", processes["camera"])

    processes["vision"], vision = start_vision(spec, frames_in, context, meanwhile=others_ready)
    stack.callback(vision.stop)
    frames_in.close()
    link = None
    if world_ours is not None:
        link = WorldLink(world_ours)
        stack.callback(link.close)
        link.wait_for_state(5.0)
        trial.world_link = link
    trial.vision = vision
    trial.processes = processes
    if link is not None and kind == "sim":
        arm, track, gripper = RemoteArm(link), RemoteTrack(link), RemoteGripper(link)
        for device in (arm, track, gripper):
            device.connect()
    else:
        devices = RealDevices.from_config(config.devices, trial.start.rig)
        stack.callback(devices.close)
        trial.devices = devices
        arm, track, gripper = devices.arm, devices.track, devices.gripper

    trial.loop = ControlLoop(
        arm=arm,
        track=track,
        gripper=gripper,
        vision=vision,
        geometry=trial.geometry,
        config=config.approach,
        clock=RealClock(),
        log=trial.log,
        truth=None if link is None else functools.partial(_truth, link),
        observers=trial._observers(),
    )
    trial.realtime = stack.enter_context(RealtimePriority())
    if kind != "sim":
        # Last, and under SCHED_FIFO: the arm's watchdog runs from the zero twist that ends
        # start(), so the loop's first tick must follow within the watchdog's period even on
        # a loaded machine (at normal priority it did not, at load average 20); the drivers'
        # own threads (ur-rtde's receive threads) inherit the priority.
        trial.devices.start()

    def resources() -> dict[str, Any]:
        """Peak memory of every process (the vision process reports its own and its workers'
        as it stops) and whether the loop ran under SCHED_FIFO."""
        peaks = {name: peak_rss_mib(p.pid) for name, p in processes.items() if p.is_alive()}
        vision.stop()
        peaks |= {f"vision/{name}": mib for name, mib in vision.peak_rss.items()}
        peaks["control"] = peak_rss_mib()
        return {
            "peak_rss_mib": peaks,
            "sched_fifo": trial.realtime.granted,
            "sched_note": trial.realtime.reason,
        }

    trial.resources = resources


def _truth(link: WorldLink) -> TruthRecord | None:
    """The ground truth of the simulated world's newest state (a rig has none)."""

    newest = link.newest()
    if newest is None:
        return None
    return truth_record({"X_WT": newest.X_WT, "X_WC": newest.X_WC})


def start_render_camera(
    trial: RigSetup, context: Any, processes: dict[str, mp.process.BaseProcess]
) -> tuple[Connection, CameraReady]:
    """The rendering camera process of ``trial``'s simulated world; returns the frames' reading
    end and its ``CameraReady`` (which holds the world's end of the render requests)."""
    config = trial.config
    requests_in, requests_out = context.Pipe(duplex=False)  # world → camera
    frames_in, frames_out = context.Pipe(duplex=False)  # camera → vision
    ready_in, ready_out = context.Pipe(duplex=False)
    processes["camera"] = context.Process(
        target=camera_main,
        args=(
            trial.mockup,
            trial.camera,
            config.noise,
            config.render.for_noise(config.noise),
            config.camera_timing,
            trial.seed,
            requests_in,
            frames_out,
            ready_out,
        ),
        name="satgrasp-camera",
    )
    with sigint_blocked_in_children():
        processes["camera"].start()
    for connection in (requests_in, frames_out, ready_out):
        connection.close()
    return frames_in, CameraReady(ready_in, requests_out)


def _start_device_camera(
    camera: Any, context: Any, processes: dict[str, mp.process.BaseProcess], stack: Any
) -> tuple[Connection, _DeviceCamera]:
    """The camera process of a real camera (or a replay): ``hil.runtime.devices``."""
    frames_in, frames_out = context.Pipe(duplex=False)
    ours, theirs = context.Pipe()
    processes["camera"] = context.Process(
        target=device_camera_main, args=(camera, frames_out, theirs), name="satgrasp-camera"
    )
    with sigint_blocked_in_children():
        processes["camera"].start()
    frames_out.close()
    theirs.close()
    handle = _DeviceCamera(ours)
    stack.callback(handle.stop)
    return frames_in, handle


def start_world(
    trial: RigSetup,
    context: Any,
    processes: dict[str, mp.process.BaseProcess],
    camera: CameraReady | _DeviceCamera | None,
) -> Connection:
    """The world process — simulated, or emulated behind the real devices' protocols — fed
    with the rendering camera's request pipe when there is one; returns the control's end."""
    config, start = trial.config, trial.start
    from hil.runtime.compose import rig_options

    options = rig_options(config, start)
    if config.devices.kind == "emulated":
        endpoints = emulated_endpoints(config.devices)
        options.pop("links")  # the emulated rig's track and gripper are its Modbus servers
        build = functools.partial(EmulatedRig, start.rig, endpoints, **options)
        run: Any = run_emulated_world
    else:
        build = functools.partial(SimRig, start.rig, **options)
        run = run_world
    ours, theirs = context.Pipe()
    requests = camera.requests if isinstance(camera, CameraReady) else None
    processes["world"] = context.Process(
        target=world_main, args=(build, theirs, requests, run), name="satgrasp-world"
    )
    with sigint_blocked_in_children():
        processes["world"].start()
    theirs.close()
    if requests is not None:
        requests.close()
    return ours


class CameraReady:
    """The rendering camera process's ready pipe (it answers with a bare string); ``requests``:
    the writing end of its render requests, for the world process."""

    def __init__(self, connection: Connection, requests: Connection | None = None):
        self._connection = connection
        self.requests = requests

    def poll(self, timeout: float) -> bool:
        return self._connection.poll(timeout)

    def recv(self) -> tuple[str, Any]:
        answer = self._connection.recv()
        return ("ready", None) if answer == "ready" else ("failed", answer)


class _DeviceCamera:
    """The control side of a real camera's process: its ready answer carries the camera's
    ``CameraInfo``; ``stop`` asks it to end."""

    def __init__(self, connection: Connection):
        self._connection = connection
        self.info: CameraInfo | None = None

    def poll(self, timeout: float) -> bool:
        return self._connection.poll(timeout)

    def recv(self) -> tuple[str, Any]:
        kind, detail = self._connection.recv()
        if kind == "ready":
            self.info = detail
        return kind, detail

    def await_info(self, process: mp.process.BaseProcess) -> CameraInfo:
        await_ready(self, "camera", process)
        assert self.info is not None
        return self.info

    def stop(self) -> None:
        with contextlib.suppress(BrokenPipeError, OSError):
            self._connection.send("stop")
