"""The Modbus link's pure parts (register encoding, exception names) at their edges, and the
TCP link's own checks that need no device; its requests are tested through the track and
gripper drivers against real pymodbus servers."""

import pytest

from drivers.base import DeviceError, DeviceFault, DeviceTimeout
from drivers.modbus_link import (
    ModbusTcpLink,
    exception_error,
    int32_to_registers,
    registers_to_int32,
    scaled_int32,
)

LOW, HIGH = -(2**31), 2**31 - 1


@pytest.mark.parametrize("value", [LOW, -1, 0, 1, HIGH])
def test_int32_round_trips_at_its_edges(value):
    assert registers_to_int32(*int32_to_registers(value)) == value


def test_int32_register_words_high_first():
    assert int32_to_registers(LOW) == [0x8000, 0]
    assert int32_to_registers(-1) == [0xFFFF, 0xFFFF]
    assert registers_to_int32(0, 1) == 1 and registers_to_int32(0x8000, 1) == LOW + 1


@pytest.mark.parametrize("value", [LOW - 1, HIGH + 1, -(2**32), 2**32])
def test_int32_refuses_what_does_not_fit(value):
    with pytest.raises(ValueError, match=f"^{value} does not fit a signed 32-bit register pair$"):
        int32_to_registers(value)


def test_scaled_int32_edges_and_message():
    assert scaled_int32(LOW / 1e6, 1e6, "position") == [0x8000, 0]
    assert registers_to_int32(*scaled_int32(HIGH / 1e6, 1e6, "position")) == HIGH
    for value in ((LOW - 1) / 1e6, (HIGH + 1) / 1e6):
        with pytest.raises(ValueError, match=r"^position = .* is out of the register range$"):
            scaled_int32(value, 1e6, "position")


@pytest.mark.parametrize(
    ("code", "kind", "name"),
    [
        (2, DeviceError, "illegal data address"),
        (4, DeviceFault, "device failure"),
        (11, DeviceTimeout, "gateway target device failed to respond"),
        (99, DeviceError, "unknown exception"),
    ],
)
def test_exception_errors_name_the_request_code_and_meaning(code, kind, name):
    error = exception_error(code, "reading 8 registers")
    assert type(error) is kind
    assert (
        str(error) == f"reading 8 registers: the device answered Modbus exception {code} ({name})"
    )


def test_tcp_link_time_out_must_be_positive_and_defaults_to_half_a_second():
    assert ModbusTcpLink("127.0.0.1", 502, 1).timeout_s == 0.5
    for bad in (0.0, -0.1):
        with pytest.raises(ValueError, match=f"^timeout_s must be positive; got {bad}$"):
            ModbusTcpLink("127.0.0.1", 502, 1, timeout_s=bad)


def test_tcp_link_requests_before_connect_or_after_close_say_not_connected():
    link = ModbusTcpLink("127.0.0.1", 1, 7, timeout_s=0.1)
    expected = "Modbus TCP 127.0.0.1:1 device 7: writing 2 registers at 5: not connected"
    with pytest.raises(DeviceError, match=f"^{expected}"):
        link.write(5, [1, 2])
    link.close()
    link.close()  # twice: harmless
    with pytest.raises(DeviceError, match="reading 3 holding registers at 4: not connected"):
        link.read_holding(4, 3)
