"""The mock-up's linear track over Modbus: its register map and the ``Track`` driver.

The register map (documented for people in ``docs/track_modbus.md``) is the contract between
this driver and the axis controller — the real one or ``sim_backends.track.TrackModel``:

* holding registers 0–8, commands (FC03 read back, FC06/FC16 write): control bits, mode,
  target position, profile speed, target velocity, host heartbeat;
* input registers 100–115, status (FC04; FC03 answers too): status bits, fault bits, active
  mode, device heartbeat, actual position and velocity, soft limits, speed and acceleration
  limits.

Lengths are µm, speeds µm/s, accelerations µm/s², each a signed 32-bit integer in two
registers, high word first. The controller tracks its command registers continuously: a write
takes effect at once, so one FC16 write of registers 0–8 is one complete command.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Mapping
from types import MappingProxyType
from typing import ClassVar

from drivers.base import DeviceError, DeviceFault, TrackState
from drivers.modbus_link import ModbusTcpLink, RegisterLink, registers_to_int32, scaled_int32

MICRO = 1_000_000.0  # register units per SI unit (µm per m)


class TrackRegisters:
    """Addresses and bits of the track's register map."""

    # holding registers (commands)
    CONTROL = 0
    MODE = 1
    TARGET_POSITION = 2  # int32 µm (2–3)
    PROFILE_SPEED = 4  # int32 µm/s (4–5), position moves
    TARGET_VELOCITY = 6  # int32 µm/s (6–7), velocity mode
    HOST_HEARTBEAT = 8  # any value; written with every command
    COMMAND_COUNT = 9

    # CONTROL bits
    CTRL_ENABLE = 1 << 0
    CTRL_FAULT_RESET = 1 << 1  # write 1: clear latched faults; reads back 0

    # MODE values
    MODE_STOP = 0
    MODE_POSITION = 1
    MODE_VELOCITY = 2
    MODE_NAMES: ClassVar[Mapping[int, str]] = MappingProxyType(
        {0: "stop", 1: "position", 2: "velocity"}
    )

    # input registers (status)
    STATUS = 100
    FAULTS = 101
    ACTIVE_MODE = 102
    HEARTBEAT = 103  # device cycle counter, wraps at 65536
    ACTUAL_POSITION = 104  # int32 µm (104–105)
    ACTUAL_VELOCITY = 106  # int32 µm/s (106–107)
    SOFT_LIMIT_MIN = 108  # int32 µm (108–109)
    SOFT_LIMIT_MAX = 110  # int32 µm (110–111)
    MAX_SPEED = 112  # int32 µm/s (112–113)
    MAX_ACCELERATION = 114  # int32 µm/s² (114–115)
    STATUS_COUNT = 16

    # STATUS bits
    ST_ENABLED = 1 << 0
    ST_MOVING = 1 << 1
    ST_IN_POSITION = 1 << 2
    ST_FAULT = 1 << 3

    # FAULTS bits
    FAULT_SOFT_LIMIT_MIN = 1 << 0
    FAULT_SOFT_LIMIT_MAX = 1 << 1
    FAULT_WATCHDOG = 1 << 2
    FAULT_DRIVE = 1 << 3
    FAULT_NAMES: ClassVar[Mapping[int, str]] = MappingProxyType(
        {
            FAULT_SOFT_LIMIT_MIN: "soft limit min crossed",
            FAULT_SOFT_LIMIT_MAX: "soft limit max crossed",
            FAULT_WATCHDOG: "communication watchdog (no request in time)",
            FAULT_DRIVE: "drive fault",
        }
    )


def describe_faults(bits: int) -> str | None:
    """Readable names of the set fault bits, or None when there are none."""
    names = [name for bit, name in TrackRegisters.FAULT_NAMES.items() if bits & bit]
    unknown = bits & ~sum(TrackRegisters.FAULT_NAMES)
    if unknown:
        names.append(f"unknown fault bits 0x{unknown:04x}")
    return "; ".join(names) if names else None


