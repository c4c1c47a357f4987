"""Robotiq 2F-85/2F-140-style gripper over Modbus: register layout and the ``Gripper`` driver.

Register layout (Robotiq 2F-85 & 2F-140 instruction manual, §4; shared/DEVICES.md), each
register holding two bytes, high byte first:

* output (commands) from 1000, written with FC16: 1000 high = ACTION REQUEST (rACT bit 0,
  rGTO bit 3, rATR bit 4, rARD bit 5); 1001 low = rPR position request (0 open … 255 closed);
  1002 high = rSP speed, low = rFR force (0…255 each);
* input (status) from 2000, read with FC04: 2000 high = GRIPPER STATUS (gACT bit 0, gGTO bit 3,
  gSTA bits 4–5 — 0 reset, 1 activating, 3 activated — gOBJ bits 6–7 — 0 moving, 1/2 stopped
  on an object while opening/closing, 3 at the requested position, no object); 2001 high =
  gFLT fault, low = gPR position request echo; 2002 high = gPO position, low = gCU current
  (≈ 10 mA per count).

Commands are not blocking: ``activate()``, ``open()`` and ``grip()`` write the request and
return; ``state()`` tells when the gripper is activated, moving, at position or holding an
object (a simulated gripper advances only with the world's clock, so waiting here would stall
it).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from types import MappingProxyType
from typing import ClassVar

from drivers.base import DeviceError, GripperState
from drivers.modbus_link import ModbusTcpLink, RegisterLink


class RobotiqRegisters:
    """Addresses, bits and codes of the Robotiq 2-finger register map."""

    OUTPUT = 1000  # 3 registers
    INPUT = 2000  # 3 registers
    COUNT = 3

    # ACTION REQUEST bits (high byte of 1000)
    rACT = 1 << 0
    rGTO = 1 << 3
    rATR = 1 << 4
    rARD = 1 << 5

    # GRIPPER STATUS fields (high byte of 2000)
    gACT = 1 << 0
    gGTO = 1 << 3
    gSTA_SHIFT = 4
    gOBJ_SHIFT = 6
    STA_RESET, STA_ACTIVATING, STA_ACTIVATED = 0, 1, 3
    OBJ_MOVING, OBJ_CONTACT_OPENING, OBJ_CONTACT_CLOSING, OBJ_AT_POSITION = 0, 1, 2, 3

    # FAULT STATUS codes (gFLT); below 0x08 are minor (cleared by a valid command), the rest
    # major (cleared by resetting and re-activating).
    FAULT_NAMES: ClassVar[Mapping[int, str]] = MappingProxyType(
        {
            0x05: "action delayed: activation must complete first",
            0x07: "the activation bit must be set prior to action",
            0x08: "maximum operating temperature exceeded",
            0x09: "no communication during at least 1 second",
            0x0A: "under minimum operating voltage",
            0x0B: "automatic release in progress",
            0x0C: "internal fault",
            0x0D: "activation fault",
            0x0E: "overcurrent triggered",
            0x0F: "automatic release completed",
        }
    )


def fault_name(code: int) -> str | None:
    if code == 0:
        return None
    return RobotiqRegisters.FAULT_NAMES.get(code, f"fault 0x{code:02x}")


def command_registers(action: int, position: int = 0, speed: int = 0, force: int = 0) -> list[int]:
    """The three output registers for an action request and rPR/rSP/rFR (0…255 each)."""
    for name, value in (("position", position), ("speed", speed), ("force", force)):
        if not 0 <= value <= 255:
            raise ValueError(f"gripper {name} request {value} is outside 0…255")
    return [(action & 0xFF) << 8, position & 0xFF, ((speed & 0xFF) << 8) | (force & 0xFF)]


class RobotiqGripper:
    """``drivers.base.Gripper`` for a Robotiq 2F gripper over Modbus (device id 9 by default).

    ``speed`` and ``force`` (0…1) scale rSP and rFR for ``open``/``grip``.
    """

    def __init__(
        self,
        link: RegisterLink,
        *,
        speed: float = 1.0,
        force: float = 0.5,
        clock: Callable[[], float] = time.monotonic,
    ):
        for name, value in (("speed", speed), ("force", force)):
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"gripper {name} must be in [0, 1]; got {value}")
        self._link = link
        self._speed = round(255 * speed)
        self._force = round(255 * force)
        self._clock = clock

    @classmethod
    def over_tcp(
        cls,
        host: str,
        port: int,
        device_id: int = 9,
        *,
        timeout_s: float = 0.5,
        speed: float = 1.0,
        force: float = 0.5,
        clock: Callable[[], float] = time.monotonic,
    ) -> RobotiqGripper:
        link = ModbusTcpLink(host, port, device_id, timeout_s=timeout_s)
        return cls(link, speed=speed, force=force, clock=clock)

    @property
    def link(self) -> RegisterLink:
        return self._link

    def connect(self) -> None:
        self._link.connect()
        self._read_status()  # a device that does not answer status reads is not our gripper

    def close(self) -> None:
        self._link.close()

    def activate(self) -> None:
        """Reset (clears faults), then request activation; ``state().activated`` tells when
        it completed."""
        self._link.write(RobotiqRegisters.OUTPUT, command_registers(0))
        self._link.write(RobotiqRegisters.OUTPUT, command_registers(RobotiqRegisters.rACT))

    def deactivate(self) -> None:
        """Nothing to do: clearing rACT would open the fingers and could drop the part."""

    def open(self) -> None:
        self.move(0)

    def grip(self) -> None:
        self.move(255)

    def move(self, position: int) -> None:
        """Go to ``position`` (0 open … 255 closed) at the configured speed and force."""
        action = RobotiqRegisters.rACT | RobotiqRegisters.rGTO
        self._link.write(
            RobotiqRegisters.OUTPUT, command_registers(action, position, self._speed, self._force)
        )

    def state(self) -> GripperState:
        status, fault_and_echo, position_and_current = self._read_status()
        stamp = self._clock()
        gripper_status = status >> 8
        sta = (gripper_status >> RobotiqRegisters.gSTA_SHIFT) & 0b11
        obj = (gripper_status >> RobotiqRegisters.gOBJ_SHIFT) & 0b11
        going = bool(gripper_status & RobotiqRegisters.gGTO)
        return GripperState(
            stamp=stamp,
            activated=sta == RobotiqRegisters.STA_ACTIVATED,
            position=(position_and_current >> 8) / 255.0,
            moving=sta == RobotiqRegisters.STA_ACTIVATING
            or (going and obj == RobotiqRegisters.OBJ_MOVING),
            object_detected=obj
            in (RobotiqRegisters.OBJ_CONTACT_OPENING, RobotiqRegisters.OBJ_CONTACT_CLOSING),
            fault=fault_name(fault_and_echo >> 8),
        )

    def _read_status(self) -> list[int]:
        regs = self._link.read_input(RobotiqRegisters.INPUT, RobotiqRegisters.COUNT)
        if len(regs) != RobotiqRegisters.COUNT:
            raise DeviceError(
                f"{self._link.description}: short status read ({len(regs)} registers)"
            )
        return regs
