"""Serving simulated register devices: over a real pymodbus TCP server on loopback, or in-process.

A simulated device (the linear track, the gripper) is a ``RegisterDevice``: it names its valid
register blocks and answers reads and writes from its own state, under its own lock, while the
world loop advances it with ``step(dt)`` from another thread. ``ModbusDeviceServer`` puts such
devices behind pymodbus' TCP server (``SimDevice`` with an async ``action`` that forwards every
request to the device model, so the server's register copy is never stale) in a background
thread with its own event loop; it binds loopback only. ``DirectLink`` reaches a device
in-process through the same ``RegisterLink`` interface the real drivers use, for simulations
that should not pay for sockets.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable, Mapping, Sequence
from typing import Protocol, runtime_checkable

from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from drivers.base import DeviceError, DeviceTimeout
from drivers.modbus_link import exception_error
from sim_backends.loopback import check_loopback

#: Function codes a device sees: reads of holding (3) and input (4) registers, writes (6, 16).
READ_HOLDING, READ_INPUT, WRITE_SINGLE, WRITE_MULTIPLE = 3, 4, 6, 16


class RegisterAccessError(Exception):
    """A device refuses a request; ``code`` is the Modbus exception code it answers with."""

    def __init__(self, code: int, message: str):
        super().__init__(message)
        self.code = int(code)


@runtime_checkable
class RegisterDevice(Protocol):
    """A register-level device model. All methods are called from any thread."""

    def register_blocks(self) -> list[tuple[int, int]]:
        """Valid (first address, count) blocks."""
        ...

    def read_registers(self, function_code: int, address: int, count: int) -> list[int]:
        """Values of ``count`` registers from ``address``, or ``RegisterAccessError``."""
        ...

    def write_registers(self, address: int, values: Sequence[int]) -> None:
        """Apply a write, or ``RegisterAccessError``."""
        ...


#: How often a silenced device looks whether it may answer again (s).
_SILENT_POLL_S = 0.02


def _action_for(device: RegisterDevice, silent: Callable[[], bool] = lambda: False):
    """The pymodbus ``SimDevice`` action forwarding each request to ``device``; while
    ``silent()`` holds the request gets no answer (the client's reply time-out expires)."""

    async def action(
        function_code: int,
        start_address: int,
        address: int,
        count: int,
        current_registers: list[int],
        set_values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        while silent():
            await asyncio.sleep(_SILENT_POLL_S)
        try:
            if set_values is not None and function_code in (WRITE_SINGLE, WRITE_MULTIPLE):
                device.write_registers(address, [int(v) for v in set_values])
                return None
            values = device.read_registers(function_code, address, count)
        except RegisterAccessError as exc:
            return ExcCodes(exc.code)
        except Exception:  # a model bug must not kill the server thread
            return ExcCodes.DEVICE_FAILURE
        offset = address - start_address
        current_registers[offset : offset + count] = values
        return None

    return action


def _sim_device(
    device_id: int, device: RegisterDevice, silent: Callable[[], bool] = lambda: False
) -> SimDevice:
    blocks = [
        SimData(start, count=count, datatype=DataType.REGISTERS)
        for start, count in sorted(device.register_blocks())
    ]
    return SimDevice(id=device_id, simdata=blocks, action=_action_for(device, silent))


def _absent_devices(devices: list[RegisterDevice]) -> SimDevice:
    """pymodbus' catch-all device (id 0): requests for an id nobody serves are answered like
    a gateway whose target is silent (exception 11), instead of pymodbus' internal error."""
    blocks = sorted({block for device in devices for block in device.register_blocks()})
    merged: list[tuple[int, int]] = []
    for start, count in blocks:  # pymodbus refuses overlapping blocks
        if merged and start <= merged[-1][0] + merged[-1][1]:
            first, length = merged[-1]
            merged[-1] = (first, max(length, start + count - first))
        else:
            merged.append((start, count))

    async def silent(*_args) -> ExcCodes:
        return ExcCodes.GATEWAY_NO_RESPONSE

    simdata = [SimData(a, count=n, datatype=DataType.REGISTERS) for a, n in merged]
    return SimDevice(id=0, simdata=simdata, action=silent)


class ModbusDeviceServer:
    """A pymodbus Modbus TCP server on loopback serving ``devices`` (device id → model).

    Use as a context manager, or ``start()``/``stop()``. ``port=0`` takes a free port (read it
    from ``port`` after starting); a restart reuses the port it got, so clients can reconnect.
    ``silence(device_id)`` makes a device stop answering (fault injection: a device that hangs
    or lost power behind a gateway) until ``silence(device_id, False)``.
    """

    def __init__(
        self,
        devices: Mapping[int, RegisterDevice],
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        start_timeout_s: float = 5.0,
    ):
        check_loopback(host)
        if not devices:
            raise ValueError("ModbusDeviceServer needs at least one device")
        self.host = host
        self._port = int(port)
        self._devices = dict(devices)
        self._start_timeout_s = start_timeout_s
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: ModbusTcpServer | None = None
        self._stopped: asyncio.Event | None = None
        self._silent: set[int] = set()

    def silence(self, device_id: int, silent: bool = True) -> None:
        """Device ``device_id`` answers no request while ``silent`` (requests wait, unanswered)."""
        if device_id not in self._devices:
            raise ValueError(f"no device {device_id} on this server")
        if silent:
            self._silent.add(device_id)
        else:
            self._silent.discard(device_id)

    def _is_silent(self, device_id: int) -> Callable[[], bool]:
        return lambda: (
            device_id in self._silent and not (self._stopped is not None and self._stopped.is_set())
        )

    @property
    def port(self) -> int:
        if self._port == 0:
            raise RuntimeError("the server has not started yet; its port is not known")
        return self._port

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self) -> ModbusDeviceServer:
        if self.running:
            return self
        ready = threading.Event()
        failure: list[BaseException] = []
        self._thread = threading.Thread(
            target=self._serve, args=(ready, failure), name="modbus-sim-server", daemon=True
        )
        self._thread.start()
        if not ready.wait(self._start_timeout_s):
            raise DeviceError(f"Modbus simulator on {self.host}:{self._port} did not start")
        if failure:
            self._thread.join(1.0)
            raise DeviceError(
                f"Modbus simulator could not listen on {self.host}:{self._port}: {failure[0]}"
            )
        return self

    def stop(self) -> None:
        """Close the listener and every client connection, and join the server thread."""
        thread, loop, stopped = self._thread, self._loop, self._stopped
        if thread is None or loop is None or stopped is None:
            return
        if thread.is_alive():
            loop.call_soon_threadsafe(stopped.set)
            thread.join(self._start_timeout_s)
        self._thread = self._loop = self._server = self._stopped = None

    def __enter__(self) -> ModbusDeviceServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _serve(self, ready: threading.Event, failure: list[BaseException]) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        try:
            loop.run_until_complete(self._main(ready, failure))
        finally:
            loop.close()
            ready.set()

    async def _main(self, ready: threading.Event, failure: list[BaseException]) -> None:
        self._stopped = asyncio.Event()
        try:
            devices = [_sim_device(i, d, self._is_silent(i)) for i, d in self._devices.items()]
            if 0 not in self._devices:
                devices.append(_absent_devices(list(self._devices.values())))
            server = ModbusTcpServer(devices, address=(self.host, self._port))
            await server.serve_forever(background=True)
            if server.transport is None:
                raise OSError("the listener did not open (address in use?)")
        except Exception as exc:
            failure.append(exc)
            ready.set()
            return
        self._server = server
        self._port = server.transport.sockets[0].getsockname()[1]
        ready.set()
        await self._stopped.wait()
        await server.shutdown()


class DirectLink:
    """``RegisterLink`` calling a ``RegisterDevice`` in-process (no sockets), with the same error
    types as ``ModbusTcpLink``; ``drop()``/``restore()`` simulate a lost link."""

    def __init__(self, device: RegisterDevice, name: str = "simulated device"):
        self._device = device
        self._name = name
        self._connected = False
        self._dropped = False

    @property
    def description(self) -> str:
        return f"in-process {self._name}"

    def connect(self) -> None:
        if self._dropped:
            raise DeviceTimeout(f"{self.description}: no answer (link dropped)")
        self._connected = True

    def close(self) -> None:
        self._connected = False

    def drop(self) -> None:
        self._dropped = True

    def restore(self) -> None:
        self._dropped = False

    def read_holding(self, address: int, count: int) -> list[int]:
        return self._call(
            f"reading {count} holding registers at {address}", READ_HOLDING, address, count
        )

    def read_input(self, address: int, count: int) -> list[int]:
        return self._call(
            f"reading {count} input registers at {address}", READ_INPUT, address, count
        )

    def write(self, address: int, values: Sequence[int]) -> None:
        self._call(f"writing {len(values)} registers at {address}", WRITE_MULTIPLE, address, values)

    def _call(self, what: str, function_code: int, address: int, arg):
        what = f"{self.description}: {what}"
        if self._dropped:
            raise DeviceTimeout(f"{what}: no answer (link dropped)")
        if not self._connected:
            raise DeviceError(f"{what}: not connected (call connect())")
        try:
            if function_code == WRITE_MULTIPLE:
                self._device.write_registers(address, [int(v) & 0xFFFF for v in arg])
                return None
            return self._device.read_registers(function_code, address, int(arg))
        except RegisterAccessError as exc:
            raise exception_error(exc.code, what) from None
