"""The UR arm over ur-rtde: ``URArm`` implements ``drivers.base.Arm``.

Lifecycle (``drivers.base``): ``connect()`` opens ur-rtde's ``RTDEReceiveInterface`` (the state
stream) and the dashboard (status, unlocking a protective stop); ``activate()`` opens the
``RTDEControlInterface`` — ur-rtde uploads its control script — and checks that the TCP offset
is zero; the first ``servo()`` arms the controller's RTDE watchdog (arming it at activation
would stop the script whenever the first command comes later than the watchdog's period —
the time a control loop takes to start, or ur-rtde's own first command, which measured up to
90 ms on a loaded machine); ``deactivate()`` stops the arm (``speedStop``),
ends the script (``stopScript``) and closes the control interface; ``close()`` releases all.

Frames and units: the TCP is the flange ``tool0`` — the driver requires the controller's TCP
offset to be zero (``activate()`` refuses otherwise) — so ``getActualTCPPose`` is X_BE, the pose
of E in the controller's ``base`` frame B, and ``getActualTCPSpeed`` is V_BE = [v, ω] in B.
UR's axis-angle pose vectors are converted to ``Pose`` here and nowhere else.
``getActualTCPForce`` (e-Series: the wrench at the TCP expressed in B) becomes ``wrench_B``.

Time-outs, because ur-rtde's constructors wait for the controller with no time-out while
holding the GIL (a thread cannot rescue them; see ``drivers.ur_probe``): before each constructor
the driver walks the same RTDE handshake with socket time-outs. Methods release the GIL, so a
control call that can block (speedStop waits for the arm to rest; stopScript, disconnect) runs
in a helper thread joined with ``command_timeout_s``. After such a time-out the control
interface is not used again until that call returns. Releasing an interface costs ur-rtde's
fixed 0.5 s sleep twice: once in ``disconnect()`` (GIL released) and once in its destructor,
which holds the GIL — the whole process pauses for 0.5 s in ``deactivate()`` and ``close()``
(measured), so call them when the arm is already stopped, never inside the control loop.

Faults are read on every ``state()`` and before every ``servo()``: protective stop, emergency
stop, safety mode, robot mode and — while active — the control script's runtime state.
ur-rtde's stream calls can return True during a protective stop, so ``servo()`` checks the
flags itself before sending, and a refused call is reported with the reason the flags give.
A state stream that stops (link dropped, controller stalled) raises ``DeviceTimeout`` once no
new controller time stamp came for ``state_timeout_s``. Nothing retries silently:
``reconnect()`` is the one, bounded, way back (ur-rtde would reconnect inside a command sent
over a lost link; the driver checks the link before each command so that never happens).

Streaming: ``servo(command)`` sends ``speedL(V_BE, acceleration, time)``; a stop (a stop
command, or ``stop()``) is a zero twist ``speedL(0, deceleration)``: the arm decelerates at
that rate while the call returns at once — a control loop must keep its period while the arm
stops (``speedStop`` returns only at rest: 60 ms from 0.03 m/s measured, which the supervisor
took for a missed deadline) — and every repetition feeds the controller's watchdog like any
command (no ``kickWatchdog``: right after a ``speedL`` it overwrites the command register
before the script's next 2 ms cycle reads it — the emulator shows the speedL then lost;
docs/ur_emulator.md). ``deactivate()`` still ends with ``speedStop``, which waits for rest.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import dashboard_client
import numpy as np
import rtde_control
import rtde_receive

from drivers.base import ArmState, DeviceError, DeviceFault, DeviceTimeout, ServoCommand
from drivers.ur_probe import SCRIPT_PORT, probe_port, probe_rtde
from drivers.ur_states import (
    SAFETY_EMERGENCY,
    SAFETY_MOVABLE,
    RobotMode,
    RuntimeState,
    SafetyMode,
    name_of,
)
from estimators.geometry import Pose
from estimators.so3 import exp_so3

log = logging.getLogger(__name__)

#: What the driver reads from the controller (an RTDE output recipe of ten variables).
RECEIVE_VARIABLES = (
    "timestamp",
    "actual_q",
    "actual_TCP_pose",
    "actual_TCP_speed",
    "actual_TCP_force",
    "robot_mode",
    "safety_mode",
    "safety_status_bits",
    "runtime_state",
    "robot_status_bits",
)

_LOCAL_HOSTS = ("localhost", "127.0.0.1")  # ur-rtde skips its remote-control check for these


@dataclass(frozen=True, slots=True)
class URArmOptions:
    """How ``URArm`` talks to the controller (configuration: ``URArmConfig``).

    * ``connect_timeout_s``: bound on each connection step (probe, dashboard, constructors'
      handshake);
    * ``state_timeout_s``: no new controller time stamp for this long → ``DeviceTimeout``;
    * ``command_timeout_s``: bound on a blocking control call (speedStop, stopScript, disconnect);
    * ``speed_acceleration``: speedL's ``acc`` (m/s²) when a command gives none;
    * ``stop_deceleration``: speedStop's deceleration (m/s²) for stop commands;
    * ``watchdog_min_frequency_hz``: the controller stops the script when the command register
      gets no update at this rate (0: no watchdog);
    * ``receive_frequency_hz``: state stream rate (None: the controller's, 500 Hz on e-Series);
    * ``upper_range_registers``: use RTDE registers 24–47 (when a fieldbus owns 0–23);
    * ``reconnect_attempts`` and ``reconnect_backoff_s``: ``reconnect()``'s bounds.
    """

    connect_timeout_s: float = 2.0
    state_timeout_s: float = 0.1
    command_timeout_s: float = 2.0
    speed_acceleration: float = 1.0
    stop_deceleration: float = 2.0
    watchdog_min_frequency_hz: float = 10.0
    receive_frequency_hz: float | None = None
    upper_range_registers: bool = False
    reconnect_attempts: int = 3
    reconnect_backoff_s: float = 0.5

    def __post_init__(self) -> None:
        for name in (
            "connect_timeout_s",
            "state_timeout_s",
            "command_timeout_s",
            "speed_acceleration",
            "stop_deceleration",
            "reconnect_backoff_s",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"URArmOptions.{name} must be positive; got {value}")
        if not (
            math.isfinite(self.watchdog_min_frequency_hz) and self.watchdog_min_frequency_hz >= 0
        ):
            raise ValueError(
                f"URArmOptions.watchdog_min_frequency_hz must be ≥ 0; got {self.watchdog_min_frequency_hz}"
            )
        if self.receive_frequency_hz is not None and not 0 < self.receive_frequency_hz <= 500:
            raise ValueError(
                f"URArmOptions.receive_frequency_hz must be in (0, 500]; got {self.receive_frequency_hz}"
            )
        if self.reconnect_attempts < 1:
            raise ValueError(
                f"URArmOptions.reconnect_attempts must be ≥ 1; got {self.reconnect_attempts}"
            )


class URArm:
    """``drivers.base.Arm`` on a UR e-Series controller at ``host`` (see the module docstring).
    Not thread-safe: one thread (the control loop) calls it."""

    def __init__(self, host: str, options: URArmOptions | None = None):
        if not host:
            raise ValueError("URArm needs the controller's host name or address")
        self.host = host
        self.options = options if options is not None else URArmOptions()
        self._receive: Any = None
        self._dashboard: Any = None
        self._control: Any = None
        self._busy: threading.Thread | None = None  # a control call that outlived its time-out
        self._last_timestamp: float | None = None
        self._fresh_at = 0.0
        self._stopped = True  # no twist streamed since the last stop
        self._watchdog_armed = False
        self.polyscope_version = ""

    # --- lifecycle ------------------------------------------------------------------------------
    @property
    def connected(self) -> bool:
        return self._receive is not None

    @property
    def active(self) -> bool:
        return self._control is not None

    def connect(self) -> None:
        """Open the state stream and the dashboard within ``connect_timeout_s`` per step."""
        if self._receive is None:
            self._connect(self.options.connect_timeout_s)

    def activate(self) -> None:
        """Take control: upload ur-rtde's script, check the TCP offset. The first ``servo()``
        arms the watchdog."""
        self._require_connected("activate")
        if self._control is not None:
            return
        reason = self.state().fault_reason
        if reason is not None:
            raise DeviceFault(f"UR {self.host}: activate refused: {reason}")
        self._check_remote_control()
        timeout = self.options.connect_timeout_s
        probe_rtde(self.host, timeout_s=timeout)
        probe_port(self.host, SCRIPT_PORT, timeout_s=timeout, what="script")
        flags = rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT
        if self.options.upper_range_registers:
            flags |= rtde_control.RTDEControlInterface.FLAG_UPPER_RANGE_REGISTERS
        try:
            control = rtde_control.RTDEControlInterface(self.host, self._frequency(), flags)
        except RuntimeError as exc:
            raise DeviceError(
                f"UR {self.host}: the control interface did not start: {exc}"
            ) from None
        self._control, self._busy = control, None  # a stuck call of an old interface is moot
        self._stopped = True
        self._watchdog_armed = False
        try:
            offset = np.asarray(self._bounded("getTCPOffset", control.getTCPOffset), dtype=float)
            if offset.shape != (6,) or np.any(np.abs(offset) > 1e-6):
                raise DeviceError(
                    f"UR {self.host}: the TCP offset is {np.round(offset, 6).tolist()}, not zero; "
                    "this driver reports the flange tool0 as X_BE: set the TCP to zero in the "
                    "robot's installation (the camera's hand-eye pose X_EC carries the offset)"
                )
        except DeviceError:
            self.deactivate()
            raise

    def deactivate(self) -> None:
        """Stop the arm, end the control script and close the control interface."""
        self._disconnect(self._end_control())

    def close(self) -> None:
        """Deactivate, then close the state stream and the dashboard (safe to call twice)."""
        control = self._end_control()
        receive, self._receive = self._receive, None
        dashboard, self._dashboard = self._dashboard, None
        self._disconnect(control, receive, dashboard)

    def reconnect(self, *, attempts: int | None = None, timeout_s: float | None = None) -> None:
        """Close everything, then connect again: at most ``attempts`` tries (default
        ``options.reconnect_attempts``) of at most ``timeout_s`` per step, ``reconnect_backoff_s``
        apart. Leaves the arm connected and *inactive*: moving again is the caller's decision
        (``activate()``). Raises ``DeviceTimeout`` naming the attempts and the last cause."""
        attempts = self.options.reconnect_attempts if attempts is None else int(attempts)
        timeout = self.options.connect_timeout_s if timeout_s is None else float(timeout_s)
        if attempts < 1 or not timeout > 0:
            raise ValueError(
                f"reconnect needs attempts ≥ 1 and timeout_s > 0; got {attempts}, {timeout}"
            )
        self.close()
        last: DeviceError | None = None
        for attempt in range(attempts):
            if attempt:
                time.sleep(self.options.reconnect_backoff_s)
            try:
                self._connect(timeout)
                return
            except DeviceError as exc:
                last = exc
                log.warning(
                    "UR %s: reconnect attempt %d of %d failed: %s",
                    self.host,
                    attempt + 1,
                    attempts,
                    exc,
                )
        raise DeviceTimeout(f"UR {self.host}: reconnect failed after {attempts} attempts: {last}")

    # --- state --------------------------------------------------------------------------------
    def state(self) -> ArmState:
        """The newest controller state, stamped with the host's ``time.monotonic()``."""
        receive = self._require_connected("state")
        if not receive.isConnected():
            raise DeviceTimeout(f"UR {self.host}: RTDE connection lost")
        stamp = time.monotonic()
        timestamp = receive.getTimestamp()
        if timestamp != self._last_timestamp:
            self._last_timestamp, self._fresh_at = timestamp, stamp
        elif stamp - self._fresh_at > self.options.state_timeout_s:
            raise DeviceTimeout(
                f"UR {self.host}: no new state for {(stamp - self._fresh_at) * 1e3:.0f} ms "
                "(controller stalled or link lost)"
            )
        pose = receive.getActualTCPPose()
        speed = receive.getActualTCPSpeed()
        q = receive.getActualQ()
        wrench = receive.getActualTCPForce()
        # flags last, so a stop that arrives while the rest is read is not missed
        protective, emergency, fault = self._flags(receive)
        return ArmState(
            stamp=stamp,
            q=np.array(q),
            X_BE=Pose.unchecked(exp_so3(np.array(pose[3:])), np.array(pose[:3])),
            V_BE=np.array(speed),
            protective_stop=protective,
            emergency_stop=emergency,
            fault=fault,
            wrench_B=np.array(wrench),
        )

    def controller_modes(self) -> dict[str, str]:
        """The controller's safety mode, robot mode and program runtime state, by name (what
        ``satgrasp check-rig`` reports)."""
        receive = self._require_connected("controller_modes")
        return {
            "safety mode": name_of(SafetyMode, receive.getSafetyMode()),
            "robot mode": name_of(RobotMode, receive.getRobotMode()),
            "runtime state": name_of(RuntimeState, receive.getRuntimeState()),
        }

    def _flags(self, receive) -> tuple[bool, bool, str | None]:
        # Each getter reads the latest package, and one may arrive between two reads. A stop
        # changes the safety mode and pauses the program in the same package: read the program
        # and robot modes first and the safety flags last, so that a stop straddling the reads
        # is read as the stop, not as a program that stopped for no reason (the emulated
        # protective stop was once logged "control script not running").
        robot_mode = receive.getRobotMode()
        runtime = receive.getRuntimeState()
        safety = receive.getSafetyMode()
        protective = bool(receive.isProtectiveStopped()) or safety == SafetyMode.PROTECTIVE_STOP
        emergency = bool(receive.isEmergencyStopped()) or safety in SAFETY_EMERGENCY
        fault = None
        if not (protective or emergency) and safety not in SAFETY_MOVABLE:
            fault = f"safety mode {name_of(SafetyMode, safety)}"
        elif robot_mode != RobotMode.RUNNING:
            fault = f"robot mode {name_of(RobotMode, robot_mode)}"
        elif self._control is not None and runtime != RuntimeState.PLAYING:
            fault = (
                f"control script not running (runtime state {name_of(RuntimeState, runtime)}: "
                "watchdog, stopScript or a stop on the controller)"
            )
        return protective, emergency, fault

    # --- commands -------------------------------------------------------------------------------
    def servo(self, command: ServoCommand) -> None:
        """Stream ``command``'s twist with speedL, or stop (speedStop) when it is a stop."""
        if not isinstance(command, ServoCommand):
            raise TypeError(f"URArm.servo expects a ServoCommand; got {type(command).__name__}")
        control = self._require_active("servo")
        self._refuse_if_faulted("servo", control)
        if not self._watchdog_armed:
            self._arm_watchdog(control)
        if command.stop:
            self._stop(control, self.options.stop_deceleration)
            return
        acceleration = command.acceleration or self.options.speed_acceleration
        accepted = control.speedL(
            [float(v) for v in command.V_BE], acceleration, command.duration_s
        )
        self._stopped = False
        if not accepted:
            raise self._refusal("speedL")

    def stop(self, deceleration: float = 2.0) -> None:
        """Decelerate to rest at ``deceleration`` (m/s²); returns at once (``state()`` shows
        the arm at rest when it is). A no-op while inactive or once the controller stopped the
        control script (nothing of ours moves the arm then) and during a protective or
        emergency stop (the controller holds the arm already)."""
        if not (math.isfinite(deceleration) and deceleration > 0):
            raise ValueError(f"URArm.stop: deceleration must be positive; got {deceleration}")
        control = self._control
        if control is None:
            return
        if not (self._receive.isConnected() and control.isConnected()):
            raise DeviceTimeout(f"UR {self.host}: stop: RTDE connection lost")
        protective, emergency, _ = self._flags(self._receive)
        playing = self._receive.getRuntimeState() == RuntimeState.PLAYING
        if playing and not (protective or emergency):
            self._stop(control, deceleration)

    def unlock_protective_stop(self) -> None:
        """Ask the controller (dashboard) to release a protective stop. UR refuses within 5 s
        of the stop; inspect its cause first. ``activate()`` again afterwards."""
        dashboard = self._dashboard
        if dashboard is None:
            raise DeviceError(f"UR {self.host}: not connected (call connect())")
        try:
            self._bounded(
                "unlock protective stop", dashboard.unlockProtectiveStop, control_call=False
            )
        except DeviceError as exc:
            raise DeviceFault(
                f"UR {self.host}: unlocking the protective stop was refused: {exc}"
            ) from None

    def _arm_watchdog(self, control) -> None:
        """From the first streamed command on, the controller stops the script when commands
        stop coming at ``watchdog_min_frequency_hz``."""
        frequency = self.options.watchdog_min_frequency_hz
        if frequency > 0 and not self._bounded("setWatchdog", control.setWatchdog, frequency):
            raise DeviceError(f"UR {self.host}: setWatchdog({frequency:g} Hz) was refused")
        self._watchdog_armed = True

    def _stop(self, control, deceleration: float) -> None:
        """A zero twist reached at ``deceleration``, without waiting (module docstring)."""
        accepted = control.speedL([0.0] * 6, deceleration, 0.0)
        self._stopped = True
        if not accepted:
            raise self._refusal("speedL (stop)")

    # --- internals ------------------------------------------------------------------------------
    def _connect(self, timeout_s: float) -> None:
        probe_rtde(self.host, timeout_s=timeout_s)
        dashboard = dashboard_client.DashboardClient(self.host)
        try:
            dashboard.connect(max(int(timeout_s * 1000), 1))
            self.polyscope_version = dashboard.polyscopeVersion()
        except RuntimeError as exc:
            with contextlib.suppress(RuntimeError):
                dashboard.disconnect()
            raise DeviceTimeout(f"UR {self.host}: the dashboard did not answer: {exc}") from None
        try:
            receive = rtde_receive.RTDEReceiveInterface(
                self.host,
                self._frequency(),
                list(RECEIVE_VARIABLES),
                False,
                self.options.upper_range_registers,
            )
        except RuntimeError as exc:
            dashboard.disconnect()
            raise DeviceError(
                f"UR {self.host}: the RTDE state stream did not start: {exc}"
            ) from None
        self._receive, self._dashboard = receive, dashboard
        self._last_timestamp, self._fresh_at = None, time.monotonic()

    def _frequency(self) -> float:
        return (
            -1.0 if self.options.receive_frequency_hz is None else self.options.receive_frequency_hz
        )

    def _check_remote_control(self) -> None:
        if self.host in _LOCAL_HOSTS or self._dashboard is None:
            return
        try:
            remote = self._bounded(
                "is in remote control", self._dashboard.isInRemoteControl, control_call=False
            )
        except DeviceError:
            return  # PolyScope before 5.6 cannot say; ur-rtde then does not check either
        if not remote:
            raise DeviceError(
                f"UR {self.host}: the robot is in local control; enable remote control on the teach "
                "pendant (Settings → System → Remote Control, then the pendant's mode switch)"
            )

    def _require_connected(self, call: str):
        if self._receive is None:
            raise DeviceError(f"UR {self.host}: {call} refused: not connected (call connect())")
        return self._receive

    def _require_active(self, call: str):
        self._require_connected(call)
        if self._control is None:
            raise DeviceError(
                f"UR {self.host}: {call} refused: the arm is not active (call activate())"
            )
        if self._busy is not None:
            if self._busy.is_alive():
                raise DeviceTimeout(
                    f"UR {self.host}: {call} refused: an earlier control call has not returned"
                )
            self._busy = None
        return self._control

    def _refuse_if_faulted(self, call: str, control) -> None:
        receive = self._receive
        # ur-rtde reconnects by itself inside a command sent over a lost link: never let it
        if not (receive.isConnected() and control.isConnected()):
            raise DeviceTimeout(f"UR {self.host}: {call}: RTDE connection lost")
        protective, emergency, fault = self._flags(receive)
        reason = "emergency stop" if emergency else "protective stop" if protective else fault
        if reason is not None:
            raise DeviceFault(f"UR {self.host}: {call} refused: {reason}")

    def _refusal(self, call: str) -> DeviceError:
        """Why the controller refused ``call``, from the flags it publishes."""
        receive = self._receive
        if receive is None or not receive.isConnected():
            return DeviceTimeout(f"UR {self.host}: {call} failed: RTDE connection lost")
        protective, emergency, fault = self._flags(receive)
        reason = "emergency stop" if emergency else "protective stop" if protective else fault
        if reason is not None:
            return DeviceFault(f"UR {self.host}: {call} refused: {reason}")
        return DeviceError(f"UR {self.host}: {call} was refused by the control script")

    def _bounded(self, what: str, call: Callable, *args, control_call: bool = True):
        """``call(*args)`` in a helper thread, waited for at most ``command_timeout_s``."""
        result: dict[str, Any] = {}

        def run() -> None:
            try:
                result["value"] = call(*args)
            except Exception as exc:  # reported to the caller below
                result["error"] = exc

        thread = threading.Thread(target=run, name=f"ur-{what}", daemon=True)
        thread.start()
        thread.join(self.options.command_timeout_s)
        if thread.is_alive():
            if control_call:
                self._busy = thread
            raise DeviceTimeout(
                f"UR {self.host}: {what} did not return within {self.options.command_timeout_s:g} s"
            )
        if "error" in result:
            raise DeviceError(f"UR {self.host}: {what} failed: {result['error']}")
        return result.get("value")

    def _end_control(self):
        """Stop the arm and end the script (skipped over a lost link: ur-rtde would try to
        reconnect inside the call, and the controller's watchdog stops the script anyway);
        returns the detached control interface, or None when there is none to disconnect
        (a call that outlived its time-out still holds it; it is dropped when that returns)."""
        control, self._control = self._control, None
        moving, self._stopped = not self._stopped, True
        if control is None or (self._busy is not None and self._busy.is_alive()):
            return None
        self._busy = None
        if control.isConnected():
            if moving:
                with contextlib.suppress(DeviceError):
                    self._bounded("speedStop", control.speedStop, self.options.stop_deceleration)
            if self._busy is None:
                with contextlib.suppress(DeviceError):
                    self._bounded("stopScript", control.stopScript)
        return None if self._busy is not None else control

    def _disconnect(self, *interfaces) -> None:
        """Disconnect ur-rtde interfaces in parallel within ``command_timeout_s`` (each sleeps
        0.5 s in ``disconnect()``); their destructors then run here, 0.5 s each, holding the GIL."""
        threads = [
            threading.Thread(target=interface.disconnect, name="ur-disconnect", daemon=True)
            for interface in interfaces
            if interface is not None
        ]
        for thread in threads:
            thread.start()
        deadline = time.monotonic() + self.options.command_timeout_s
        for thread in threads:
            thread.join(max(deadline - time.monotonic(), 0.0))
        stuck = sum(thread.is_alive() for thread in threads)
        if stuck:
            log.warning(
                "UR %s: %d disconnect(s) still running after %g s",
                self.host,
                stuck,
                self.options.command_timeout_s,
            )
