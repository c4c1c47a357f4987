"""The script port (30003): clients write URScript; nothing is read back by ur-rtde.

A program is a top-level ``def name():`` up to its top-level ``end``, which is how ur-rtde sends
its control script. Text outside a program (single statements) is reported as such; the
emulator does not run arbitrary URScript.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

_DEF = re.compile(r"^def\s+(\w+)\s*\(\s*\)\s*:")


@dataclass(frozen=True, slots=True)
class ScriptText:
    """A complete program (``name`` set) or a stray statement (``name`` None)."""

    name: str | None
    text: str


class ScriptCollector:
    """Turns the bytes of one connection into complete programs and stray statements."""

    def __init__(self) -> None:
        self._partial = ""
        self._program: list[str] | None = None
        self._name: str | None = None

    def feed(self, data: bytes) -> list[ScriptText]:
        self._partial += data.decode("utf-8", errors="replace")
        *lines, self._partial = self._partial.split("\n")
        found = []
        for line in lines:
            if self._program is None:
                match = _DEF.match(line)
                if match:
                    self._program, self._name = [line], match.group(1)
                elif line.strip() and not line.lstrip().startswith("#"):
                    found.append(ScriptText(None, line))
                continue
            self._program.append(line)
            if line.rstrip() == "end":  # the top-level end closes the program
                found.append(ScriptText(self._name, "\n".join(self._program) + "\n"))
                self._program, self._name = None, None
        return found
