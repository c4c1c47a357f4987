"""A loopback emulator of a Universal Robots e-Series controller that the real ur-rtde client
drives: dashboard server (29999), script port (30003), RTDE (30004) with ur-rtde's control-script
register protocol, backed by the simulated arm's kinematics (``SimArm``) stepped on the wall
clock at the controller rate, in a process of its own. See docs/ur_emulator.md.

Modules, one job each: ``rtde_server`` (RTDE sessions; the wire codec is ``drivers.rtde_protocol``,
shared with the driver's probe), ``rtde_variables`` (which outputs and inputs exist),
``dashboard``, ``script_socket``, ``interpreter`` (the register protocol), ``controller`` (arm,
program, safety, registers), ``motion`` (servoL/moveL as twists), ``faults``, ``command_log``,
``server`` (the event loop), ``process`` (the process and its handle).
"""

from sim_backends.ur_emulator.command_log import CommandRecord
from sim_backends.ur_emulator.process import (
    EmulatorError,
    UREmulator,
    arm_config,
    free_loopback_host,
)
from sim_backends.ur_emulator.server import EmulatorStatus

__all__ = [
    "CommandRecord",
    "EmulatorError",
    "EmulatorStatus",
    "UREmulator",
    "arm_config",
    "free_loopback_host",
]
