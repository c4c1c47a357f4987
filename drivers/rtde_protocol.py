"""The RTDE wire format (Universal Robots' Real-Time Data Exchange, protocol version 2).

Shared by the UR driver's bounded reachability probe (``drivers.ur_probe``) and the loopback UR
controller emulator (``sim_backends.ur_emulator``), so both sides of the wire read one
definition. Source: UR's "Real-Time Data Exchange (RTDE) Guide" (message types, data types,
setup replies); read for understanding only.

A message is ``uint16 size`` (the whole message, 3-byte header included) + ``uint8 type`` +
payload, big-endian. Types used here:

* ``V`` request protocol version: uint16 version → reply uint8 accepted;
* ``v`` controller version: reply 4 × uint32 (major, minor, bugfix, build);
* ``O`` set up outputs: double frequency (Hz) + comma-separated names → reply uint8 recipe id +
  comma-separated types (``NOT_FOUND`` for an unknown name);
* ``I`` set up inputs: comma-separated names → reply uint8 recipe id + types (``IN_USE`` for a
  variable another client or a fieldbus owns);
* ``S`` start / ``P`` pause synchronisation → reply uint8 accepted;
* ``U`` data package: uint8 recipe id + the recipe's values packed in order;
* ``M`` text message.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from enum import IntEnum


class RTDEProtocolError(ValueError):
    """Bytes that do not follow the RTDE wire format."""


class Message(IntEnum):
    """RTDE message types (the ASCII letter of each)."""

    REQUEST_PROTOCOL_VERSION = ord("V")
    GET_URCONTROL_VERSION = ord("v")
    TEXT_MESSAGE = ord("M")
    DATA_PACKAGE = ord("U")
    SETUP_OUTPUTS = ord("O")
    SETUP_INPUTS = ord("I")
    START = ord("S")
    PAUSE = ord("P")


PROTOCOL_VERSION = 2
HEADER = struct.Struct(">HB")
MAX_MESSAGE = 0xFFFF

#: struct format of each RTDE data type (big-endian, no padding).
TYPE_FORMATS: dict[str, str] = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}
#: How many numbers one value of each type holds (vectors are tuples).
TYPE_WIDTH = {name: int(fmt[:-1]) if len(fmt) > 1 else 1 for name, fmt in TYPE_FORMATS.items()}
NOT_FOUND = "NOT_FOUND"
IN_USE = "IN_USE"


def encode(kind: int, payload: bytes = b"") -> bytes:
    """One message of type ``kind`` carrying ``payload``."""
    size = HEADER.size + len(payload)
    if size > MAX_MESSAGE:
        raise RTDEProtocolError(f"RTDE message of {size} bytes exceeds {MAX_MESSAGE}")
    return HEADER.pack(size, int(kind)) + payload


class MessageReader:
    """Splits a byte stream into ``(type, payload)`` messages; keeps a partial one for later."""

    def __init__(self) -> None:
        self._buffer = bytearray()

    def feed(self, data: bytes) -> list[tuple[int, bytes]]:
        self._buffer += data
        messages = []
        while len(self._buffer) >= HEADER.size:
            size, kind = HEADER.unpack_from(self._buffer)
            if size < HEADER.size:
                raise RTDEProtocolError(f"RTDE header announces {size} bytes (< 3)")
            if len(self._buffer) < size:
                break
            messages.append((kind, bytes(self._buffer[HEADER.size : size])))
            del self._buffer[:size]
        return messages


class RecipeCodec:
    """Packs and unpacks the data packages of one recipe (a list of RTDE type names)."""

    def __init__(self, types: Sequence[str]):
        unknown = [t for t in types if t not in TYPE_FORMATS]
        if unknown:
            raise RTDEProtocolError(f"unknown RTDE data types {unknown}")
        self.types = tuple(types)
        self._struct = struct.Struct(">B" + "".join(TYPE_FORMATS[t] for t in self.types))
        self._widths = [TYPE_WIDTH[t] for t in self.types]

    @property
    def size(self) -> int:
        """Bytes of a data payload (recipe id included)."""
        return self._struct.size

    def pack(self, recipe_id: int, values: Sequence) -> bytes:
        """A complete ``U`` message; vector values are sequences of their width."""
        if len(values) != len(self.types):
            raise RTDEProtocolError(f"recipe needs {len(self.types)} values; got {len(values)}")
        flat: list = []
        for value, width in zip(values, self._widths, strict=True):
            if width == 1:
                flat.append(value)
            else:
                flat.extend(value)
        return encode(Message.DATA_PACKAGE, self._struct.pack(recipe_id, *flat))

    def unpack(self, payload: bytes) -> tuple[int, list]:
        """(recipe id, values) of a ``U`` payload; vectors come back as tuples."""
        if len(payload) != self._struct.size:
            raise RTDEProtocolError(
                f"data package of {len(payload)} bytes does not match its recipe "
                f"({self._struct.size} bytes)"
            )
        flat = self._struct.unpack(payload)
        values, i = [], 1
        for width in self._widths:
            values.append(flat[i] if width == 1 else tuple(flat[i : i + width]))
            i += width
        return flat[0], values


# --- setup and control messages -------------------------------------------------------------


def names_payload(names: Sequence[str]) -> bytes:
    return ",".join(names).encode("ascii")


def decode_names(payload: bytes) -> list[str]:
    """Comma-separated variable names (ur-rtde ends its list with a comma)."""
    text = payload.decode("ascii", errors="replace")
    return [name.strip() for name in text.split(",") if name.strip()]


def encode_output_setup(frequency_hz: float, names: Sequence[str]) -> bytes:
    return encode(Message.SETUP_OUTPUTS, struct.pack(">d", frequency_hz) + names_payload(names))


def decode_output_setup(payload: bytes) -> tuple[float, list[str]]:
    if len(payload) < 8:
        raise RTDEProtocolError("output setup shorter than its frequency field")
    (frequency,) = struct.unpack_from(">d", payload)
    return frequency, decode_names(payload[8:])


def encode_setup_reply(kind: int, recipe_id: int, types: Sequence[str]) -> bytes:
    return encode(kind, bytes([recipe_id]) + names_payload(types))


def decode_setup_reply(payload: bytes) -> tuple[int, list[str]]:
    if not payload:
        raise RTDEProtocolError("empty setup reply")
    return payload[0], decode_names(payload[1:])


def encode_accepted(kind: int, accepted: bool) -> bytes:
    return encode(kind, bytes([1 if accepted else 0]))


def decode_accepted(payload: bytes) -> bool:
    if not payload:
        raise RTDEProtocolError("empty reply where an accepted flag was expected")
    return payload[0] != 0


def encode_version_request(version: int = PROTOCOL_VERSION) -> bytes:
    return encode(Message.REQUEST_PROTOCOL_VERSION, struct.pack(">H", version))


def decode_version_request(payload: bytes) -> int:
    if len(payload) != 2:
        raise RTDEProtocolError("protocol-version request must carry a uint16")
    return struct.unpack(">H", payload)[0]


def encode_controller_version(version: Sequence[int]) -> bytes:
    return encode(Message.GET_URCONTROL_VERSION, struct.pack(">4I", *version))


def decode_controller_version(payload: bytes) -> tuple[int, int, int, int]:
    if len(payload) != 16:
        raise RTDEProtocolError("controller version must be 4 × uint32")
    return struct.unpack(">4I", payload)
