"""The emulated rig: the simulated world behind the real devices' protocols, in one process.

``configs/emulated.yaml`` runs the real drivers — ``URArm`` on ur-rtde, ``ModbusTrack`` and
``RobotiqGripper`` on pymodbus — against loopback emulators, and the camera must render what the
emulated arm really does. So the emulators are not programs with models of their own but the
front ends of one simulated world, ``EmulatedRig`` (a ``SimRig``):

* the UR controller emulator (``ur_emulator.EmulatorServer``: dashboard, script and RTDE ports on
  its own 127.x.y.z address) drives the world's ``SimArm`` — the arm whose camera pose the world
  renders from — one 2 ms controller period at a time as the world advances;
* the track and gripper models are served over Modbus TCP at their configured endpoints
  (``ModbusDeviceServer``, a thread of its own; the models lock), as their controllers are;
* at each frame instant the world asks the camera process to render the scene as it is then.

One thread runs it on the monotonic clock (``run_emulated_world``): wait on the UR ports until
the next grid instant (``SimRig.grid_s``, 4 ms); answer what arrived; advance the world to the
present in whole grid steps (controller periods, track, gripper, frame instants); send the RTDE
data packages; stream the ground truth to the control process for the trial log.

The ur-rtde client stays out of this process: its constructors hold the GIL while they wait
for the controller's answers, which this process would then never send.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection

from configuration.rig import ModbusEndpoint, RigConfig
from drivers.base import DeviceError
from sim_backends.loopback import check_loopback
from sim_backends.modbus_server import ModbusDeviceServer
from sim_backends.ur_emulator.controller import EmulatedController
from sim_backends.ur_emulator.server import EmulatorServer, EmulatorSettings
from sim_backends.world import SimRig
from sim_backends.world_server import (
    LatestSender,
    apply_message,
    capture_requests,
    snapshot,
)

#: Faults the control side may inject, per device: the UR emulator's requests
#: (``UREmulator``'s methods), and the Modbus devices' own.
FAULTS = {
    "ur": {
        "drop_link",
        "restore_link",
        "stall_outputs",
        "set_jitter",
        "protective_stop",
        "unlock_protective_stop",
        "emergency_stop",
        "release_emergency_stop",
        "set_tcp_force",
    },
    "track": {"silence", "inject_drive_fault"},
    "gripper": {"silence", "inject_fault"},
}


@dataclass(frozen=True, slots=True)
class EmulatedEndpoints:
    """Where the emulators listen: the UR controller's address (its ports are fixed: 29999,
    30003, 30004) and the Modbus endpoints of the track and the gripper (the two may share a
    host and port, as devices behind one gateway do, with distinct device ids)."""

    ur_host: str
    track: ModbusEndpoint
    gripper: ModbusEndpoint

    def __post_init__(self) -> None:
        check_loopback(self.ur_host, ipv4_only=True)
        for endpoint in (self.track, self.gripper):
            check_loopback(endpoint.host)
        same_server = (self.track.host, self.track.port) == (self.gripper.host, self.gripper.port)
        if same_server and self.track.device_id == self.gripper.device_id:
            raise ValueError("the emulated track and gripper have the same Modbus address")


class EmulatedRig(SimRig):
    """A ``SimRig`` whose arm is driven by an emulated UR controller and whose track and gripper
    answer over Modbus TCP; nothing in this process drives them (the control process does,
    through the real drivers). ``rig_options`` are ``SimRig``'s (grasp pose, start joints,
    capture range, camera timing, start time)."""

    def __init__(
        self,
        rig: RigConfig,
        endpoints: EmulatedEndpoints,
        *,
        unlock_delay_s: float = 5.0,
        **rig_options,
    ):
        self.endpoints = endpoints
        self._unlock_delay_s = unlock_delay_s
        self.server: EmulatorServer | None = None
        self._modbus: dict[str, tuple[ModbusDeviceServer, int]] = {}
        super().__init__(rig, **rig_options)

    def _drivers(self, links: str) -> tuple[None, None]:
        """Instead of drivers: the emulators in front of the models, listening."""
        endpoints = self.endpoints
        served = {}  # (host, port) → {device id: model}
        for endpoint, model in (
            (endpoints.track, self.track_model),
            (endpoints.gripper, self.gripper_model),
        ):
            served.setdefault((endpoint.host, endpoint.port), {})[endpoint.device_id] = model
        servers = {}
        for (host, port), devices in served.items():
            server = ModbusDeviceServer(devices, host=host, port=port)
            self._servers.append(server)  # stopped by SimRig.close
            servers[(host, port)] = server.start()
        for name, endpoint in (("track", endpoints.track), ("gripper", endpoints.gripper)):
            self._modbus[name] = (servers[(endpoint.host, endpoint.port)], endpoint.device_id)
        settings = EmulatorSettings(
            host=endpoints.ur_host, arm=self.rig.arm, unlock_delay_s=self._unlock_delay_s
        )
        self.server = EmulatorServer(settings, arm=self.arm, clock=self.clock.now)
        self.server.listen()
        return None, None

    @property
    def controller(self) -> EmulatedController:
        assert self.server is not None
        return self.server.controller

    def devices(self) -> tuple:
        return ()  # driven from the control process

    def start(self, settle_s: float = 1.0, dt: float = 0.01) -> None:
        """Frames are captured from now on (the drivers connect and activate the devices)."""
        self._next_capture = self.clock.now()

    def _step_arm(self, dt: float) -> None:
        self.controller.advance(dt)

    def inject(self, device: str, fault: str, *args: object) -> object:
        """Fault injection by name (``FAULTS``): the UR emulator's requests, a Modbus device
        going silent (``silence``, ``True``/``False``), a track drive fault, a gripper fault."""
        if fault not in FAULTS.get(device, set()):
            raise DeviceError(f"{device}.{fault} is not a fault of the emulated rig")
        if device == "ur":
            assert self.server is not None
            return self.server.request(fault, *args)
        if fault == "silence":
            server, device_id = self._modbus[device]
            server.silence(device_id, *(bool(a) for a in args))
            return None
        model = self.track_model if device == "track" else self.gripper_model
        return getattr(model, fault)(*args)

    def close(self) -> None:
        server, self.server = self.server, None
        if server is not None:
            server.close()
        super().close()


def _emulated_call(world: EmulatedRig, kind: str, device: str, method: str, args: tuple) -> None:
    if kind != "fault":
        raise DeviceError(f"{device}.{method}: the emulated rig is driven through its drivers")
    world.inject(device, method, *args)


def run_emulated_world(
    world: EmulatedRig,
    control: Connection,
    camera: Connection | None,
    *,
    truth_every_s: float = 0.008,
) -> None:
    """Run ``world`` and its emulators in real time until the control side says stop (or goes
    away); see the module docstring."""
    server = world.server
    assert server is not None
    requests = capture_requests(world, camera)
    sender = LatestSender(control)
    grid = world.grid_s
    next_truth = 0.0
    running = True
    while running and not sender.broken:
        server.poll(max(world.clock.now() + grid - time.monotonic(), 0.0))
        try:
            while control.poll(0):
                running = apply_message(world, control.recv(), sender, _emulated_call) and running
        except (EOFError, OSError):
            break
        # Whole grid steps only: every model's state is then the state of its stamp.
        steps = math.floor((time.monotonic() - world.clock.now()) / grid)
        if steps > 0:
            world.advance(steps * grid)
            server.publish()
        now = time.monotonic()
        if now >= next_truth:
            sender.put(snapshot(world, states=False))  # the states go through the drivers
            next_truth = now + truth_every_s
    sender.close()
    if requests is not None:
        requests.close()
