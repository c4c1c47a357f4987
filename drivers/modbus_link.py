"""A register link to one Modbus device, and the helpers device drivers share.

``RegisterLink`` is what a register-level driver (the linear track, the Robotiq gripper) talks
to: read holding registers (FC03), read input registers (FC04), write registers (FC16).
``ModbusTcpLink`` implements it over Modbus TCP with pymodbus' synchronous client, turns every
failure into a ``DeviceError`` that names the device, address and cause, and reconnects by
itself after the link dropped (one silent retry of the request on a fresh connection; the
requests our drivers send are idempotent register writes and reads). Simulated devices are
reached through the same drivers, in-process (``sim_backends.modbus_server.DirectLink``) or over
a loopback server.

32-bit values occupy two registers, high word first ("big" word order, ABCD), as pymodbus'
``convert_to_registers`` writes them by default.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Protocol, TypeVar, runtime_checkable

from pymodbus.client import ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.pdu import ExceptionResponse

from drivers.base import DeviceError, DeviceFault, DeviceTimeout

ResultT = TypeVar("ResultT")

#: Modbus exception codes (Modbus application protocol v1.1b3, §7) and what they mean here.
EXCEPTION_NAMES = {
    1: "illegal function",
    2: "illegal data address",
    3: "illegal data value",
    4: "device failure",
    5: "acknowledge",
    6: "device busy",
    10: "gateway path unavailable",
    11: "gateway target device failed to respond",
}


def exception_error(code: int, what: str) -> DeviceError:
    """The error a Modbus exception response ``code`` to request ``what`` raises: device failure
    (4) is a ``DeviceFault`` (the device refuses because of its state), a silent gateway target
    (11) a ``DeviceTimeout``, everything else a ``DeviceError``."""
    name = EXCEPTION_NAMES.get(code, "unknown exception")
    message = f"{what}: the device answered Modbus exception {code} ({name})"
    if code == 4:
        return DeviceFault(message)
    if code == 11:
        return DeviceTimeout(message)
    return DeviceError(message)


def int32_to_registers(value: int) -> list[int]:
    """A signed 32-bit integer as two 16-bit registers, high word first."""
    value = int(value)
    if not -(2**31) <= value < 2**31:
        raise ValueError(f"{value} does not fit a signed 32-bit register pair")
    raw = value & 0xFFFFFFFF
    return [raw >> 16, raw & 0xFFFF]


def registers_to_int32(high: int, low: int) -> int:
    """The signed 32-bit integer held in two registers, high word first."""
    raw = ((high & 0xFFFF) << 16) | (low & 0xFFFF)
    return raw - (1 << 32) if raw & 0x80000000 else raw


def scaled_int32(value: float, scale: float, name: str) -> list[int]:
    """``value`` (SI) times ``scale`` rounded to an int32 register pair; ``name`` for errors."""
    scaled = round(value * scale)
    if not -(2**31) <= scaled < 2**31:
        raise ValueError(f"{name} = {value} is out of the register range")
    return int32_to_registers(scaled)


@runtime_checkable
class RegisterLink(Protocol):
    """Register access to one Modbus device. Errors are ``DeviceError`` subclasses."""

    @property
    def description(self) -> str: ...

    def connect(self) -> None: ...

    def close(self) -> None: ...

    def read_holding(self, address: int, count: int) -> list[int]: ...

    def read_input(self, address: int, count: int) -> list[int]: ...

    def write(self, address: int, values: Sequence[int]) -> None: ...


class ModbusTcpLink:
    """``RegisterLink`` over Modbus TCP (pymodbus ``ModbusTcpClient``, device id via
    ``device_id=``). ``timeout_s`` bounds connecting and each reply."""

    def __init__(self, host: str, port: int, device_id: int, *, timeout_s: float = 0.5):
        if timeout_s <= 0:
            raise ValueError(f"timeout_s must be positive; got {timeout_s}")
        self.host = host
        self.port = int(port)
        self.device_id = int(device_id)
        self.timeout_s = float(timeout_s)
        self._client: ModbusTcpClient | None = None

    @property
    def description(self) -> str:
        return f"Modbus TCP {self.host}:{self.port} device {self.device_id}"

    def connect(self) -> None:
        if self._client is None:
            # retries=0: a lost reply surfaces at once; reconnect_delay=0: no background retry
            # loop — reconnecting is this class's job, done on the next request.
            self._client = ModbusTcpClient(
                self.host, port=self.port, timeout=self.timeout_s, retries=0, reconnect_delay=0
            )
        if not self._client.connect():
            self.close()
            raise DeviceError(
                f"{self.description}: nothing accepts connections there (refused or "
                f"unreachable within {self.timeout_s} s) — is the device on and the address right?"
            )

    def close(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None

    def reconnect(self) -> None:
        """Drop the connection and open a new one."""
        self.close()
        self.connect()

    def read_holding(self, address: int, count: int) -> list[int]:
        what = f"{self.description}: reading {count} holding registers at {address}"
        return self._request(
            what,
            lambda c: c.read_holding_registers(address, count=count, device_id=self.device_id),
        ).registers

    def read_input(self, address: int, count: int) -> list[int]:
        what = f"{self.description}: reading {count} input registers at {address}"
        return self._request(
            what,
            lambda c: c.read_input_registers(address, count=count, device_id=self.device_id),
        ).registers

    def write(self, address: int, values: Sequence[int]) -> None:
        what = f"{self.description}: writing {len(values)} registers at {address}"
        payload = [int(v) & 0xFFFF for v in values]
        self._request(what, lambda c: c.write_registers(address, payload, device_id=self.device_id))

    def _request(self, what: str, call: Callable[[ModbusTcpClient], ResultT]) -> ResultT:
        if self._client is None:
            raise DeviceError(f"{what}: not connected (call connect())")
        try:
            response = self._attempt(what, call)
        except _LinkDropped as first:
            # The connection is gone (device restarted, cable, …): reconnect once and retry.
            if not self._client.connect():
                raise DeviceError(
                    f"{what}: the link dropped ({first}) and nothing accepts connections there "
                    f"now (refused or unreachable within {self.timeout_s} s)"
                ) from None
            try:
                response = self._attempt(what, call)
            except _LinkDropped as again:
                raise DeviceError(
                    f"{what}: the link dropped again after reconnecting ({again})"
                ) from None
        if isinstance(response, ExceptionResponse) or response.isError():
            raise exception_error(int(getattr(response, "exception_code", 0)), what)
        return response

    def _attempt(self, what: str, call: Callable[[ModbusTcpClient], ResultT]) -> ResultT:
        """One request; a broken connection is closed (the next request reconnects)."""
        client = self._client
        assert client is not None
        try:
            return call(client)
        except ModbusIOException as exc:
            # Connected, but no (complete) reply within the timeout: the device is silent.
            client.close()
            raise DeviceTimeout(
                f"{what}: no reply within {self.timeout_s} s ({_reason(exc)})"
            ) from None
        except ConnectionException as exc:
            client.close()
            raise _LinkDropped(_reason(exc)) from None
        except (ModbusException, OSError) as exc:
            client.close()
            raise DeviceError(f"{what}: {_reason(exc)}") from None


class _LinkDropped(Exception):
    """Internal: the TCP connection is gone (closed by the peer or refused)."""


def _reason(exc: BaseException) -> str:
    return str(exc).replace("Modbus Error: ", "").strip() or type(exc).__name__