class ModbusTrack:
    """``drivers.base.Track`` over Modbus: the linear axis carrying the mock-up.

    ``connect()`` reads the device's soft limits and speed/acceleration limits; commands outside
    them raise ``ValueError`` before anything is sent. Every command is one FC16 write of the
    whole command block, so a command is never half-applied. A device in fault refuses motion
    (exception 4) and the driver raises ``DeviceFault`` naming the fault; ``reset_fault()``
    clears it once its cause is gone.
    """

    def __init__(self, link: RegisterLink, *, clock: Callable[[], float] = time.monotonic):
        self._link = link
        self._clock = clock
        self._heartbeat = 0
        self._active = False
        self.travel_min = -math.inf
        self.travel_max = math.inf
        self.max_speed = math.inf
        self.max_acceleration = math.inf

    @classmethod
    def over_tcp(
        cls,
        host: str,
        port: int,
        device_id: int = 1,
        *,
        timeout_s: float = 0.5,
        clock: Callable[[], float] = time.monotonic,
    ) -> ModbusTrack:
        return cls(ModbusTcpLink(host, port, device_id, timeout_s=timeout_s), clock=clock)

    @property
    def link(self) -> RegisterLink:
        return self._link

    # --- lifecycle ----------------------------------------------------------------------
    def connect(self) -> None:
        self._link.connect()
        regs = self._link.read_input(TrackRegisters.SOFT_LIMIT_MIN, 8)
        self.travel_min = registers_to_int32(regs[0], regs[1]) / MICRO
        self.travel_max = registers_to_int32(regs[2], regs[3]) / MICRO
        self.max_speed = registers_to_int32(regs[4], regs[5]) / MICRO
        self.max_acceleration = registers_to_int32(regs[6], regs[7]) / MICRO
        if not (self.travel_min < self.travel_max and self.max_speed > 0):
            raise DeviceError(
                f"{self._link.description}: implausible limits read from the track "
                f"(travel {self.travel_min}…{self.travel_max} m, max speed {self.max_speed} m/s)"
            )

    def activate(self) -> None:
        """Enable the drive, holding still: motion commands are accepted from now on."""
        self._command(TrackRegisters.MODE_STOP)
        self._active = True

    def deactivate(self) -> None:
        """Stop and remove drive power; the state stays readable."""
        self._active = False
        self.disable()

    def close(self) -> None:
        if self._active:
            with contextlib.suppress(DeviceError):
                self.deactivate()
        self._active = False
        self._link.close()

    # --- state --------------------------------------------------------------------------
    def state(self) -> TrackState:
        regs = self._link.read_input(TrackRegisters.STATUS, 8)
        stamp = self._clock()
        status, faults = regs[0], regs[1]
        fault = describe_faults(faults)
        if fault is None and status & TrackRegisters.ST_FAULT:
            fault = "fault (no fault bits given)"
        return TrackState(
            stamp=stamp,
            position=registers_to_int32(regs[4], regs[5]) / MICRO,
            velocity=registers_to_int32(regs[6], regs[7]) / MICRO,
            moving=bool(status & TrackRegisters.ST_MOVING),
            fault=fault,
        )

    # --- commands -----------------------------------------------------------------------
    def move_velocity(self, velocity: float) -> None:
        """Run at ``velocity`` (m/s, signed along the axis) until told otherwise."""
        self.check_velocity(velocity)
        self._command(TrackRegisters.MODE_VELOCITY, velocity=velocity)

    def check_velocity(self, velocity: float) -> None:
        """What ``move_velocity(velocity)`` would refuse, without sending it: ``DeviceError``
        when the track is not active, ``ValueError`` outside the device's speed limit."""
        self._require_active("move_velocity")
        if not math.isfinite(velocity) or abs(velocity) > self.max_speed:
            raise ValueError(
                f"track velocity {velocity} m/s is outside ±{self.max_speed} m/s (max_speed)"
            )

    def move_to(self, position: float, speed: float) -> None:
        """Move to ``position`` (m) at up to ``speed`` (m/s) with a trapezoidal profile."""
        self._require_active("move_to")
        if not math.isfinite(position) or not self.travel_min <= position <= self.travel_max:
            raise ValueError(
                f"track position {position} m is outside the travel "
                f"[{self.travel_min}, {self.travel_max}] m"
            )
        if not math.isfinite(speed) or not 0 < speed <= self.max_speed:
            raise ValueError(f"track speed {speed} m/s must be in (0, {self.max_speed}] m/s")
        self._command(TrackRegisters.MODE_POSITION, position=position, speed=speed)

    def stop(self) -> None:
        """Decelerate to rest at the device's maximum acceleration and hold."""
        self._command(TrackRegisters.MODE_STOP)

    def reset_fault(self) -> None:
        """Clear latched faults (the device keeps a fault whose cause is still there)."""
        self._command(TrackRegisters.MODE_STOP, control_extra=TrackRegisters.CTRL_FAULT_RESET)

    def disable(self) -> None:
        """Stop and remove drive power."""
        self._command(TrackRegisters.MODE_STOP, enable=False)

    def _require_active(self, call: str) -> None:
        if not self._active:
            raise DeviceError(
                f"{self._link.description}: {call} refused: the track is not active "
                "(call activate())"
            )

    def _command(
        self,
        mode: int,
        *,
        position: float = 0.0,
        speed: float = 0.0,
        velocity: float = 0.0,
        enable: bool = True,
        control_extra: int = 0,
    ) -> None:
        self._heartbeat = (self._heartbeat + 1) & 0xFFFF
        control = (TrackRegisters.CTRL_ENABLE if enable else 0) | control_extra
        block = [
            control,
            mode,
            *scaled_int32(position, MICRO, "position"),
            *scaled_int32(speed, MICRO, "speed"),
            *scaled_int32(velocity, MICRO, "velocity"),
            self._heartbeat,
        ]
        try:
            self._link.write(TrackRegisters.CONTROL, block)
        except DeviceFault as exc:
            reason = self._fault_reason()
            name = TrackRegisters.MODE_NAMES[mode]
            raise DeviceFault(f"track refused the {name} command: {reason or exc}") from None

    def _fault_reason(self) -> str | None:
        try:
            return self.state().fault
        except DeviceError:
            return None
