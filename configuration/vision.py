"""The vision pipeline beside the control loop: how frames become fused measurements.

Every model is frozen and rejects unknown keys.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from configuration.base import Strict

#: Time per frame of each system (ms) on the 2-core development machine, 2026-12-02 (after
#: issue 12's image stack, solver and compiled fits): tracking (with a prior), the medians of
#: the estimators' own ``time_ms`` over a closed-loop approach (``satgrasp approach --seed 1``,
#: low noise, nothing else running); acquisition (a search of the whole image), the median of
#: the VGA cells of ``satgrasp bench report`` (docs/benchmarks.md; a closed-loop approach
#: acquires too rarely to measure it). What ``--clock sim`` charges. Re-measure after a change
#: to the estimators (docs/realtime.md).
BENCH_PROCESSING_MS = {"corners": 38.0, "lines": 47.0, "ellipses": 45.0}
BENCH_ACQUISITION_MS = {"corners": 173.0, "lines": 193.0, "ellipses": 129.0}


class CameraTiming(Strict):
    """When frames are taken and when they reach the host: ``fps`` frames a second, each
    delivered ``latency_s`` ± ``jitter_s`` (uniform) after its mid-exposure — a real OAK
    delivers 100–130 ms late. The simulated camera follows this; a real one is measured."""

    fps: Annotated[float, Field(gt=0.0, le=120.0)] = 15.0
    latency_s: Annotated[float, Field(ge=0.0, le=2.0)] = 0.12
    jitter_s: Annotated[float, Field(ge=0.0, le=0.5)] = 0.01


class VisionConfig(Strict):
    """The pipeline: each system takes the newest frame whenever it is free.

    ``fuse_at``: ``capture`` applies a measurement at its frame's capture stamp with the
    camera-to-carriage pose of that instant (the right way); ``arrival`` applies it when it
    reaches fusion, with the pose of then — kept to show what the delayed update buys.
    ``max_frame_age_s``: a result whose frame is older than this when it comes is not fused (no
    stale frame is acted on; its pose may still seed the system's next search).
    ``processing_ms`` / ``acquisition_ms``: per system, the time charged under ``--clock sim`` for
    a frame with a prior / without one (a system not listed is charged its ``bench`` figure, or
    40 / 150 ms); under ``--clock wall`` the real time counts. ``workers``: ``process`` runs each system in a process
    of its own (pybullet and the estimators hold the GIL); ``inline`` runs them in the vision
    process one after the other (for comparison in ``satgrasp bench loop``).
    ``concurrent_estimators``: at most this many systems process a frame at once; ``auto`` runs
    every system at once under ``--clock sim`` (the modelled rig has a core per system) and,
    under ``--clock wall``, as many as there are cores beside the control loop's. On a machine
    with fewer cores than estimators, running them all at once only makes each result later
    (they take turns on the same cores), and a later result is a staler one.
    ``log_frames_every_s``: frames kept in the trial log (0 keeps none).
    ``repeat_motion_m`` / ``repeat_motion_deg``: a camera whose image stays byte for byte the
    same while the camera moved this far relative to the carriage (or turned this much) since
    the image first appeared is frozen (a live sensor's noise alone changes every frame; a
    noiseless simulated view of a still scene does not, hence the motion).
    """

    fuse_at: Literal["capture", "arrival"] = "capture"
    max_frame_age_s: Annotated[float, Field(gt=0.0, le=5.0)] = 0.25
    processing_ms: dict[str, Annotated[float, Field(ge=0.0, le=10000.0)]] = Field(
        default_factory=lambda: dict(BENCH_PROCESSING_MS)
    )
    acquisition_ms: dict[str, Annotated[float, Field(ge=0.0, le=10000.0)]] = Field(
        default_factory=lambda: dict(BENCH_ACQUISITION_MS)
    )
    workers: Literal["process", "inline"] = "process"
    concurrent_estimators: Annotated[int, Field(ge=1)] | Literal["auto"] = "auto"
    log_frames_every_s: Annotated[float, Field(ge=0.0)] = 1.0
    repeat_motion_m: Annotated[float, Field(gt=0.0)] = 0.005
    repeat_motion_deg: Annotated[float, Field(gt=0.0)] = 0.5

    def estimator_slots(self, systems: int, cores: int | None) -> int:
        """How many of ``systems`` may process a frame at once, on a machine with ``cores``
        usable cores (``--clock wall``) or on the modelled rig (``cores`` None, ``--clock sim``)."""
        if self.concurrent_estimators != "auto":
            return min(systems, self.concurrent_estimators)
        if cores is None:
            return systems
        return max(1, min(systems, cores - 1))

    def processing_s(self, system: str, *, acquiring: bool = False) -> float:
        """Modelled time (s) ``system`` takes over a frame, with a prior or searching without."""
        if acquiring:
            ms = self.acquisition_ms.get(system, BENCH_ACQUISITION_MS.get(system, 150.0))
        else:
            ms = self.processing_ms.get(system, BENCH_PROCESSING_MS.get(system, 40.0))
        return ms / 1000.0
