"""One RTDE client session on the emulated controller (port 30004).

A session negotiates the protocol version, sets up one output recipe and any number of input
recipes, starts and pauses synchronisation, writes inputs with data packages and receives the
output recipe at its requested frequency. Replies follow the RTDE guide: ``NOT_FOUND`` for an
output the controller does not know, ``IN_USE`` for an input another session (or a fieldbus,
by fault injection) owns, recipe ids 1, 2, 3… in setup order per kind (ur-rtde assumes this for
its inputs).
"""

from __future__ import annotations

from collections.abc import Callable

from drivers import rtde_protocol as rtde
from sim_backends.ur_emulator.command_log import CommandLog
from sim_backends.ur_emulator.controller import EmulatedController
from sim_backends.ur_emulator.rtde_variables import INPUTS, OUTPUTS

#: What the emulated controller reports as its software version (PolyScope 5.15, e-Series).
CONTROLLER_VERSION = (5, 15, 0, 0)
MAX_FREQUENCY_HZ = 500.0


class InputOwnership:
    """Which session owns each input variable; a variable has one writer at a time."""

    def __init__(self) -> None:
        self._owner: dict[str, object] = {}

    def claim(self, owner: object, names: list[str]) -> bool:
        if any(self._owner.get(name, owner) is not owner for name in names):
            return False
        for name in names:
            self._owner[name] = owner
        return True

    def owner(self, name: str) -> object | None:
        return self._owner.get(name)

    def release(self, owner: object) -> None:
        self._owner = {name: o for name, o in self._owner.items() if o is not owner}


class RTDESession:
    """The protocol state of one connection; ``handle`` answers a message, ``data_package``
    produces the next output package when one is due."""

    def __init__(
        self,
        controller: EmulatedController,
        ownership: InputOwnership,
        log: CommandLog,
        *,
        peer: str,
        clock: Callable[[], float],
    ):
        self.controller = controller
        self.ownership = ownership
        self.log = log
        self.peer = peer
        self._clock = clock
        self.started = False
        self._output_names: list[str] = []
        self._output_getters: list[Callable] = []
        self._output_codec: rtde.RecipeCodec | None = None
        self._output_id = 0
        self._output_period = 0.0
        self._next_output_time = 0.0
        self._inputs: dict[int, tuple[list[str], rtde.RecipeCodec]] = {}
        self.packages_sent = 0

    # --- requests ---------------------------------------------------------------------------
    def handle(self, kind: int, payload: bytes) -> bytes | None:
        """The reply to one message (None when the message needs none)."""
        try:
            return self._handle(kind, payload)
        except rtde.RTDEProtocolError as exc:
            self.log.add(self._clock(), "rtde", "bad message", detail=f"{self.peer}: {exc}")
            return None

    def _handle(self, kind: int, payload: bytes) -> bytes | None:
        M = rtde.Message
        if kind == M.REQUEST_PROTOCOL_VERSION:
            # version 2 only: version 1's setup messages differ (no output frequency)
            accepted = rtde.decode_version_request(payload) == rtde.PROTOCOL_VERSION
            return rtde.encode_accepted(kind, accepted)
        if kind == M.GET_URCONTROL_VERSION:
            return rtde.encode_controller_version(CONTROLLER_VERSION)
        if kind == M.SETUP_OUTPUTS:
            return self._setup_outputs(payload)
        if kind == M.SETUP_INPUTS:
            return self._setup_inputs(payload)
        if kind == M.START:
            accepted = self._output_codec is not None or bool(self._inputs)
            self.started = accepted
            self._next_output_time = self.controller.timestamp
            self.log.add(self._clock(), "rtde", "start", detail=self.peer)
            return rtde.encode_accepted(kind, accepted)
        if kind == M.PAUSE:
            self.started = False
            self.log.add(self._clock(), "rtde", "pause", detail=self.peer)
            return rtde.encode_accepted(kind, True)
        if kind == M.DATA_PACKAGE:
            self._apply_inputs(payload)
            return None
        if kind == M.TEXT_MESSAGE:
            return None
        self.log.add(self._clock(), "rtde", "unknown message", detail=f"{self.peer}: {kind}")
        return None

    def _setup_outputs(self, payload: bytes) -> bytes:
        frequency, names = rtde.decode_output_setup(payload)
        types = [OUTPUTS[name][0] if name in OUTPUTS else rtde.NOT_FOUND for name in names]
        valid = bool(names) and rtde.NOT_FOUND not in types and 0 < frequency <= MAX_FREQUENCY_HZ
        detail = f"{self.peer}: {len(names)} variables at {frequency:g} Hz"
        if not valid:
            missing = [n for n, t in zip(names, types, strict=True) if t == rtde.NOT_FOUND]
            detail += f"; refused (not found: {missing}, frequency {frequency:g})"
            self.log.add(self._clock(), "rtde", "output setup", detail=detail)
            return rtde.encode_setup_reply(rtde.Message.SETUP_OUTPUTS, 0, types)
        self._output_id += 1
        self._output_names = names
        self._output_getters = [OUTPUTS[name][1] for name in names]
        self._output_codec = rtde.RecipeCodec(types)
        self._output_period = 1.0 / frequency
        self.log.add(self._clock(), "rtde", "output setup", detail=detail)
        return rtde.encode_setup_reply(rtde.Message.SETUP_OUTPUTS, self._output_id, types)

    def _setup_inputs(self, payload: bytes) -> bytes:
        names = rtde.decode_names(payload)
        types = [INPUTS.get(name, rtde.NOT_FOUND) for name in names]
        if rtde.NOT_FOUND in types or not names:
            return rtde.encode_setup_reply(rtde.Message.SETUP_INPUTS, 0, types)
        if not self.ownership.claim(self, names):
            types = [
                rtde.IN_USE if self.ownership.owner(n) not in (None, self) else t
                for n, t in zip(names, types, strict=True)
            ]
            self.log.add(self._clock(), "rtde", "input setup refused", detail=f"IN_USE: {names}")
            return rtde.encode_setup_reply(rtde.Message.SETUP_INPUTS, 0, types)
        recipe_id = len(self._inputs) + 1
        self._inputs[recipe_id] = (names, rtde.RecipeCodec(types))
        return rtde.encode_setup_reply(rtde.Message.SETUP_INPUTS, recipe_id, types)

    def _apply_inputs(self, payload: bytes) -> None:
        if not payload:
            raise rtde.RTDEProtocolError("empty data package")
        recipe = self._inputs.get(payload[0])
        if recipe is None:
            raise rtde.RTDEProtocolError(f"data package for unknown input recipe {payload[0]}")
        names, codec = recipe
        _, values = codec.unpack(payload)
        self.controller.write_inputs(names, values)

    # --- outputs ----------------------------------------------------------------------------
    def data_package(self) -> bytes | None:
        """The output package when started and due at the recipe's frequency, else None."""
        if not self.started or self._output_codec is None:
            return None
        now = self.controller.timestamp
        if now + 1e-9 < self._next_output_time:
            return None
        self._next_output_time = max(self._next_output_time + self._output_period, now)
        values = [getter(self.controller) for getter in self._output_getters]
        self.packages_sent += 1
        return self._output_codec.pack(self._output_id, values)

    def close(self) -> None:
        self.ownership.release(self)
