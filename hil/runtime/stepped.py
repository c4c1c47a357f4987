"""``--clock sim``: time stands still while the control loop computes; sleeping until the next
deadline steps the simulated world and the vision pipeline to it.

The loop cannot tell this clock from the monotonic one: it calls ``now`` and ``sleep_until``.
The vision pipeline is charged modelled processing times (``InlineWorkers``), so what the loop
sees — frames 120 ms late, results another few tens of milliseconds later, out of order across
systems — is what the rig would show it, and the run is deterministic for a seed.
"""

from __future__ import annotations

import contextlib
from typing import Protocol

from drivers.base import Camera, DeviceTimeout
from drivers.clock import SimClock
from hil.runtime.vision import VisionPipeline


class SteppedWorld(Protocol):
    """A simulated world that advances its devices and its clock together."""

    clock: SimClock

    def advance(self, dt: float) -> None: ...


class SteppedClock:
    """The simulated clock of a world, stepping ``world`` and ``vision`` in ``step_s`` steps."""

    real_time = False

    def __init__(
        self, world: SteppedWorld, camera: Camera, vision: VisionPipeline, *, step_s: float
    ) -> None:
        if not step_s > 0:
            raise ValueError(f"step_s must be positive; got {step_s}")
        self.world, self.camera, self.vision, self.step_s = world, camera, vision, step_s

    def now(self) -> float:
        return self.world.clock.now()

    def work_time(self) -> float:
        return self.world.clock.work_time()

    def sleep_until(self, t: float) -> None:
        while (now := self.world.clock.now()) < t - 1e-12:
            self.world.advance(min(self.step_s, t - now))
            self.pump(self.world.clock.now())

    def pump(self, now: float) -> None:
        """Hand the camera's newest frame (if a new one arrived) to the pipeline and step it."""
        with contextlib.suppress(DeviceTimeout):
            self.vision.on_frame(self.camera.read(timeout_s=0.0), now)
        self.vision.step(now)
