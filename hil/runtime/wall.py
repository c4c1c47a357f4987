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
import time
from dataclasses import dataclass, replace
from multiprocessing.connection import Connection, wait
from typing import TYPE_CHECKING, Any

from configuration.vision import VisionConfig
from drivers.base import DeviceTimeout
from drivers.clock import RealClock
from estimators.frame import CameraInfo
from estimators.fusion import FusionParams, PoseFusion
from estimators.registry import build_estimator
from estimators.target import TargetModel
from hil.logs.foxglove import bounded_features
from hil.logs.records import VisionRecord
from hil.runtime.history import StateHistory, StateRing, StateSample
from hil.runtime.judge import truth_record
from hil.runtime.loop import ControlLoop
from hil.runtime.processes import peak_rss_mib, sigint_blocked_in_children, stop_process
from hil.runtime.rig import RigGeometry
from hil.runtime.vision import LoggedImage, VisionPipeline, VisionStatus
from hil.runtime.workers import InlineWorkers, ProcessWorkers
from sim_backends.camera_server import camera_main
from sim_backends.remote import RemoteArm, RemoteCamera, RemoteGripper, RemoteTrack, WorldLink
from sim_backends.world import SimRig
from sim_backends.world_server import world_main

if TYPE_CHECKING:
    from hil.runtime.compose import Trial

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
    spec: VisionSpec, frames: Connection, context: Any = None
) -> tuple[mp.process.BaseProcess, VisionClient]:
    """Start the vision process on the reading end ``frames`` of a camera's pipe; returns it
    and the control side's link once it is ready (its workers built). The caller closes the
    link (``VisionClient.stop``), which also frees the shared state ring."""
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
        _await_ready(ours, "vision", process)
    except BaseException:
        stop_process(process, timeout_s=0.0)
        states.close()
        raise
    return process, VisionClient(ours, states)


class VisionClient:
    """The control loop's ``VisionLink`` to the vision process: the state goes through shared
    memory (never blocks), reading takes whatever has arrived on the pipe."""

    def __init__(self, connection: Connection, states: StateRing):
        self._connection = connection
        self._states = states
        self._status = VisionStatus(fusion=None)
        self._items: list[VisionRecord | LoggedImage] = []
        self.peak_rss: dict[str, float] = {}

    def begin(self, t0: float) -> None:
        self._connection.send(("begin", t0))

    def publish_state(self, sample: StateSample) -> None:
        self._states.write(sample)

    def latest(self) -> VisionStatus:
        self._receive()
        return self._status

    def drain(self) -> list[VisionRecord | LoggedImage]:
        self._receive()
        items, self._items = self._items, []
        return items

    def stop(self, timeout_s: float = 10.0) -> None:
        if self._states is None:
            return
        with contextlib.suppress(BrokenPipeError, OSError):
            self._connection.send(("stop",))
        deadline = time.monotonic() + timeout_s
        while not self.peak_rss and time.monotonic() < deadline:
            if not self._connection.poll(0.05):
                continue
            self._receive()
        self._states.close()
        self._states = None

    def _receive(self) -> None:
        try:
            while self._connection.poll(0):
                kind, payload = self._connection.recv()
                if kind == "status":
                    self._status = payload
                elif kind == "records":
                    self._items.extend(payload)
                elif kind == "peak_rss_mib":
                    self.peak_rss = payload
        except (EOFError, OSError):
            pass


# --- building the wall-clock trial -----------------------------------------------------------


def _await_ready(connection: Connection, what: str, process: mp.process.BaseProcess) -> None:
    deadline = time.monotonic() + START_TIMEOUT_S
    while time.monotonic() < deadline:
        if connection.poll(0.1):
            kind, detail = connection.recv()
            if kind == "ready":
                return
            raise RuntimeError(f"the {what} process failed to start: {detail}")
        if not process.is_alive():
            raise RuntimeError(f"the {what} process exited during start-up ({process.exitcode})")
    raise RuntimeError(f"the {what} process did not start within {START_TIMEOUT_S:.0f} s")


