"""What a UR controller's state numbers mean (UR's RTDE guide): robot mode, safety mode, the
program's runtime state and the status bit fields — read by the driver, written by the
emulator."""

from __future__ import annotations

from enum import IntEnum


class RobotMode(IntEnum):
    NO_CONTROLLER = -1
    DISCONNECTED = 0
    CONFIRM_SAFETY = 1
    BOOTING = 2
    POWER_OFF = 3
    POWER_ON = 4
    IDLE = 5
    BACKDRIVE = 6
    RUNNING = 7
    UPDATING_FIRMWARE = 8


class SafetyMode(IntEnum):
    NORMAL = 1
    REDUCED = 2
    PROTECTIVE_STOP = 3
    RECOVERY = 4
    SAFEGUARD_STOP = 5
    SYSTEM_EMERGENCY_STOP = 6
    ROBOT_EMERGENCY_STOP = 7
    VIOLATION = 8
    FAULT = 9
    VALIDATE_JOINT_ID = 10
    UNDEFINED_SAFETY_MODE = 11
    AUTOMATIC_MODE_SAFEGUARD_STOP = 12
    SYSTEM_THREE_POSITION_ENABLING_STOP = 13


#: Safety modes in which the arm may move.
SAFETY_MOVABLE = frozenset({SafetyMode.NORMAL, SafetyMode.REDUCED})
SAFETY_EMERGENCY = frozenset({SafetyMode.SYSTEM_EMERGENCY_STOP, SafetyMode.ROBOT_EMERGENCY_STOP})


class RuntimeState(IntEnum):
    STOPPING = 0
    STOPPED = 1
    PLAYING = 2
    PAUSING = 3
    PAUSED = 4
    RESUMING = 5


# safety_status_bits
SAFETY_BIT_NORMAL = 1 << 0
SAFETY_BIT_PROTECTIVE_STOPPED = 1 << 2
SAFETY_BIT_ROBOT_EMERGENCY_STOPPED = 1 << 6
SAFETY_BIT_EMERGENCY_STOPPED = 1 << 7
SAFETY_BIT_STOPPED_DUE_TO_SAFETY = 1 << 10
# robot_status_bits
STATUS_BIT_POWER_ON = 1 << 0
STATUS_BIT_PROGRAM_RUNNING = 1 << 1


def name_of(enum: type[IntEnum], value: int) -> str:
    """The member's name, or the number when the controller sent one this table lacks."""
    try:
        return enum(value).name
    except ValueError:
        return str(value)
