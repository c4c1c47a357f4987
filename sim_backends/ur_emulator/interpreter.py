"""The register protocol of ur-rtde's control script (``rtde_control.script``), interpreted.

ur-rtde uploads a URScript program that reads a command id from ``input_int_register_<k>`` once
per controller cycle and its parameters from the double (and int) registers after it, and
answers in ``output_int_register_<k>`` (1 ready, 2 done) with return values in the output double
registers, where k is the register offset (0, or 24 with ``FLAG_UPPER_RANGE_REGISTERS``). This
class behaves like that program's main loop, one step per controller cycle:

* real-time commands (servoL, speedL, servoJ, speedJ, getStepTime) are applied and the script
  signals ready at once; the client does not wait;
* every other command runs once (``executing``), the script signals done when it has finished
  — a blocking moveL or a stop only when the arm rests — and waits for the client to write
  0 (no command) before signalling ready again;
* 255 (stopScript) ends the program.

Command ids, parameters and the async progress register follow ur-rtde 1.6.5 (its bindings'
embedded script and ``RobotCommand::Type``): 3 moveL (d0–5 pose, d6 speed, d7 acceleration, i1
async), 10 speedL (d0–5 twist, d6 acceleration, d7 time), 24 servoL (d0–5 pose, d6 speed, d7
acceleration, d8 time, d9 lookahead time, d10 gain), 11 servoJ (the same with joints), 15
speedStop and 16 servoStop (d0 deceleration), 31 protective stop, 33/34 stopL/stopJ (d0
deceleration, i1 async), 35 setWatchdog (d0 minimum frequency), 40 getTCPOffset, 26
getStepTime, 255 stopScript. Anything else is logged as unsupported and signalled done, so a
client never hangs on it.
"""

from __future__ import annotations

import re

import numpy as np

from drivers.ur_kinematics import forward_kinematics
from estimators.geometry import Pose
from sim_backends.ur_emulator.command_log import command_name
from sim_backends.ur_emulator.controller import EmulatedController, Operation

READY, DONE = 1, 2
REALTIME = frozenset({6, 9, 10, 11, 24, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71})
STOP_SCRIPT = 255
#: Operations whose async flag is input int register 1.
_ASYNC = frozenset({1, 2, 3, 4, 33, 34, 45})

# ur-rtde injects each offset right after the comment that ends the assignment's line, so the
# number opens the next line: "global reg_offset_int = # int register offset\n0    global …".
_OFFSET = {
    kind: re.compile(rf"global\s+reg_offset_{kind}\s*=\s*(?:#[^\n]*\n)?\s*(\d+)")
    for kind in ("int", "float")
}


def is_control_script(text: str) -> bool:
    """Whether a URScript program is ur-rtde's control script (it reads commands with
    ``rtde_cmd()`` and declares its register offsets)."""
    return "rtde_cmd()" in text and _OFFSET["int"].search(text) is not None


def register_offsets(text: str) -> tuple[int, int]:
    """(int offset, float offset) the uploaded script was given (0 or 24)."""
    found = {kind: pattern.search(text) for kind, pattern in _OFFSET.items()}
    return tuple(int(m.group(1)) if m else 0 for m in (found["int"], found["float"]))  # type: ignore[return-value]


