"""A simulated Robotiq 2F-85-style gripper, answering the register map of
``drivers.gripper_robotiq`` and moving only when the world loop calls ``step(dt)``.

Behaviour modelled after the 2F-85 manual: rACT 0 resets (clears every fault); rACT 1 starts an
activation that takes ``activation_s`` (gSTA 1, then 3); a write with rGTO 1 starts a move to
rPR at a speed set by rSP (linear between ``min_speed`` and ``max_speed``, in opening change
per second) — before activation that is fault 0x07, during activation fault 0x05 (the move then
starts when activation completes). An object of ``object_width`` centred between the fingers
stops a closing move where the opening equals its width: gOBJ 2, current from rFR. A move that
reaches rPR reports gOBJ 3. Major faults (``inject_fault``) stop the fingers until a reset and
re-activation.

Simplification: positions 0…255 map linearly onto the stroke (255 = fingers touching); the real
2F-85 stops at its software limits a few counts short of both ends.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Sequence

from configuration.rig import GripperConfig
from drivers.gripper_robotiq import RobotiqRegisters
from sim_backends.modbus_server import READ_HOLDING, READ_INPUT, RegisterAccessError

RQ = RobotiqRegisters
_MINOR_FAULTS = (0x05, 0x07)
_FULL_CURRENT_COUNTS = 80  # gCU at rFR = 255 while squeezing (≈ 0.8 A)


class GripperModel:
    """Simulated 2-finger gripper; thread-safe, stepped by ``step(dt)``."""

    def __init__(self, config: GripperConfig, *, control_rate_hz: float = 500.0):
        self.config = config
        self._lock = threading.Lock()
        self.control_rate_hz = control_rate_hz
        self._period = 1.0 / control_rate_hz
        self._pending = 0.0
        self._time = 0.0
        self._commands = [0, 0, 0]
        self._sta = RQ.STA_RESET
        self._activation_left = 0.0
        self._position = 0.0  # counts, 0 open … 255 closed
        self._target: float | None = None  # counts, while a move runs
        self._go = False  # gGTO
        self._obj = RQ.OBJ_MOVING
        self._fault = 0
        self._delayed_move = False
        self._current = 0
        self._object_width = config.object_width

    # --- world-loop API -------------------------------------------------------------------
    @property
    def time(self) -> float:
        with self._lock:
            return self._time + self._pending

    @property
    def opening(self) -> float:
        """Distance between the fingers (m)."""
        with self._lock:
            return self._opening(self._position)

    def set_object(self, width: float | None) -> None:
        """Put an object of ``width`` (m) between the fingers, or remove it (None)."""
        if width is not None and not 0 < width < self.config.stroke:
            raise ValueError(f"object width {width} m must be in (0, {self.config.stroke}) m")
        with self._lock:
            self._object_width = width
            holding = self._obj == RQ.OBJ_CONTACT_CLOSING and self._target is None
            if holding and (width is None or width < self._opening(self._position) - 1e-9):
                # the object slipped out or shrank: the fingers keep closing toward rPR
                self._target = float(self._commands[1] & 0xFF)
                self._obj = RQ.OBJ_MOVING
                self._current = 0

    def inject_fault(self, code: int = 0x0E) -> None:
        """Fault injection: a major fault (default 0x0E overcurrent) stops the fingers."""
        if code < 0x08 or code > 0xFF:
            raise ValueError(f"inject a major fault code (0x08…0xFF); got 0x{code:02x}")
        with self._lock:
            self._fault = code
            self._target = None

    def step(self, dt: float) -> None:
        if not (math.isfinite(dt) and dt >= 0):
            raise ValueError(f"GripperModel.step: dt must be finite and ≥ 0; got {dt}")
        with self._lock:
            self._pending += dt
            while self._pending >= self._period - 1e-12:
                self._pending -= self._period
                self._cycle(self._period)

    # --- RegisterDevice -------------------------------------------------------------------
    def register_blocks(self) -> list[tuple[int, int]]:
        return [(RQ.OUTPUT, RQ.COUNT), (RQ.INPUT, RQ.COUNT)]

    def read_registers(self, function_code: int, address: int, count: int) -> list[int]:
        if function_code not in (READ_HOLDING, READ_INPUT):
            raise RegisterAccessError(1, f"function code {function_code} cannot read")
        with self._lock:
            image = {RQ.OUTPUT + i: v for i, v in enumerate(self._commands)}
            image.update({RQ.INPUT + i: v for i, v in enumerate(self._status_registers())})
        try:
            return [image[a] for a in range(address, address + count)]
        except KeyError:
            raise RegisterAccessError(2, f"registers {address}…{address + count - 1}") from None

    def write_registers(self, address: int, values: Sequence[int]) -> None:
        if address < RQ.OUTPUT or address + len(values) > RQ.OUTPUT + RQ.COUNT:
            raise RegisterAccessError(2, f"registers {address}… are not command registers")
        with self._lock:
            commands = list(self._commands)
            commands[address - RQ.OUTPUT : address - RQ.OUTPUT + len(values)] = [
                int(v) & 0xFFFF for v in values
            ]
            self._commands = commands
            self._apply(commands[0] >> 8)

    # --- internals ------------------------------------------------------------------------
    def _opening(self, counts: float) -> float:
        return self.config.stroke * (1.0 - counts / 255.0)

    def _counts(self, opening: float) -> float:
        return 255.0 * (1.0 - opening / self.config.stroke)

    def _apply(self, action: int) -> None:
        if not action & RQ.rACT:
            # reset: everything stops, every fault clears
            self._sta, self._go, self._target = RQ.STA_RESET, False, None
            self._obj, self._fault, self._delayed_move, self._current = RQ.OBJ_MOVING, 0, False, 0
            if action & RQ.rGTO:
                self._fault = 0x07
            return
        if self._sta == RQ.STA_RESET:
            self._sta = RQ.STA_ACTIVATING
            self._activation_left = self.config.activation_s
        if not action & RQ.rGTO:
            self._go, self._target, self._delayed_move = False, None, False
            return
        if self._fault and self._fault not in _MINOR_FAULTS:
            return  # a major fault blocks motion until reset
        if self._sta == RQ.STA_ACTIVATING:
            self._fault, self._delayed_move = 0x05, True
            return
        self._start_move()

    def _start_move(self) -> None:
        if self._fault in _MINOR_FAULTS:
            self._fault = 0
        self._delayed_move = False
        self._go = True
        self._target = float(self._commands[1] & 0xFF)
        self._obj = RQ.OBJ_MOVING
        self._current = 0

    def _cycle(self, h: float) -> None:
        cfg = self.config
        self._time += h
        if self._sta == RQ.STA_ACTIVATING:
            self._activation_left -= h
            if self._activation_left <= 0:
                self._sta = RQ.STA_ACTIVATED
                if self._delayed_move:
                    self._start_move()
            return
        if self._target is None or (self._fault and self._fault not in _MINOR_FAULTS):
            return
        speed_request = (self._commands[2] >> 8) / 255.0
        rate = (cfg.min_speed + (cfg.max_speed - cfg.min_speed) * speed_request) / cfg.stroke
        step_counts = 255.0 * rate * h
        error = self._target - self._position
        closing = error > 0
        arrives = abs(error) <= step_counts
        new_position = (
            self._target if arrives else self._position + math.copysign(step_counts, error)
        )
        width = self._object_width
        if closing and width is not None and self._opening(new_position) <= width:
            self._position = max(self._position, self._counts(width))
            self._target = None
            self._obj = RQ.OBJ_CONTACT_CLOSING
            self._current = round(_FULL_CURRENT_COUNTS * (self._commands[2] & 0xFF) / 255.0)
            return
        self._position = new_position
        if arrives:
            self._target = None
            self._obj = RQ.OBJ_AT_POSITION

    def _status_registers(self) -> list[int]:
        status = (self._sta << RQ.gSTA_SHIFT) | (self._obj << RQ.gOBJ_SHIFT)
        if self._sta != RQ.STA_RESET:
            status |= RQ.gACT
        if self._go:
            status |= RQ.gGTO
        echo = self._commands[1] & 0xFF
        position = min(255, max(0, round(self._position)))
        return [status << 8, (self._fault << 8) | echo, (position << 8) | self._current]
