"""Faults of the link between a client and the emulated controller, injected from the test side.

* dropped link: every connection is closed and the ports stop listening (a client's connect is
  refused) until the link is restored — a pulled cable or a rebooting controller;
* stalled outputs: connections stay open but nothing is sent — no data packages, no replies to
  RTDE requests or dashboard lines — while inputs are still received: a hung publisher;
* jitter: each data package leaves up to ``jitter_s`` late (uniform, seeded), so clients see
  irregular state updates as on a loaded network.

Controller-side faults (protective stop, emergency stop, a wrench at the TCP) live on the
controller itself; ``InputOwnership`` lets a test claim inputs as a fieldbus would (``IN_USE``).
"""

from __future__ import annotations

import random
from dataclasses import dataclass, field


@dataclass
class LinkFaults:
    dropped: bool = False
    stalled: bool = False
    jitter_s: float = 0.0
    seed: int = 0
    _rng: random.Random = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._rng = random.Random(self.seed)

    def set_jitter(self, jitter_s: float, seed: int | None = None) -> None:
        if not (0.0 <= jitter_s <= 1.0):
            raise ValueError(f"jitter_s must be within [0, 1] s; got {jitter_s}")
        self.jitter_s = float(jitter_s)
        if seed is not None:
            self._rng.seed(seed)

    def publish_delay(self) -> float:
        """How late (s) the next data package leaves."""
        return self._rng.uniform(0.0, self.jitter_s) if self.jitter_s > 0 else 0.0
