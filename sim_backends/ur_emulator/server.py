"""The emulator's event loop: the three ports, the controller on the wall clock, the control
channel.

One thread does everything, so nothing needs a lock: it waits on every socket (and the control
channel) until the next controller period, answers what arrived, runs the controller's periods
that are due on the wall clock (``time.monotonic``; a late loop catches up period by period, at
most ``MAX_CATCH_UP_S`` at once), then sends each started RTDE session its data package.
Connections use short send time-outs: a client that stops reading is dropped, never waited for.
"""

from __future__ import annotations

import contextlib
import selectors
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from multiprocessing.connection import Connection

import numpy as np

from configuration.rig import ArmConfig
from drivers import rtde_protocol as rtde
from drivers.ur_probe import DASHBOARD_PORT, RTDE_PORT, SCRIPT_PORT
from estimators.geometry import Pose
from sim_backends.arm import SimArm
from sim_backends.loopback import check_loopback
from sim_backends.ur_emulator.command_log import CommandLog
from sim_backends.ur_emulator.controller import EmulatedController
from sim_backends.ur_emulator.dashboard import WELCOME, DashboardSession
from sim_backends.ur_emulator.faults import LinkFaults
from sim_backends.ur_emulator.interpreter import ControlScript, is_control_script, register_offsets
from sim_backends.ur_emulator.rtde_server import InputOwnership, RTDESession
from sim_backends.ur_emulator.script_socket import ScriptCollector

PORTS = {"dashboard": DASHBOARD_PORT, "script": SCRIPT_PORT, "rtde": RTDE_PORT}
SEND_TIMEOUT_S = 0.2
#: The longest stretch of controller time one late loop iteration catches up; beyond it the
#: periods are skipped (counted in ``skipped_periods``): the model pauses rather than jumps.
MAX_CATCH_UP_S = 0.1


@dataclass(frozen=True)
class EmulatorSettings:
    """What the emulator is: where it listens, which arm it models, how strict it is."""

    host: str
    arm: ArmConfig
    #: The dashboard refuses ``unlock protective stop`` this long after the stop (UR: 5 s).
    unlock_delay_s: float = 5.0
    #: What ``is in remote control`` answers.
    remote_control: bool = True
    seed: int = 0


@dataclass(frozen=True)
class EmulatorStatus:
    """A snapshot of the emulated controller for tests and the CLI. Stamps are host
    ``time.monotonic()``; ``published`` holds when the latest occurrence of each safety event
    first went out in a data package."""

    stamp: float
    timestamp: float
    q: tuple[float, ...]
    tcp_pose: tuple[float, ...]
    tcp_speed: tuple[float, ...]
    robot_mode: str
    safety_mode: str
    runtime_state: str
    program: str | None
    watchdog: tuple[str, float] | None
    watchdog_tripped: bool
    rtde_sessions: int
    started_sessions: int
    packages_sent: int
    cycles: int
    skipped_periods: int
    max_lag_s: float
    dropped: bool
    stalled: bool
    jitter_s: float
    published: dict[str, float] = field(default_factory=dict)
    command_count: int = 0

    @property
    def X_BE(self) -> Pose:
        return Pose.from_rotvec(np.array(self.tcp_pose[3:]), np.array(self.tcp_pose[:3]))


class _Client:
    def __init__(self, sock: socket.socket, kind: str, session):
        self.sock = sock
        self.kind = kind
        self.session = session
        self.reader = rtde.MessageReader() if kind == "rtde" else None
        self.line = b""