class ControlScript:
    """ur-rtde's control script running on the emulated controller (see the module docstring)."""

    def __init__(
        self, controller: EmulatedController, *, int_offset: int = 0, float_offset: int = 0
    ):
        self.name = "rtde_control"
        self.controller = controller
        self.command_register = int_offset
        self._int = int_offset
        self._float = float_offset
        self._executing = False
        self._blocking: Operation | None = None
        self._async: Operation | None = None
        self._async_count = 0
        self._async_id = 0
        self._write_async_progress(-1)
        self._out_int(0, READY)

    # --- registers --------------------------------------------------------------------------
    def _in_int(self, i: int) -> int:
        return self.controller.input_int[self._int + i]

    def _in_double(self, i: int) -> float:
        return self.controller.input_double[self._float + i]

    def _in_vector6(self, first: int = 0) -> np.ndarray:
        return np.array([self._in_double(first + k) for k in range(6)])

    def _out_int(self, i: int, value: int) -> None:
        self.controller.output_int[self._int + i] = int(value)

    def _out_double(self, i: int, value: float) -> None:
        self.controller.output_double[self._float + i] = float(value)

    def _write_async_progress(self, value: int) -> None:
        """output int register 2: bits 0–14 progress, 15 running, 16–22 write count,
        24–30 operation id (the script's write_async_progress_register)."""
        self._async_count = (self._async_count + 1) % 128
        if value == 0:
            self._async_id = (self._async_id + 1) % 128
        register = self._async_count * 65536 + self._async_id * 16777216
        if value >= 0:
            register += min(value, 32767) + 32768
        self._out_int(2, register)

    # --- the main loop, one controller cycle --------------------------------------------------
    def cycle(self) -> None:
        if self._async is not None and self._async.done:
            self._async = None
            self._write_async_progress(-1)
        if self._blocking is not None:
            if not self._blocking.done:
                return  # still inside process_cmd
            self._blocking = None
            self._out_int(0, DONE)
            return
        command, fresh = self.controller.read_command(self._int)
        if command in REALTIME:
            # The script re-applies a real-time command every cycle from unchanged registers;
            # doing it once per data package is the same and spares a pose conversion a cycle.
            # (One difference: after a resumed pause the script would re-apply the last one.)
            if fresh:
                self._process(command)
            self._out_int(0, READY)
        elif command == 0:
            self._executing = False
            self._out_int(0, READY)
        elif not self._executing:
            self._executing = True
            if self._process(command) and self._blocking is None:
                self._out_int(0, DONE)

    def abort(self) -> None:
        """The program was stopped: nothing is waited for any more."""
        self._blocking = None
        self._async = None

    # --- commands -----------------------------------------------------------------------------
    def _log(self, command: int, values: tuple[float, ...] = (), detail: str = "") -> None:
        c = self.controller
        c.log.add(c.now(), "script", command_name(command), tuple(map(float, values)), detail)

    def _pose(self, first: int = 0) -> Pose:
        v = self._in_vector6(first)
        return Pose.from_rotvec(v[3:], v[:3])

    def _process(self, command: int) -> bool:
        """Run one command; False for stopScript (the program ends)."""
        c = self.controller
        if command == 10:  # speedL
            twist = self._in_vector6()
            acceleration, duration = self._in_double(6), self._in_double(7)
            self._log(command, (*twist, acceleration, duration))
            c.speed(twist, acceleration)
        elif command in (24, 11):  # servoL, servoJ (joints through the flange pose)
            values = tuple(self._in_double(k) for k in range(11))
            self._log(command, values)
            target = (
                self._pose() if command == 24 else forward_kinematics(c.model, self._in_vector6())
            )
            c.servo_to(target, time_constant_s=values[9])
        elif command == 26:  # getStepTime
            self._out_double(0, c.period_s)
        elif command == 3:  # moveL
            values = (*self._in_vector6(), self._in_double(6), self._in_double(7))
            asynchronous = self._in_int(1) == 1
            self._log(command, values, "async" if asynchronous else "")
            operation = c.move_linear(self._pose(), speed=values[6], acceleration=values[7])
            self._start(operation, asynchronous)
        elif command in (15, 16, 33, 34):  # speedStop, servoStop, stopL, stopJ
            deceleration = self._in_double(0)
            asynchronous = command in _ASYNC and self._in_int(1) == 1
            self._log(command, (deceleration,), "async" if asynchronous else "")
            self._start(c.stop_motion(deceleration), asynchronous)
        elif command == 31:
            self._log(command)
            c.protective_stop("triggerProtectiveStop")
        elif command == 35:  # setWatchdog
            frequency = self._in_double(0)
            self._log(command, (frequency,))
            c.set_watchdog(f"input_int_register_{self._int}", frequency)
        elif command == 40:  # getTCPOffset
            self._log(command)
            for k, value in enumerate(c.tcp_offset):
                self._out_double(k, value)
        elif command == STOP_SCRIPT:
            self._log(command)
            c.stop_program("stopScript")
            return False
        else:
            self._log(command, detail="not emulated: ignored and signalled done")
        return True

    def _start(self, operation: Operation, asynchronous: bool) -> None:
        if asynchronous:
            self._async = operation
            self._write_async_progress(0)
        elif not operation.done:
            self._blocking = operation
