"""The linear track carrying the mock-up, as a simulated axis controller.

``TrackModel`` is the device behind the register map of ``drivers.track_modbus``
(``docs/track_modbus.md``): it answers register reads and writes (``RegisterDevice``, so it can
be served over Modbus TCP by ``sim_backends.modbus_server`` or reached in-process by
``DirectLink``) and moves only when the world loop calls ``step(dt)``.

Motion: velocity mode ramps to the set velocity at the maximum acceleration; position mode
follows a trapezoidal profile (v_des = min(speed, braking speed that stops on the target),
speed changes limited to a·h per cycle) and snaps onto the target once within tolerance at crawl
speed. Soft limits: crossing one while moving outward latches its fault bit and brakes at the
maximum acceleration (the carriage overshoots by v²/2a, like a real axis' software limit
switch); a position target beyond them is refused (exception 3). A latched fault, a cleared
enable bit or a silent host (no request within ``watchdog_s``) stops the axis; motion commands
are refused (exception 4) until the host writes FAULT_RESET.

The mock-up's pose follows the carriage, plus an optional drift on its mount (TrackConfig).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Sequence

import numpy as np

from configuration.rig import TrackConfig
from drivers.modbus_link import int32_to_registers, registers_to_int32
from drivers.track_modbus import MICRO, TrackRegisters
from estimators.geometry import Pose
from sim_backends.modbus_server import READ_HOLDING, READ_INPUT, RegisterAccessError

R = TrackRegisters


class TrackModel:
    """A simulated linear axis (one carriage), stepped by ``step(dt)``; thread-safe."""

    def __init__(self, config: TrackConfig):
        self.config = config
        self._lock = threading.Lock()
        self._period = 1.0 / config.control_rate_hz
        self._axis_W = config.axis_unit_W
        self._X_WM0 = config.X_WM0.pose
        self._X_MT0 = config.X_MT.pose
        self._drift_v_M = np.array(config.drift_velocity_M, dtype=float)
        self._drift_w_T = np.radians(config.drift_rate_deg_s)
        self._turned_T = np.zeros(3)  # the turn accumulated before the rate last changed
        self._rate_since = 0.0
        self._x = float(config.start_position)
        self._v = 0.0
        self._time = 0.0
        self._pending = 0.0
        self._commands = [0] * R.COMMAND_COUNT
        self._faults = 0
        self._heartbeat = 0
        self._last_request = 0.0

    # --- world-loop API -------------------------------------------------------------------
    @property
    def time(self) -> float:
        """Model time (s): the sum of the ``dt`` it was stepped by."""
        with self._lock:
            return self._time + self._pending

    @property
    def position(self) -> float:
        with self._lock:
            return self._x

    @property
    def velocity(self) -> float:
        with self._lock:
            return self._v

    @property
    def faults(self) -> int:
        """Latched fault bits (``TrackRegisters.FAULT_*``)."""
        with self._lock:
            return self._faults

    def step(self, dt: float) -> None:
        """Advance the axis by ``dt`` seconds in control cycles of 1/control_rate_hz."""
        if not (math.isfinite(dt) and dt >= 0):
            raise ValueError(f"TrackModel.step: dt must be finite and ≥ 0; got {dt}")
        with self._lock:
            self._pending += dt
            while self._pending >= self._period - 1e-12:
                self._pending -= self._period
                self._cycle(self._period)

    def inject_drive_fault(self) -> None:
        """Fault injection: the drive reports a fault and brakes to rest."""
        with self._lock:
            self._latch(R.FAULT_DRIVE)

    def start_tumble(self, rate_deg_s: np.ndarray) -> None:
        """Fault injection: from now on the mock-up turns at ``rate_deg_s`` about its own axes
        (continuing from where it is)."""
        t = self.time
        self._turned_T = self._turned_T + self._drift_w_T * (t - self._rate_since)
        self._drift_w_T = np.radians(np.asarray(rate_deg_s, dtype=float))
        self._rate_since = t

    def X_WM(self) -> Pose:
        """Carriage pose in W at the current position."""
        with self._lock:
            x = self._x
        return Pose.unchecked(self._X_WM0.R, self._X_WM0.p + x * self._axis_W)

    def X_MT(self) -> Pose:
        """The mock-up (target frame T) on the carriage, drift included."""
        if not (self._drift_v_M.any() or self._drift_w_T.any() or self._turned_T.any()):
            return self._X_MT0  # on its mount, still: the common case, asked every step
        t = self.time
        translate = Pose.unchecked(np.eye(3), self._drift_v_M * t)
        turned = self._turned_T + self._drift_w_T * (t - self._rate_since)
        turn = Pose.from_rotvec(turned, np.zeros(3))
        return translate @ self._X_MT0 @ turn

    def X_WT(self) -> Pose:
        """The mock-up's target frame in W."""
        return self.X_WM() @ self.X_MT()

    # --- RegisterDevice -------------------------------------------------------------------
    def register_blocks(self) -> list[tuple[int, int]]:
        return [(R.CONTROL, R.COMMAND_COUNT), (R.STATUS, R.STATUS_COUNT)]

    def read_registers(self, function_code: int, address: int, count: int) -> list[int]:
        if function_code not in (READ_HOLDING, READ_INPUT):
            raise RegisterAccessError(1, f"function code {function_code} cannot read")
        with self._lock:
            self._last_request = self._time
            image = self._register_image()
        try:
            return [image[a] for a in range(address, address + count)]
        except KeyError:
            raise RegisterAccessError(2, f"registers {address}…{address + count - 1}") from None

    def write_registers(self, address: int, values: Sequence[int]) -> None:
        if address < R.CONTROL or address + len(values) > R.CONTROL + R.COMMAND_COUNT:
            raise RegisterAccessError(2, f"registers {address}… are not writable command registers")
        with self._lock:
            self._last_request = self._time
            commands = list(self._commands)
            commands[address : address + len(values)] = [int(v) & 0xFFFF for v in values]
            control, mode = commands[R.CONTROL], commands[R.MODE]
            if mode not in R.MODE_NAMES:
                raise RegisterAccessError(3, f"mode {mode} is not a mode")
            faults = self._faults
            if control & R.CTRL_FAULT_RESET:
                faults = 0
                commands[R.CONTROL] = control & ~R.CTRL_FAULT_RESET  # reads back 0
            if mode != R.MODE_STOP:
                if faults:
                    raise RegisterAccessError(4, "faulted: motion refused until FAULT_RESET")
                if not control & R.CTRL_ENABLE:
                    raise RegisterAccessError(4, "drive not enabled")
            if mode == R.MODE_POSITION:
                target = self._int32(commands, R.TARGET_POSITION) / MICRO
                speed = self._int32(commands, R.PROFILE_SPEED) / MICRO
                if not self.config.travel_min <= target <= self.config.travel_max:
                    raise RegisterAccessError(3, f"target {target} m beyond the soft limits")
                if speed <= 0:
                    raise RegisterAccessError(3, f"profile speed {speed} m/s must be positive")
            self._faults = faults
            self._commands = commands

    # --- internals ------------------------------------------------------------------------
    @staticmethod
    def _int32(registers: list[int], address: int) -> int:
        return registers_to_int32(registers[address], registers[address + 1])

    def _latch(self, bit: int) -> None:
        self._faults |= bit
        self._commands[R.MODE] = R.MODE_STOP  # a fault never lets an old command resume

    def _desired_velocity(self, h: float) -> float:
        cfg = self.config
        mode = self._commands[R.MODE]
        enabled = self._commands[R.CONTROL] & R.CTRL_ENABLE
        if self._faults or not enabled or mode == R.MODE_STOP:
            return 0.0
        if mode == R.MODE_VELOCITY:
            v = self._int32(self._commands, R.TARGET_VELOCITY) / MICRO
            return float(np.clip(v, -cfg.max_speed, cfg.max_speed))
        error = self._int32(self._commands, R.TARGET_POSITION) / MICRO - self._x
        speed = min(self._int32(self._commands, R.PROFILE_SPEED) / MICRO, cfg.max_speed)
        # Largest speed that still stops on the target at the maximum deceleration, in this
        # discrete cycle (trapezoid integration): v²/2a + v·h/2 ≤ |e| − |v_now|·h/2.
        a = cfg.max_acceleration
        room = max(abs(error) - 0.5 * abs(self._v) * h, 0.0)
        v_brake = a * (math.sqrt(0.25 * h * h + 2.0 * room / a) - 0.5 * h)
        return math.copysign(min(speed, v_brake), error)

    def _cycle(self, h: float) -> None:
        cfg = self.config
        self._time += h
        self._heartbeat = (self._heartbeat + 1) & 0xFFFF
        moving_commanded = self._commands[R.MODE] != R.MODE_STOP
        if (
            cfg.watchdog_s > 0
            and moving_commanded
            and self._time - self._last_request > cfg.watchdog_s
        ):
            self._latch(R.FAULT_WATCHDOG)
        a_step = cfg.max_acceleration * h
        v_new = self._v + float(np.clip(self._desired_velocity(h) - self._v, -a_step, a_step))
        self._x += 0.5 * (self._v + v_new) * h
        self._v = v_new
        if self._commands[R.MODE] == R.MODE_POSITION:
            error = self._int32(self._commands, R.TARGET_POSITION) / MICRO - self._x
            if abs(error) <= cfg.position_tolerance and abs(self._v) <= a_step:
                self._x += error
                self._v = 0.0
        if self._x < cfg.travel_min and self._v < 0:
            self._latch(R.FAULT_SOFT_LIMIT_MIN)
        elif self._x > cfg.travel_max and self._v > 0:
            self._latch(R.FAULT_SOFT_LIMIT_MAX)

    def _status_bits(self) -> int:
        cfg = self.config
        bits = 0
        mode = self._commands[R.MODE]
        if self._commands[R.CONTROL] & R.CTRL_ENABLE:
            bits |= R.ST_ENABLED
        if abs(self._v) > 1e-6:
            bits |= R.ST_MOVING
        if mode == R.MODE_POSITION and self._v == 0.0:
            error = self._int32(self._commands, R.TARGET_POSITION) / MICRO - self._x
            if abs(error) <= cfg.position_tolerance:
                bits |= R.ST_IN_POSITION
        if self._faults:
            bits |= R.ST_FAULT
        return bits

    def _register_image(self) -> dict[int, int]:
        cfg = self.config
        image = dict(enumerate(self._commands))
        status = [
            self._status_bits(),
            self._faults,
            self._commands[R.MODE],
            self._heartbeat,
            *int32_to_registers(round(self._x * MICRO)),
            *int32_to_registers(round(self._v * MICRO)),
            *int32_to_registers(round(cfg.travel_min * MICRO)),
            *int32_to_registers(round(cfg.travel_max * MICRO)),
            *int32_to_registers(round(cfg.max_speed * MICRO)),
            *int32_to_registers(round(cfg.max_acceleration * MICRO)),
        ]
        image.update({R.STATUS + i: value for i, value in enumerate(status)})
        return image
