"""Bounded checks that a UR controller answers, run before any ur-rtde constructor.

Why: ur-rtde's ``RTDEReceiveInterface`` and ``RTDEControlInterface`` constructors read the
controller's replies with no time-out and hold the GIL while they wait (measured: a thread
constructing one against a server that accepts but never answers freezes every other thread of
the process). A deadline enforced by another thread cannot fire, and the object cannot be built
in another process and used in this one. So the driver first walks the same steps the
constructors will — TCP connect, protocol version, controller version, an output recipe, start,
the first data package — over a plain socket whose every read has the remaining deadline, and
constructs ur-rtde's interfaces only when the controller has just answered all of them. What is
left unguarded is a controller that stops answering in the few milliseconds between the probe
and the constructor.
"""

from __future__ import annotations

import socket
import time
from dataclasses import dataclass

from drivers import rtde_protocol as rtde
from drivers.base import DeviceError, DeviceTimeout

RTDE_PORT = 30004
SCRIPT_PORT = 30003
DASHBOARD_PORT = 29999


@dataclass(frozen=True, slots=True)
class RTDEProbe:
    """What the probe learnt: the controller's version and how long the walk took (s)."""

    controller_version: tuple[int, int, int, int]
    elapsed_s: float


class _Deadline:
    def __init__(self, timeout_s: float):
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be positive; got {timeout_s}")
        self.timeout_s = timeout_s
        self.end = time.monotonic() + timeout_s

    def remaining(self) -> float:
        return max(self.end - time.monotonic(), 1e-3)


def probe_port(host: str, port: int, *, timeout_s: float, what: str) -> None:
    """Open and close a TCP connection to ``host:port`` within ``timeout_s``.

    Raises ``DeviceTimeout`` when nothing answers in time and ``DeviceError`` when the connection
    is refused (nothing listens) or the address is unusable."""
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            pass
    except TimeoutError:
        raise DeviceTimeout(
            f"UR {host}: the {what} port {port} did not answer within {timeout_s:g} s"
        ) from None
    except ConnectionRefusedError:
        raise DeviceError(
            f"UR {host}: the {what} port {port} refused the connection "
            "(controller off, wrong address, or a link drop)"
        ) from None
    except OSError as exc:
        raise DeviceError(f"UR {host}: cannot reach the {what} port {port}: {exc}") from None


def probe_rtde(host: str, *, timeout_s: float, port: int = RTDE_PORT) -> RTDEProbe:
    """Walk the RTDE handshake up to the first data package within ``timeout_s`` in total.

    Raises ``DeviceTimeout`` naming the step that got no answer, ``DeviceError`` for a refused
    connection or a reply that is not RTDE."""
    deadline = _Deadline(timeout_s)
    start = time.monotonic()
    try:
        sock = socket.create_connection((host, port), timeout=deadline.remaining())
    except TimeoutError:
        raise DeviceTimeout(
            f"UR {host}: RTDE port {port}: no connection within {timeout_s:g} s"
        ) from None
    except ConnectionRefusedError:
        raise DeviceError(
            f"UR {host}: RTDE port {port} refused the connection "
            "(controller off, wrong address, or a link drop)"
        ) from None
    except OSError as exc:
        raise DeviceError(f"UR {host}: cannot reach RTDE port {port}: {exc}") from None
    with sock:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        link = _Link(sock, host, deadline)
        link.send(rtde.encode_version_request())
        if not rtde.decode_accepted(link.expect(rtde.Message.REQUEST_PROTOCOL_VERSION, "version")):
            raise DeviceError(f"UR {host}: the controller refused RTDE protocol version 2")
        link.send(rtde.encode(rtde.Message.GET_URCONTROL_VERSION))
        version = rtde.decode_controller_version(
            link.expect(rtde.Message.GET_URCONTROL_VERSION, "controller version")
        )
        link.send(rtde.encode_output_setup(10.0, ["timestamp"]))
        _, types = rtde.decode_setup_reply(link.expect(rtde.Message.SETUP_OUTPUTS, "output setup"))
        if types != ["DOUBLE"]:
            raise DeviceError(f"UR {host}: RTDE output 'timestamp' answered as {types}")
        link.send(rtde.encode(rtde.Message.START))
        if not rtde.decode_accepted(link.expect(rtde.Message.START, "start")):
            raise DeviceError(f"UR {host}: the controller refused to start RTDE synchronisation")
        link.expect(rtde.Message.DATA_PACKAGE, "first data package")
        link.send(rtde.encode(rtde.Message.PAUSE))  # polite; the reply is not waited for
    return RTDEProbe(controller_version=version, elapsed_s=time.monotonic() - start)


class _Link:
    def __init__(self, sock: socket.socket, host: str, deadline: _Deadline):
        self._sock = sock
        self._host = host
        self._deadline = deadline
        self._reader = rtde.MessageReader()
        self._pending: list[tuple[int, bytes]] = []

    def send(self, data: bytes) -> None:
        self._sock.settimeout(self._deadline.remaining())
        try:
            self._sock.sendall(data)
        except OSError as exc:
            raise DeviceError(f"UR {self._host}: RTDE send failed: {exc}") from None

    def expect(self, kind: int, step: str) -> bytes:
        """The payload of the next message of type ``kind`` (text messages are skipped)."""
        while True:
            while self._pending:
                got, payload = self._pending.pop(0)
                if got == kind:
                    return payload
                if got not in (rtde.Message.TEXT_MESSAGE, rtde.Message.DATA_PACKAGE):
                    raise DeviceError(
                        f"UR {self._host}: RTDE {step}: expected message {chr(kind)!r}, "
                        f"got {chr(got)!r}"
                    )
            self._sock.settimeout(self._deadline.remaining())
            try:
                data = self._sock.recv(65536)
            except TimeoutError:
                raise DeviceTimeout(
                    f"UR {self._host}: RTDE {step}: no answer within "
                    f"{self._deadline.timeout_s:g} s (controller stalled?)"
                ) from None
            except OSError as exc:
                raise DeviceError(f"UR {self._host}: RTDE {step}: {exc}") from None
            if not data:
                raise DeviceError(f"UR {self._host}: RTDE {step}: the controller closed the link")
            try:
                self._pending.extend(self._reader.feed(data))
            except rtde.RTDEProtocolError as exc:
                raise DeviceError(f"UR {self._host}: RTDE {step}: {exc}") from None