class RealtimePriority:
    """``SCHED_FIFO`` for the control thread while it runs (with a logged warning when the
    system refuses it: a rig needs CAP_SYS_NICE or an rtprio limit for its user)."""

    def __init__(self, priority: int = 50):
        self.priority = priority
        self.granted = False
        self.reason = ""

    def __enter__(self) -> RealtimePriority:
        try:
            self._previous = os.sched_getscheduler(0), os.sched_getparam(0)
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.priority))
            self.granted = True
        except (AttributeError, OSError) as exc:
            self.reason = f"SCHED_FIFO refused ({exc}); the control loop runs at normal priority"
            log.warning(self.reason)
        return self

    def __exit__(self, *exc: object) -> None:
        if self.granted:
            with contextlib.suppress(OSError):
                os.sched_setscheduler(0, self._previous[0], self._previous[1])


def build_wall(trial: Trial) -> None:
    """Start the world, camera and vision processes for ``trial`` and build its loop on them."""
    config, start, stack = trial.config, trial.start, trial._stack
    context = mp.get_context("spawn")
    build = functools.partial(SimRig, start.rig, **trial.rig_options())
    world_ours, world_theirs = context.Pipe()
    # Pipe(duplex=False) gives (reading end, writing end).
    requests_in, requests_out = context.Pipe(duplex=False)  # world → camera
    frames_in, frames_out = context.Pipe(duplex=False)  # camera → vision
    camera_ready_in, camera_ready_out = context.Pipe(duplex=False)
    processes: dict[str, mp.process.BaseProcess] = {}

    def stop_all() -> None:
        for process in processes.values():
            stop_process(process)

    stack.callback(stop_all)
    processes["camera"] = context.Process(
        target=camera_main,
        args=(
            trial.mockup,
            trial.camera,
            config.noise,
            config.render,
            config.camera_timing,
            trial.seed,
            requests_in,
            frames_out,
            camera_ready_out,
        ),
        name="satgrasp-camera",
    )
    processes["world"] = context.Process(
        target=world_main, args=(build, world_theirs, requests_out), name="satgrasp-world"
    )
    with sigint_blocked_in_children():
        for process in processes.values():
            process.start()
    for connection in (world_theirs, requests_out, requests_in, frames_out, camera_ready_out):
        connection.close()
    spec = VisionSpec(
        tuple(config.systems),
        trial.mockup.target_model(),
        trial.camera.camera_info(),
        config.fusion,
        trial.geometry,
        config.vision,
    )
    processes["vision"], vision = start_vision(spec, frames_in, context)
    frames_in.close()
    _await_ready(_Ready(camera_ready_in), "camera", processes["camera"])
    _await_ready(world_ours, "world", processes["world"])

    link = WorldLink(world_ours)
    stack.callback(link.close)
    link.wait_for_state(5.0)
    stack.callback(vision.stop)
    trial.vision = vision
    trial.world_link = link
    trial.processes = processes
    arm, track, gripper = RemoteArm(link), RemoteTrack(link), RemoteGripper(link)
    for device in (arm, track, gripper):
        device.connect()

    def truth():
        newest = link.newest()
        return None if newest is None else truth_record({"X_WT": newest.X_WT, "X_WC": newest.X_WC})

    trial.loop = ControlLoop(
        arm=arm,
        track=track,
        gripper=gripper,
        vision=vision,
        geometry=trial.geometry,
        config=config.approach,
        clock=RealClock(),
        log=trial.log,
        truth=truth,
        observers=trial._observers(),
    )
    trial.realtime = stack.enter_context(RealtimePriority())

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


class _Ready:
    """The camera process answers its ready pipe with a bare string."""

    def __init__(self, connection: Connection):
        self._connection = connection

    def poll(self, timeout: float) -> bool:
        return self._connection.poll(timeout)

    def recv(self) -> tuple[str, Any]:
        answer = self._connection.recv()
        return ("ready", None) if answer == "ready" else ("failed", answer)
