"""A register link that records what a driver writes and answers reads from a register image:
the drivers' encodings checked word by word, in-process (fast enough for mutation testing)."""

from __future__ import annotations

from collections.abc import Sequence

from drivers.base import DeviceError


class RecordingLink:
    """``RegisterLink`` over a dict of input registers; writes are recorded as (address,
    values). ``refuse`` makes writes raise it; ``unreadable`` makes reads raise it."""

    description = "recording link"

    def __init__(self, inputs: dict[int, int] | None = None):
        self.inputs = dict(inputs or {})
        self.writes: list[tuple[int, list[int]]] = []
        self.connected = False
        self.closed = False
        self.refuse: DeviceError | None = None
        self.unreadable: DeviceError | None = None

    def connect(self) -> None:
        self.connected = True

    def close(self) -> None:
        self.closed = True

    def read_holding(self, address: int, count: int) -> list[int]:
        return self.read_input(address, count)

    def read_input(self, address: int, count: int) -> list[int]:
        if self.unreadable is not None:
            raise self.unreadable
        return [self.inputs.get(a, 0) for a in range(address, address + count)]

    def write(self, address: int, values: Sequence[int]) -> None:
        if self.refuse is not None:
            raise self.refuse
        self.writes.append((address, list(values)))
