"""The emulated UR controller: the arm model, the program, safety and the RTDE registers.

One ``cycle()`` is one 2 ms controller period, called by the server on the wall clock: the RTDE
watchdog is checked, the running program (the register-protocol interpreter) takes one step,
the motion in force becomes a twist for ``SimArm`` — the same kinematics, limits and
singularity handling as the simulated arm, so ``actual_q`` and the TCP pose always agree — and
the arm advances one period. When nothing commands motion and the arm is at rest the model is
not stepped (it would not move; this keeps an idle emulator nearly free of CPU).

The TCP offset is zero unless a test sets one: the TCP is then ``tool0`` (E), so
``actual_TCP_pose`` is X_BE and ``actual_TCP_speed`` is V_BE = [v, ω] in B. UR poses are
[x, y, z, rx, ry, rz] with an axis-angle rotation; they are converted here and in the driver.

Modes and states are UR's enumerations (``drivers.ur_states``): robot mode, safety mode,
runtime state, and the safety-status bits ur-rtde's ``isProtectiveStopped`` /
``isEmergencyStopped`` test.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Protocol

import numpy as np

from configuration.rig import ArmConfig
from drivers.base import DeviceError, ServoCommand
from drivers.ur_states import (
    SAFETY_BIT_EMERGENCY_STOPPED,
    SAFETY_BIT_NORMAL,
    SAFETY_BIT_PROTECTIVE_STOPPED,
    SAFETY_BIT_ROBOT_EMERGENCY_STOPPED,
    SAFETY_BIT_STOPPED_DUE_TO_SAFETY,
    SAFETY_EMERGENCY,
    STATUS_BIT_POWER_ON,
    STATUS_BIT_PROGRAM_RUNNING,
    RobotMode,
    RuntimeState,
    SafetyMode,
)
from estimators.geometry import Pose
from estimators.so3 import log_so3
from sim_backends.arm import SimArm
from sim_backends.ur_emulator.command_log import CommandLog, command_name
from sim_backends.ur_emulator.motion import LinearMove, pose_error_matrix, servo_twist
from sim_backends.ur_emulator.rtde_variables import REGISTER_COUNT

#: Ramp (m/s², rad/s²) of the twists that servoL and moveL become: high, so the joint
#: acceleration limit of the arm model is what bounds them, as on the controller.
POSITION_COMMAND_RAMP = 20.0
#: A move counts as arrived within these of its goal.
ARRIVED_M = 2e-5
ARRIVED_RAD = 1e-4
#: A moveL that has not arrived this long after its profile ended gives up.
MOVE_GRACE_S = 2.0


class Program(Protocol):
    """A running program: one step per controller period."""

    name: str
    #: Which input int register carries its commands (None: it reads none).
    command_register: int | None

    def cycle(self) -> None: ...

    def abort(self) -> None:
        """The controller stopped the program (stop, protective stop, watchdog)."""
        ...


class Operation:
    """A motion the program waits for (a blocking moveL, a stop); ``done`` once finished."""

    def __init__(self, name: str):
        self.name = name
        self.done = False
        self.detail = ""

    def finish(self, detail: str = "") -> None:
        self.done = True
        self.detail = detail


class EmulatedController:
    """A UR controller around a ``SimArm`` (see the module docstring).

    ``clock`` is the host clock used for time stamps and the RTDE watchdog (time.monotonic);
    the controller's own ``timestamp`` (RTDE ``timestamp``) counts periods since start-up.

    ``arm``: drive this simulated arm instead of one of its own — the arm of a simulated world
    that also carries the camera and the track (``sim_backends.emulated_world``); the world then
    owns the time and runs the controller with ``advance`` (``clock`` is then the world's).
    """

    def __init__(
        self,
        arm_config: ArmConfig,
        log: CommandLog,
        *,
        arm: SimArm | None = None,
        unlock_delay_s: float = 5.0,
        clock: Callable[[], float] = time.monotonic,
    ):
        self.arm = arm if arm is not None else SimArm(arm_config)
        arm_config = self.arm.config
        self.arm.connect()
        self.arm.activate()
        self.model = self.arm.model
        self.log = log
        self.period_s = 1.0 / arm_config.control_rate_hz
        self._pending_s = 0.0
        self.stop_deceleration = arm_config.stop_deceleration
        self.unlock_delay_s = unlock_delay_s
        self._clock = clock
        # RTDE registers
        self.input_int = [0] * REGISTER_COUNT
        self.input_double = [0.0] * REGISTER_COUNT
        self.input_bits = 0
        self.output_int = [0] * REGISTER_COUNT
        self.output_double = [0.0] * REGISTER_COUNT
        self.output_bits = 0
        self.other_inputs: dict[str, object] = {}
        # controller state
        self.timestamp = 0.0
        self.robot_mode = RobotMode.RUNNING
        self.safety_mode = SafetyMode.NORMAL
        self.runtime_state = RuntimeState.STOPPED
        self.program: Program | None = None
        self.tcp_force = (0.0,) * 6
        self._T_EP = np.eye(4)  # TCP offset: pose of the TCP P in the flange frame E
        self.protective_stop_at: float | None = None
        #: Events ("protective stop", "emergency stop", "watchdog") waiting for the first data
        #: package that shows them; the server stamps them into ``published`` (latest wins).
        self.unpublished_events: list[str] = []
        self.published: dict[str, float] = {}
        self._watchdog: tuple[str, float] | None = None  # (input variable, min frequency)
        self._watchdog_last = 0.0
        self.watchdog_tripped = False
        # motion
        self._mode = "idle"  # idle | speed | servo | move | stopping
        self._V = np.zeros(6)
        self._acceleration: float | None = None
        self._servo_target: np.ndarray | None = None  # T_BE of the servoL target
        self._servo_time_constant = 0.1
        self._move: LinearMove | None = None
        self._move_elapsed = 0.0
        self._operation: Operation | None = None
        self._refresh_outputs()
        #: (command id, host stamp) written to the program's command register and not yet read
        self._unread_command: tuple[int, float] | None = None

    def now(self) -> float:
        """The host clock (time.monotonic) the controller stamps events with."""
        return self._clock()

    # --- outputs ------------------------------------------------------------------------------
    @property
    def safety_status_bits(self) -> int:
        if self.safety_mode == SafetyMode.PROTECTIVE_STOP:
            return SAFETY_BIT_PROTECTIVE_STOPPED | SAFETY_BIT_STOPPED_DUE_TO_SAFETY
        if self.safety_mode in SAFETY_EMERGENCY:
            return (
                SAFETY_BIT_ROBOT_EMERGENCY_STOPPED
                | SAFETY_BIT_EMERGENCY_STOPPED
                | SAFETY_BIT_STOPPED_DUE_TO_SAFETY
            )
        return SAFETY_BIT_NORMAL

    @property
    def robot_status_bits(self) -> int:
        bits = 0
        if self.robot_mode in (RobotMode.POWER_ON, RobotMode.IDLE, RobotMode.RUNNING):
            bits |= STATUS_BIT_POWER_ON
        if self.runtime_state == RuntimeState.PLAYING:
            bits |= STATUS_BIT_PROGRAM_RUNNING
        return bits

    @property
    def X_BE(self) -> Pose:
        return Pose.from_matrix(self._T_BE)

    @property
    def moving(self) -> bool:
        return self._mode != "idle" or bool(np.any(self._V_BE))

    def _refresh_outputs(self) -> None:
        # matrices, not Poses: this runs every period while the arm moves
        self._T_BE = self.arm.T_BE
        self._V_BE = self.arm.V_BE
        self.q = tuple(self.arm.q.tolist())
        self.qd = tuple(self.arm.qd.tolist())
        # the TCP P = E unless a TCP offset was set (then P's pose and its point's velocity)
        T_BP = self._T_BE @ self._T_EP
        v_P = self._V_BE[:3] + np.cross(self._V_BE[3:], T_BP[:3, 3] - self._T_BE[:3, 3])
        self.tcp_pose = tuple(T_BP[:3, 3].tolist() + log_so3(T_BP[:3, :3]).tolist())
        self.tcp_speed = tuple(v_P.tolist() + self._V_BE[3:].tolist())

    # --- the controller period ----------------------------------------------------------------
    def cycle(self) -> None:
        """One controller period: watchdog, program step, motion, arm step."""
        now = self._clock()
        self.timestamp += self.period_s
        self._check_watchdog(now)
        if self.runtime_state == RuntimeState.PLAYING and self.program is not None:
            self.program.cycle()
        self._drive_arm()
        if self._mode == "idle" and not np.any(self._V_BE):
            return  # at rest and nothing commanded: the model would not move
        self.arm.step(self.period_s)
        self._refresh_outputs()

    def advance(self, dt: float) -> None:
        """Run the controller periods that fit in ``dt`` seconds (the rest carries over): for a
        world that owns the time and steps this controller with its other devices."""
        self._pending_s += dt
        while self._pending_s >= self.period_s - 1e-12:
            self._pending_s -= self.period_s
            self.cycle()

    def _drive_arm(self) -> None:
        if self.halted:
            self._mode = "idle"
            return
        mode = self._mode
        try:
            if mode == "speed":
                self.arm.servo(
                    ServoCommand(self.timestamp, self._V, acceleration=self._acceleration)
                )
            elif mode == "servo" and self._servo_target is not None:
                V = servo_twist(self._T_BE, self._servo_target, self._servo_time_constant)
                self.arm.servo(ServoCommand(self.timestamp, V, acceleration=POSITION_COMMAND_RAMP))
            elif mode == "move" and self._move is not None:
                self._drive_move()
            elif mode == "stopping" and not np.any(self._V_BE):
                self._mode = "idle"
                self._finish_operation("at rest")
        except DeviceError as exc:  # the model refused (a latched fault): stop commanding
            self.log.add(self._clock(), "safety", "arm model refused", detail=str(exc))
            self._mode = "idle"
            self._finish_operation(str(exc))

    def _drive_move(self) -> None:
        move = self._move
        self._move_elapsed += self.period_s
        error = pose_error_matrix(self._T_BE, move.T_goal)
        arrived = np.linalg.norm(error[:3]) < ARRIVED_M and np.linalg.norm(error[3:]) < ARRIVED_RAD
        if self._move_elapsed >= move.duration and arrived:
            self._begin_stop(self.stop_deceleration * 10.0)  # residual speed: a few µm/s
            return
        if self._move_elapsed > move.duration + MOVE_GRACE_S:
            self.log.add(self._clock(), "script", "moveL gave up", detail="goal not reached")
            self._begin_stop(self.stop_deceleration)
            return
        V = move.twist(self._T_BE, self._move_elapsed)
        self.arm.servo(ServoCommand(self.timestamp, V, acceleration=POSITION_COMMAND_RAMP))

    # --- motion commands (from the program) ---------------------------------------------------
    def speed(self, V_BE: np.ndarray, acceleration: float) -> None:
        """speedL: keep the twist until another command, a stop or the end of the program."""
        self._cancel_operation("superseded by speedL")
        self._V = np.array(V_BE, dtype=float)
        self._acceleration = acceleration if acceleration > 0 else None
        self._mode = "speed"

    def servo_to(self, X_BE_target: Pose, time_constant_s: float) -> None:
        """servoL: track ``X_BE_target`` (see ``motion.servo_twist``)."""
        self._cancel_operation("superseded by servoL")
        self._servo_target = X_BE_target.matrix
        self._servo_time_constant = time_constant_s
        self._mode = "servo"

    def move_linear(self, X_BE_goal: Pose, speed: float, acceleration: float) -> Operation:
        """moveL: the returned operation is done when the flange rests at the goal."""
        self._cancel_operation("superseded by moveL")
        self._move = LinearMove(self._T_BE, X_BE_goal.matrix, speed, acceleration)
        self._move_elapsed = 0.0
        self._mode = "move"
        self._operation = Operation("moveL")
        return self._operation

    def stop_motion(self, deceleration: float) -> Operation:
        """speedStop / servoStop / stopL: the returned operation is done at rest."""
        self._cancel_operation("superseded by a stop")
        operation = Operation("stop")
        self._operation = operation
        if self.halted or (self._mode == "idle" and not np.any(self._V_BE)):
            operation.finish("at rest")
            return operation
        self._begin_stop(deceleration)
        return operation

    def _begin_stop(self, deceleration: float) -> None:
        self.arm.stop(max(deceleration, 1e-3))
        self._mode = "stopping"

    def _finish_operation(self, detail: str) -> None:
        if self._operation is not None:
            self._operation.finish(detail)
            self._operation = None

    def _cancel_operation(self, detail: str) -> None:
        self._finish_operation(detail)
        self._move = None

    @property
    def halted(self) -> bool:
        return self.safety_mode != SafetyMode.NORMAL or self.robot_mode != RobotMode.RUNNING

    # --- program ----------------------------------------------------------------------------------
    def start_program(self, program: Program) -> bool:
        """Run ``program`` (replacing any other). False when the robot cannot run programs."""
        now = self._clock()
        if self.program is not None:
            self.stop_program(f"replaced by program {program.name!r}")
        if self.halted:
            self.log.add(now, "program", f"refused {program.name}", detail=self.why_halted())
            return False
        self.program = program
        self.runtime_state = RuntimeState.PLAYING
        self.watchdog_tripped = False
        self.log.add(now, "program", f"started {program.name}")
        return True

    def stop_program(self, reason: str) -> None:
        """End the program; the arm decelerates to rest (UR's stop on program end)."""
        now = self._clock()
        program, self.program = self.program, None
        was = self.runtime_state
        self.runtime_state = RuntimeState.STOPPED
        self._watchdog = None
        self._unread_command = None
        if program is not None:
            program.abort()
            self.log.add(now, "program", f"stopped {program.name}", detail=reason)
        elif was != RuntimeState.STOPPED:
            self.log.add(now, "program", "stopped", detail=reason)
        self._cancel_operation(reason)
        if not self.halted and self.moving:
            self._begin_stop(self.stop_deceleration)

    def pause_program(self, reason: str) -> None:
        if self.runtime_state == RuntimeState.PLAYING:
            self.runtime_state = RuntimeState.PAUSED
            self.log.add(self._clock(), "program", "paused", detail=reason)
        self._cancel_operation(reason)
        if not self.halted and self.moving:
            self._begin_stop(self.stop_deceleration)

    def resume_program(self) -> bool:
        if self.runtime_state != RuntimeState.PAUSED or self.program is None or self.halted:
            return False
        self.runtime_state = RuntimeState.PLAYING
        self.log.add(self._clock(), "program", "resumed")
        return True

    # --- RTDE inputs and the watchdog -------------------------------------------------------
    def write_inputs(self, names: list[str], values: list) -> None:
        """Apply a data package from a client (names and values of its input recipe)."""
        now = self._clock()
        command_register = None if self.program is None else self.program.command_register
        for name, value in zip(names, values, strict=True):
            if name.startswith("input_int_register_"):
                index = int(name.rsplit("_", 1)[1])
                if index == command_register:
                    self._note_command(int(value), now)
                self.input_int[index] = int(value)
            elif name.startswith("input_double_register_"):
                self.input_double[int(name.rsplit("_", 1)[1])] = float(value)
            elif name.startswith("input_bit_register_"):
                bit = int(name.rsplit("_", 1)[1])
                self.input_bits = (self.input_bits & ~(1 << bit)) | (int(bool(value)) << bit)
            elif name == "input_bit_registers0_to_31":
                self.input_bits = (self.input_bits & ~0xFFFFFFFF) | int(value)
            elif name == "input_bit_registers32_to_63":
                self.input_bits = (self.input_bits & ~(0xFFFFFFFF << 32)) | (int(value) << 32)
            else:
                self.other_inputs[name] = value
        if self._watchdog is not None and self._watchdog[0] in names:
            self._watchdog_last = now

    def _note_command(self, command: int, now: float) -> None:
        unread = self._unread_command
        if unread is not None and unread[0] not in (0, command):
            self.log.add(
                unread[1],
                "lost",
                command_name(unread[0]),
                detail=f"overwritten by {command_name(command)} before the script read it",
            )
        self._unread_command = (command, now)

    def read_command(self, register: int) -> tuple[int, bool]:
        """The program reads its command register: (command id, whether a data package wrote
        it since the last read)."""
        fresh = self._unread_command is not None
        self._unread_command = None
        return self.input_int[register], fresh

    def set_watchdog(self, variable: str, min_frequency_hz: float) -> None:
        """rtde_set_watchdog(variable, f, "stop"): stop the program when ``variable`` gets no
        update for 1/f seconds."""
        if not min_frequency_hz > 0:
            self._watchdog = None
            return
        self._watchdog = (variable, float(min_frequency_hz))
        self._watchdog_last = self._clock()

    @property
    def watchdog(self) -> tuple[str, float] | None:
        return self._watchdog

    def _check_watchdog(self, now: float) -> None:
        if self._watchdog is None or self.runtime_state != RuntimeState.PLAYING:
            return
        variable, frequency = self._watchdog
        silent = now - self._watchdog_last
        if silent > 1.0 / frequency:
            self.watchdog_tripped = True
            detail = f"no update of {variable} for {silent * 1e3:.0f} ms (minimum {frequency:g} Hz)"
            self.log.add(now, "safety", "RTDE watchdog", detail=detail)
            self.stop_program(f"RTDE watchdog: {detail}")
            self.unpublished_events.append("watchdog")

    # --- safety -------------------------------------------------------------------------------
    def protective_stop(self, source: str, *, program_keeps_running: bool = False) -> None:
        """Stop the joints at the next period; pause the program unless told otherwise (some
        controllers keep reporting the program as running for a while — the case where
        ur-rtde's stream calls still return True)."""
        now = self._clock()
        if self.safety_mode == SafetyMode.PROTECTIVE_STOP:
            return
        self.arm.inject_protective_stop()
        self.safety_mode = SafetyMode.PROTECTIVE_STOP
        self.protective_stop_at = now
        self._mode = "idle"
        self._cancel_operation("protective stop")
        if not program_keeps_running and self.runtime_state == RuntimeState.PLAYING:
            self.runtime_state = RuntimeState.PAUSED
        self.log.add(now, "safety", "protective stop", detail=source)
        self.unpublished_events.append("protective stop")
        self._refresh_outputs()

    def unlock_protective_stop(self) -> str:
        """The dashboard's reply to ``unlock protective stop``."""
        now = self._clock()
        if self.safety_mode != SafetyMode.PROTECTIVE_STOP:
            return "Protective stop releasing"  # what a controller answers when not stopped
        held = now - (self.protective_stop_at or now)
        if held < self.unlock_delay_s:
            return (
                f"Cannot unlock protective stop until {self.unlock_delay_s:g}s after occurrence. "
                "Always inspect cause of protective stop before unlocking"
            )
        self.arm.unlock_protective_stop()
        self.safety_mode = SafetyMode.NORMAL
        self.log.add(now, "safety", "protective stop unlocked")
        return "Protective stop releasing"

    def emergency_stop(self) -> None:
        now = self._clock()
        self.arm.inject_emergency_stop()
        self.safety_mode = SafetyMode.ROBOT_EMERGENCY_STOP
        self._mode = "idle"
        self.stop_program("emergency stop")
        self.log.add(now, "safety", "emergency stop")
        self.unpublished_events.append("emergency stop")
        self._refresh_outputs()

    def release_emergency_stop(self) -> None:
        """The e-stop button released: power is off until ``power on`` and ``brake release``."""
        if self.safety_mode not in SAFETY_EMERGENCY:
            return
        self.arm.release_emergency_stop()
        self.safety_mode = SafetyMode.NORMAL
        self.robot_mode = RobotMode.POWER_OFF
        self.log.add(self._clock(), "safety", "emergency stop released")

    def power_on(self) -> None:
        if self.robot_mode == RobotMode.POWER_OFF:
            self.robot_mode = RobotMode.IDLE

    def power_off(self) -> None:
        self.stop_program("power off")
        self.robot_mode = RobotMode.POWER_OFF

    def brake_release(self) -> None:
        if self.robot_mode in (RobotMode.POWER_ON, RobotMode.IDLE):
            self.robot_mode = RobotMode.RUNNING

    def why_halted(self) -> str:
        if self.safety_mode != SafetyMode.NORMAL:
            return f"safety mode {self.safety_mode.name}"
        if self.robot_mode != RobotMode.RUNNING:
            return f"robot mode {self.robot_mode.name}"
        return ""

    # --- set-up ------------------------------------------------------------------------------
    def set_joint_positions(self, q: np.ndarray) -> None:
        """Place the arm at rest at ``q`` (rad): test set-up, not a motion."""
        if self.moving:
            raise ValueError("set_joint_positions needs the arm at rest")
        self.arm.set_joint_positions(q)
        self._refresh_outputs()

    @property
    def tcp_offset(self) -> tuple[float, ...]:
        """The TCP offset as UR reports it: [x, y, z, rx, ry, rz] of the TCP in the flange."""
        return tuple(self._T_EP[:3, 3].tolist() + log_so3(self._T_EP[:3, :3]).tolist())

    def set_tcp_offset(self, offset: np.ndarray) -> None:
        """Set the TCP offset (UR's set_tcp): TCP pose and speed then refer to that point."""
        X_EP = Pose.from_rotvec(
            np.asarray(offset[3:], dtype=float), np.asarray(offset[:3], dtype=float)
        )
        self._T_EP = X_EP.matrix
        self._refresh_outputs()

    def set_tcp_force(self, wrench_B: np.ndarray) -> None:
        wrench = np.asarray(wrench_B, dtype=float)
        if wrench.shape != (6,) or not np.all(np.isfinite(wrench)):
            raise ValueError(f"a wrench is 6 finite values [f (N), τ (N·m)]; got {wrench_B}")
        self.tcp_force = tuple(float(v) for v in wrench)
