"""What a trial yields per cell, and a cell's statistics pooled over its trials.

A ``Series`` is one system's answers through one trial, in time order: when (s), whether it
was valid, the errors it had against ground truth (m, rad; NaN when not judged) and its latency
(ms; NaN when not modelled). Translation error is the Euclidean norm of the position error and
rotation error the norm of roll/pitch/yaw of R_true·R_estᵀ — the reference study's metrics (for
the ellipse system the circle's centre and the angle between normals, as there).

A *loss* is a run of invalid answers; it is *re-acquired* when a valid answer follows it in the
same trial, after the time between the last valid answer before it and the first after.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

NAN = float("nan")


@dataclass(frozen=True, slots=True)
class Series:
    t: tuple[float, ...]
    valid: tuple[bool, ...]
    position_m: tuple[float, ...]
    attitude_rad: tuple[float, ...]
    latency_ms: tuple[float, ...] = ()

    def to_dict(self) -> dict:
        def listed(values):
            return [None if isinstance(v, float) and math.isnan(v) else v for v in values]

        return {
            "t": list(self.t),
            "valid": list(self.valid),
            "position_m": listed(self.position_m),
            "attitude_rad": listed(self.attitude_rad),
            "latency_ms": listed(self.latency_ms),
        }

    @staticmethod
    def from_dict(data: dict) -> Series:
        def floats(values):
            return tuple(NAN if v is None else float(v) for v in values)

        return Series(
            tuple(float(v) for v in data["t"]),
            tuple(bool(v) for v in data["valid"]),
            floats(data["position_m"]),
            floats(data["attitude_rad"]),
            floats(data.get("latency_ms", [])),
        )


@dataclass(frozen=True, slots=True)
class Losses:
    episodes: int
    reacquired: int
    reacquire_times_s: tuple[float, ...]


def losses(series: Series) -> Losses:
    """Loss episodes of one trial (a trial that starts without a valid answer has not lost
    anything yet: runs before the first valid answer are acquisition, not loss)."""
    episodes = reacquired = 0
    times: list[float] = []
    last_valid_t: float | None = None
    in_loss = False
    for t, valid in zip(series.t, series.valid, strict=True):
        if valid:
            if in_loss:
                reacquired += 1
                times.append(t - last_valid_t)
                in_loss = False
            last_valid_t = t
        elif last_valid_t is not None and not in_loss:
            episodes += 1
            in_loss = True
    return Losses(episodes, reacquired, tuple(times))


@dataclass(frozen=True, slots=True)
class CellStats:
    """Statistics of one cell over the answers of all its trials (errors over the valid,
    judged answers)."""

    trials: int
    samples: int
    valid: int
    translation_mean_m: float
    translation_std_m: float
    translation_median_m: float
    translation_p95_m: float
    rotation_mean_deg: float
    rotation_std_deg: float
    rotation_median_deg: float
    rotation_p95_deg: float
    lost: int
    loss_episodes: int
    reacquired: int
    reacquire_time_mean_s: float
    reacquire_time_max_s: float
    latency_mean_ms: float
    latency_p95_ms: float


def _moments(values: np.ndarray) -> tuple[float, float, float, float]:
    finite = values[np.isfinite(values)]
    if not len(finite):
        return NAN, NAN, NAN, NAN
    return (
        float(finite.mean()),
        float(finite.std()),
        float(np.median(finite)),
        float(np.percentile(finite, 95)),
    )


def cell_stats(series: Sequence[Series]) -> CellStats:
    """Pool ``series`` (in a fixed order: the result must not depend on which trial finished
    first)."""
    valid = np.concatenate([np.asarray(s.valid, bool) for s in series]) if series else np.zeros(0)
    valid = valid.astype(bool)

    def pooled(name: str) -> np.ndarray:
        arrays = [np.asarray(getattr(s, name), float) for s in series]
        return np.concatenate(arrays) if arrays else np.zeros(0)

    position = pooled("position_m")[valid]
    rotation = np.degrees(pooled("attitude_rad")[valid])
    latency = pooled("latency_ms")
    loss = [losses(s) for s in series]
    times = np.array([t for item in loss for t in item.reacquire_times_s])
    finite_latency = latency[np.isfinite(latency)]
    return CellStats(
        trials=len(series),
        samples=len(valid),
        valid=int(valid.sum()),
        **dict(
            zip(
                ("translation_mean_m", "translation_std_m", "translation_median_m"),
                _moments(position)[:3],
                strict=True,
            )
        ),
        translation_p95_m=_moments(position)[3],
        **dict(
            zip(
                ("rotation_mean_deg", "rotation_std_deg", "rotation_median_deg"),
                _moments(rotation)[:3],
                strict=True,
            )
        ),
        rotation_p95_deg=_moments(rotation)[3],
        lost=int(len(valid) - valid.sum()),
        loss_episodes=sum(item.episodes for item in loss),
        reacquired=sum(item.reacquired for item in loss),
        reacquire_time_mean_s=float(times.mean()) if len(times) else NAN,
        reacquire_time_max_s=float(times.max()) if len(times) else NAN,
        latency_mean_ms=float(finite_latency.mean()) if len(finite_latency) else NAN,
        latency_p95_ms=float(np.percentile(finite_latency, 95)) if len(finite_latency) else NAN,
    )
