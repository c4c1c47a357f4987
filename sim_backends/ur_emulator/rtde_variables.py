"""The RTDE variables the emulated controller knows: each output's RTDE type and where its value
comes from, and each input's type. A name not listed here is ``NOT_FOUND`` to a client.

Types follow UR's RTDE guide (they are also what ur-rtde decodes with its own table). Values
the kinematic model does not produce are plausible constants (voltages, temperatures, digital
I/O), named as such in ``CONSTANT_OUTPUTS``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

REGISTER_COUNT = 48  # int and double registers 0–47 (24–47 is the "upper range")
BIT_REGISTERS = range(64, 128)  # input/output_bit_register_64 … 127


class ControllerView(Protocol):
    """What the output table reads from the emulated controller."""

    timestamp: float
    q: tuple[float, ...]
    qd: tuple[float, ...]
    tcp_pose: tuple[float, ...]
    tcp_speed: tuple[float, ...]
    tcp_force: tuple[float, ...]
    robot_mode: int
    safety_mode: int
    safety_status_bits: int
    runtime_state: int
    robot_status_bits: int
    output_int: list[int]
    output_double: list[float]
    output_bits: int
    input_int: list[int]
    input_double: list[float]
    input_bits: int
    period_s: float


Getter = Callable[[ControllerView], object]

_ZERO6 = (0.0,) * 6
_ZERO3 = (0.0,) * 3

#: Outputs the model does not produce: constant plausible values.
CONSTANT_OUTPUTS: dict[str, tuple[str, object]] = {
    "target_qdd": ("VECTOR6D", _ZERO6),
    "actual_qdd": ("VECTOR6D", _ZERO6),
    "target_current": ("VECTOR6D", _ZERO6),
    "target_moment": ("VECTOR6D", _ZERO6),
    "actual_current": ("VECTOR6D", _ZERO6),
    "actual_current_as_torque": ("VECTOR6D", _ZERO6),
    "joint_control_output": ("VECTOR6D", _ZERO6),
    "joint_temperatures": ("VECTOR6D", (32.0,) * 6),
    "actual_joint_voltage": ("VECTOR6D", (47.5,) * 6),
    "ft_raw_wrench": ("VECTOR6D", _ZERO6),
    "payload_inertia": ("VECTOR6D", _ZERO6),
    "tcp_offset": ("VECTOR6D", _ZERO6),
    "joint_mode": ("VECTOR6INT32", (253,) * 6),  # JOINT_RUNNING_MODE
    "actual_tool_accelerometer": ("VECTOR3D", (0.0, 0.0, 9.81)),
    "payload_cog": ("VECTOR3D", _ZERO3),
    "elbow_position": ("VECTOR3D", _ZERO3),
    "elbow_velocity": ("VECTOR3D", _ZERO3),
    "actual_digital_input_bits": ("UINT64", 0),
    "actual_digital_output_bits": ("UINT64", 0),
    "speed_scaling": ("DOUBLE", 1.0),
    "target_speed_fraction": ("DOUBLE", 1.0),
    "actual_momentum": ("DOUBLE", 0.0),
    "actual_main_voltage": ("DOUBLE", 48.0),
    "actual_robot_voltage": ("DOUBLE", 48.0),
    "actual_robot_current": ("DOUBLE", 0.8),
    "standard_analog_input0": ("DOUBLE", 0.0),
    "standard_analog_input1": ("DOUBLE", 0.0),
    "standard_analog_output0": ("DOUBLE", 0.0),
    "standard_analog_output1": ("DOUBLE", 0.0),
    "payload": ("DOUBLE", 0.0),
    "tool_analog_input0": ("DOUBLE", 0.0),
    "tool_analog_input1": ("DOUBLE", 0.0),
    "tool_output_current": ("DOUBLE", 0.0),
    "tool_temperature": ("DOUBLE", 30.0),
    "safety_status": ("INT32", 1),
    "tool_output_voltage": ("INT32", 0),
    "tool_mode": ("UINT32", 0),
    "analog_io_types": ("UINT32", 0),
    "io_current": ("DOUBLE", 0.0),
}


def _constant(value: object) -> Getter:
    return lambda _c: value


def _attr(name: str) -> Getter:
    return lambda c: getattr(c, name)


def _build_outputs() -> dict[str, tuple[str, Getter]]:
    outputs: dict[str, tuple[str, Getter]] = {
        "timestamp": ("DOUBLE", _attr("timestamp")),
        "actual_execution_time": ("DOUBLE", lambda c: 0.2e-3),
        "target_q": ("VECTOR6D", _attr("q")),
        "target_qd": ("VECTOR6D", _attr("qd")),
        "actual_q": ("VECTOR6D", _attr("q")),
        "actual_qd": ("VECTOR6D", _attr("qd")),
        "actual_TCP_pose": ("VECTOR6D", _attr("tcp_pose")),
        "target_TCP_pose": ("VECTOR6D", _attr("tcp_pose")),
        "actual_TCP_speed": ("VECTOR6D", _attr("tcp_speed")),
        "target_TCP_speed": ("VECTOR6D", _attr("tcp_speed")),
        "actual_TCP_force": ("VECTOR6D", _attr("tcp_force")),
        "robot_mode": ("INT32", _attr("robot_mode")),
        "safety_mode": ("INT32", _attr("safety_mode")),
        "runtime_state": ("UINT32", _attr("runtime_state")),
        "robot_status_bits": ("UINT32", _attr("robot_status_bits")),
        "safety_status_bits": ("UINT32", _attr("safety_status_bits")),
        "output_bit_registers0_to_31": ("UINT32", lambda c: c.output_bits & 0xFFFFFFFF),
        "output_bit_registers32_to_63": ("UINT32", lambda c: (c.output_bits >> 32) & 0xFFFFFFFF),
        "input_bit_registers0_to_31": ("UINT32", lambda c: c.input_bits & 0xFFFFFFFF),
        "input_bit_registers32_to_63": ("UINT32", lambda c: (c.input_bits >> 32) & 0xFFFFFFFF),
    }
    for name, (kind, value) in CONSTANT_OUTPUTS.items():
        outputs[name] = (kind, _constant(value))
    for i in range(REGISTER_COUNT):
        outputs[f"output_int_register_{i}"] = ("INT32", lambda c, i=i: c.output_int[i])
        outputs[f"output_double_register_{i}"] = ("DOUBLE", lambda c, i=i: c.output_double[i])
        outputs[f"input_int_register_{i}"] = ("INT32", lambda c, i=i: c.input_int[i])
        outputs[f"input_double_register_{i}"] = ("DOUBLE", lambda c, i=i: c.input_double[i])
    for i in BIT_REGISTERS:
        outputs[f"output_bit_register_{i}"] = ("BOOL", lambda c, i=i: bool(c.output_bits >> i & 1))
        outputs[f"input_bit_register_{i}"] = ("BOOL", lambda c, i=i: bool(c.input_bits >> i & 1))
    return outputs


#: name → (RTDE type, value getter)
OUTPUTS: dict[str, tuple[str, Getter]] = _build_outputs()


def _build_inputs() -> dict[str, str]:
    inputs = {
        "standard_digital_output_mask": "UINT8",
        "standard_digital_output": "UINT8",
        "configurable_digital_output_mask": "UINT8",
        "configurable_digital_output": "UINT8",
        "tool_digital_output_mask": "UINT8",
        "tool_digital_output": "UINT8",
        "standard_analog_output_mask": "UINT8",
        "standard_analog_output_type": "UINT8",
        "standard_analog_output_0": "DOUBLE",
        "standard_analog_output_1": "DOUBLE",
        "speed_slider_mask": "UINT32",
        "speed_slider_fraction": "DOUBLE",
        "external_force_torque": "VECTOR6D",
        "input_bit_registers0_to_31": "UINT32",
        "input_bit_registers32_to_63": "UINT32",
    }
    for i in range(REGISTER_COUNT):
        inputs[f"input_int_register_{i}"] = "INT32"
        inputs[f"input_double_register_{i}"] = "DOUBLE"
    for i in BIT_REGISTERS:
        inputs[f"input_bit_register_{i}"] = "BOOL"
    return inputs


#: name → RTDE type of every input a client may set up.
INPUTS: dict[str, str] = _build_inputs()