class EmulatorServer:
    """The emulated controller behind its ports (see the module docstring).

    Stand-alone (``run``/``serve_forever``) it keeps time itself on ``time.monotonic``. Inside a
    simulated world (``sim_backends.emulated_world``) it drives the world's ``arm`` and stamps
    with the world's ``clock``; the world then runs the controller (``controller.advance``) and
    calls ``poll`` and ``publish`` from its own loop.
    """

    def __init__(
        self,
        settings: EmulatorSettings,
        control: Connection | None = None,
        *,
        arm: SimArm | None = None,
        clock: Callable[[], float] = time.monotonic,
    ):
        check_loopback(settings.host, ipv4_only=True)
        self.settings = settings
        self.host = settings.host
        self.log = CommandLog()
        self._clock = clock
        self.controller = EmulatedController(
            settings.arm,
            self.log,
            arm=arm,
            unlock_delay_s=settings.unlock_delay_s,
            clock=self._clock,
        )
        self.faults = LinkFaults(seed=settings.seed)
        self.ownership = InputOwnership()
        self._fieldbus = object()  # owner of inputs claimed by fault injection
        self._selector = selectors.DefaultSelector()
        self._listeners: dict[str, socket.socket] = {}
        self._clients: dict[socket.socket, _Client] = {}
        self._control = control
        self._running = False
        self.cycles = 0
        self.skipped_periods = 0
        self.max_lag_s = 0.0
        self.packages_sent = 0
        if control is not None:
            self._selector.register(control, selectors.EVENT_READ, "control")

    # --- sockets ----------------------------------------------------------------------------
    def listen(self) -> None:
        """Bind the dashboard, script and RTDE ports on ``host``; ``OSError`` names the port."""
        for kind, port in PORTS.items():
            if kind in self._listeners:
                continue
            sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                sock.bind((self.host, port))
            except OSError as exc:
                sock.close()
                self.close_listeners()
                raise OSError(
                    exc.errno, f"cannot listen on {self.host}:{port} ({kind}): {exc.strerror}"
                ) from None
            sock.listen(8)
            sock.setblocking(False)
            self._listeners[kind] = sock
            self._selector.register(sock, selectors.EVENT_READ, ("listen", kind))

    def close_listeners(self) -> None:
        for sock in self._listeners.values():
            self._selector.unregister(sock)
            sock.close()
        self._listeners.clear()

    def close(self) -> None:
        for client in list(self._clients.values()):
            self._drop(client)
        self.close_listeners()
        self._selector.close()

    def _accept(self, kind: str) -> None:
        try:
            sock, peer = self._listeners[kind].accept()
        except (BlockingIOError, OSError):
            return
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.settimeout(SEND_TIMEOUT_S)
        name = f"{peer[0]}:{peer[1]}"
        if kind == "rtde":
            session = RTDESession(
                self.controller, self.ownership, self.log, peer=name, clock=self._clock
            )
        elif kind == "dashboard":
            session = DashboardSession(
                self.controller,
                self.log,
                clock=self._clock,
                remote_control=self.settings.remote_control,
            )
        else:
            session = ScriptCollector()
        client = _Client(sock, kind, session)
        self._clients[sock] = client
        self._selector.register(sock, selectors.EVENT_READ, ("client", client))
        if kind == "dashboard" and not self.faults.stalled:
            self._send(client, (WELCOME + "\n").encode())

    def _drop(self, client: _Client) -> None:
        if client.sock not in self._clients:
            return
        del self._clients[client.sock]
        with contextlib.suppress(KeyError, ValueError):
            self._selector.unregister(client.sock)
        client.sock.close()
        if client.kind == "rtde":
            client.session.close()
            self.log.add(self._clock(), "rtde", "closed", detail=client.session.peer)

    def _send(self, client: _Client, data: bytes) -> bool:
        try:
            client.sock.sendall(data)
            return True
        except OSError:  # time-out or reset: a client that does not read is dropped
            self._drop(client)
            return False

    def _read(self, client: _Client) -> None:
        try:
            data = client.sock.recv(65536)
        except OSError:
            data = b""
        if not data:
            self._drop(client)
            return
        if client.kind == "rtde":
            self._read_rtde(client, data)
        elif client.kind == "dashboard":
            self._read_dashboard(client, data)
        else:
            self._read_script(client, data)

    def _read_rtde(self, client: _Client, data: bytes) -> None:
        try:
            messages = client.reader.feed(data)
        except rtde.RTDEProtocolError as exc:
            self.log.add(self._clock(), "rtde", "bad stream", detail=str(exc))
            self._drop(client)
            return
        for kind, payload in messages:
            if self.faults.stalled and kind != rtde.Message.DATA_PACKAGE:
                continue  # a hung controller answers nothing (inputs still arrive)
            reply = client.session.handle(kind, payload)
            if reply is not None and not self._send(client, reply):
                return

    def _read_dashboard(self, client: _Client, data: bytes) -> None:
        client.line += data
        *lines, client.line = client.line.split(b"\n")
        for raw in lines:
            if self.faults.stalled:
                continue
            answer = client.session.reply(raw.decode("utf-8", errors="replace"))
            if not self._send(client, (answer + "\n").encode()):
                return
            if client.session.closed:
                self._drop(client)
                return

    def _read_script(self, client: _Client, data: bytes) -> None:
        for script in client.session.feed(data):
            now = self._clock()
            if script.name is None:
                self.log.add(now, "program", "statement not run", detail=script.text[:200])
            elif is_control_script(script.text):
                int_offset, float_offset = register_offsets(script.text)
                self.controller.start_program(
                    ControlScript(self.controller, int_offset=int_offset, float_offset=float_offset)
                )
            else:
                self.log.add(
                    now,
                    "program",
                    f"not run: {script.name}",
                    detail="only ur-rtde's control script is emulated",
                )

    # --- the loop -----------------------------------------------------------------------------
    def run(self) -> None:
        """Serve until ``stop()`` (a control request) or the control channel closes."""
        self._running = True
        period = self.controller.period_s
        next_tick = self._clock() + period
        publish_at: float | None = None
        while self._running:
            wake = next_tick if publish_at is None else min(next_tick, publish_at)
            self.poll(max(wake - self._clock(), 0.0))
            if not self._running:
                return
            now = self._clock()
            if now >= next_tick:
                lag = now - next_tick
                self.max_lag_s = max(self.max_lag_s, lag)
                due = int(lag // period) + 1
                runnable = min(due, max(1, int(MAX_CATCH_UP_S / period)))
                self.skipped_periods += due - runnable
                for _ in range(runnable):
                    self.controller.cycle()
                self.cycles += runnable
                next_tick += due * period
                if publish_at is None:
                    publish_at = now + self.faults.publish_delay()
            if publish_at is not None and self._clock() >= publish_at:
                self.publish()
                publish_at = None

    def stop(self) -> None:
        self._running = False

    def serve_forever(self) -> None:
        """``run()`` until stopped, the control channel closes or Ctrl-C; then close every
        socket."""
        try:
            self.run()
        except KeyboardInterrupt:
            pass
        finally:
            self.close()

    def poll(self, timeout_s: float) -> None:
        """Answer what arrives on the ports (and the control channel) within ``timeout_s``."""
        for key, _ in self._selector.select(timeout_s):
            self._dispatch(key.data, key.fileobj)
            if not self._running:
                return

    def _dispatch(self, data, fileobj) -> None:
        if data == "control":
            self._serve_control()
        elif data[0] == "listen":
            self._accept(data[1])
        else:
            client = data[1]
            if client.sock in self._clients:
                self._read(client)

    def publish(self) -> None:
        """Send every started RTDE session its data package when due (nothing while stalled)."""
        if self.faults.stalled:
            return
        sent = False
        for client in list(self._clients.values()):
            if client.kind != "rtde":
                continue
            package = client.session.data_package()
            if package is not None and self._send(client, package):
                self.packages_sent += 1
                sent = True
        if sent and self.controller.unpublished_events:
            now = self._clock()
            for event in self.controller.unpublished_events:
                self.controller.published[event] = now
            self.controller.unpublished_events.clear()

    # --- control channel (fault injection, inspection) ----------------------------------------
    def _serve_control(self) -> None:
        try:
            name, args, kwargs = self._control.recv()
        except (EOFError, OSError):
            self._running = False  # the owner went away
            return
        try:
            reply = ("ok", self.request(name, *args, **kwargs))
        except (ValueError, TypeError) as exc:
            reply = ("error", str(exc))
        with contextlib.suppress(OSError):
            self._control.send(reply)

    def request(self, name: str, *args, **kwargs):
        """Carry out the fault-injection or inspection request ``name`` (``UREmulator``'s
        methods); ``ValueError`` for an unknown name or bad arguments."""
        handler = self._handlers().get(name)
        if handler is None:
            raise ValueError(f"unknown emulator request {name!r}")
        return handler(*args, **kwargs)

    def _handlers(self) -> dict[str, Callable]:
        c = self.controller
        return {
            "stop": self.stop,
            "status": self.status,
            "commands": self.log.since,
            "drop_link": self.drop_link,
            "restore_link": self.restore_link,
            "stall_outputs": self.stall_outputs,
            "set_jitter": self.faults.set_jitter,
            "protective_stop": lambda program_keeps_running=False: c.protective_stop(
                "injected", program_keeps_running=program_keeps_running
            ),
            "unlock_protective_stop": c.unlock_protective_stop,
            "emergency_stop": c.emergency_stop,
            "release_emergency_stop": c.release_emergency_stop,
            "set_tcp_force": c.set_tcp_force,
            "set_tcp_offset": lambda offset: c.set_tcp_offset(np.asarray(offset, dtype=float)),
            "set_joint_positions": lambda q: c.set_joint_positions(np.asarray(q, dtype=float)),
            "claim_inputs": self.claim_inputs,
            "release_inputs": lambda: self.ownership.release(self._fieldbus),
        }

    def drop_link(self) -> None:
        self.faults.dropped = True
        self.log.add(self._clock(), "fault", "link dropped")
        for client in list(self._clients.values()):
            self._drop(client)
        self.close_listeners()

    def restore_link(self) -> None:
        self.listen()
        self.faults.dropped = False
        self.log.add(self._clock(), "fault", "link restored")

    def stall_outputs(self, stalled: bool = True) -> None:
        self.faults.stalled = bool(stalled)
        self.log.add(self._clock(), "fault", "outputs stalled" if stalled else "outputs resumed")

    def claim_inputs(self, names: list[str]) -> None:
        """A fieldbus takes these input variables: RTDE clients get ``IN_USE`` for them."""
        if not self.ownership.claim(self._fieldbus, list(names)):
            raise ValueError(f"inputs {names} are already set up by an RTDE client")
        self.log.add(self._clock(), "fault", "inputs claimed", detail=", ".join(names))

    def status(self) -> EmulatorStatus:
        c = self.controller
        sessions = [cl.session for cl in self._clients.values() if cl.kind == "rtde"]
        return EmulatorStatus(
            stamp=self._clock(),
            timestamp=c.timestamp,
            q=c.q,
            tcp_pose=c.tcp_pose,
            tcp_speed=c.tcp_speed,
            robot_mode=c.robot_mode.name,
            safety_mode=c.safety_mode.name,
            runtime_state=c.runtime_state.name,
            program=None if c.program is None else c.program.name,
            watchdog=c.watchdog,
            watchdog_tripped=c.watchdog_tripped,
            rtde_sessions=len(sessions),
            started_sessions=sum(s.started for s in sessions),
            packages_sent=self.packages_sent,
            cycles=self.cycles,
            skipped_periods=self.skipped_periods,
            max_lag_s=self.max_lag_s,
            dropped=self.faults.dropped,
            stalled=self.faults.stalled,
            jitter_s=self.faults.jitter_s,
            published=dict(c.published),
            command_count=self.log.count,
        )


def serve(settings: EmulatorSettings, control: Connection) -> None:
    """Entry point of the emulator process: bind, report ready (or why not), serve."""
    try:
        server = EmulatorServer(settings, control)
        server.listen()
    except (OSError, ValueError) as exc:
        control.send(("error", str(exc)))
        return
    control.send(("ready", {"host": settings.host, "ports": dict(PORTS)}))
    server.serve_forever()
