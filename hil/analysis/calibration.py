"""Consistency of the estimators' stated covariances against ground truth, and the scale that
makes them consistent (``FusionParams.covariance_scale``).

For an honest covariance Σ the normalised estimation error squared NEES = eᵀ Σ⁻¹ e of a
measurement's error e (``estimators.fusion.measurement_error``, in the model fusion uses for it)
is χ²-distributed with dof = len(e) degrees of freedom, so its mean is dof (Bar-Shalom, Li &
Kirubarajan 2001, "Estimation with Applications to Tracking and Navigation", §5.4.2). A system
whose mean NEES per degree of freedom is s states covariances s times too small: multiplying
them by s restores mean NEES = dof. Pure functions; no I/O (the caller collects the pairs, e.g.
from the matrix runner's frames or a trial log's vision records, and writes the result into the
fusion parameters).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from estimators.fusion import (
    calibrated_covariance,
    measurement_covariance,
    measurement_error,
    uses_pose,
)
from estimators.geometry import Pose
from estimators.measurement import Measurement
from estimators.target import TargetModel
from hil.logs.records import VisionRecord


@dataclass(frozen=True, slots=True)
class NeesStatistics:
    """NEES of one system's valid measurements against truth.

    ``scale``: Σ NEES / Σ dof — the covariance factor making the mean NEES equal to dof (1 for
    honest covariances, > 1 for over-confident ones). ``robust_scale``: median of NEES / median
    of χ²(dof), insensitive to gross errors (frames where the system lost track); when ``scale``
    is far above it, the excess comes from outliers that gating should reject, not from the
    covariance. ``consistent``: ``scale`` inside the two-sided ``probability`` χ² interval of
    Σ dof (``scale_low``, ``scale_high``) — optimistic for time-correlated errors of a tracked
    sequence. ``position_scale`` / ``attitude_scale``: the same per block (translation or circle
    centre; rotation or normal), to see which part of the covariance is off.
    """

    system: str
    count: int
    dof: int
    mean_nees: float
    scale: float
    robust_scale: float
    scale_low: float
    scale_high: float
    consistent: bool
    position_scale: float
    attitude_scale: float


def samples_with_truth(records: Iterable[VisionRecord]) -> list[tuple[Measurement, Pose]]:
    """(measurement, true X_CT at its frame's capture) of every valid result that has truth
    (a simulated trial's vision records), whatever fusion made of it: a result discarded as
    stale or rejected by the gate still says how good the estimator is."""
    return [
        (r.measurement, r.truth_X_CT)
        for r in records
        if r.truth_X_CT is not None and r.measurement.valid
    ]


def measurement_nees(m: Measurement, X_CT_true: Pose, target: TargetModel) -> tuple[float, int]:
    """(NEES, dof) of a valid measurement against the true pose of the target in the camera."""
    error = measurement_error(m, X_CT_true, target)
    cov = measurement_covariance(m)
    return float(error @ np.linalg.solve(cov, error)), len(error)


def block_nees(
    m: Measurement, X_CT_true: Pose, target: TargetModel
) -> tuple[tuple[float, int], tuple[float, int]]:
    """((position NEES, dof), (attitude NEES, dof)) with each block's marginal covariance.

    6-DOF: position = δp (3), attitude = δθ (3); 5-DOF: position = δc (3), attitude = (α, β) (2).
    """
    error = measurement_error(m, X_CT_true, target)
    cov = measurement_covariance(m)
    position = slice(3, 6) if uses_pose(m) else slice(0, 3)
    attitude = slice(0, 3) if uses_pose(m) else slice(3, 5)
    out = []
    for block in (position, attitude):
        e = error[block]
        out.append((float(e @ np.linalg.solve(cov[block, block], e)), len(e)))
    return out[0], out[1]


def nees_statistics(
    samples: Iterable[tuple[Measurement, Pose]],
    target: TargetModel,
    *,
    probability: float = 0.95,
) -> dict[str, NeesStatistics]:
    """Per-system NEES statistics of (measurement, true X_CT) pairs; lost measurements are
    skipped. Raises ValueError naming the system and sample for an unusable measurement."""
    if not 0.0 < probability < 1.0:
        raise ValueError(f"probability must be in (0, 1); got {probability}")
    rows: dict[str, list[tuple[float, int, float, int, float, int]]] = {}
    for index, (m, X_CT_true) in enumerate(samples):
        if not m.valid:
            continue
        try:
            total = measurement_nees(m, X_CT_true, target)
            position, attitude = block_nees(m, X_CT_true, target)
        except (KeyError, np.linalg.LinAlgError) as exc:
            raise ValueError(
                f"sample {index} ({m.system}): cannot compute its NEES: {exc}"
            ) from exc
        rows.setdefault(m.system, []).append((*total, *position, *attitude))
    return {system: _summarize(system, values, probability) for system, values in rows.items()}


def _summarize(system: str, values: list, probability: float) -> NeesStatistics:
    array = np.array(values, dtype=float)
    nees, dof = array[:, 0], array[:, 1]
    total_dof = float(dof.sum())
    scale = float(nees.sum() / total_dof)
    robust = float(np.median(nees / chi2.median(dof)))
    tail = (1.0 - probability) / 2.0
    low, high = (chi2.ppf([tail, 1.0 - tail], total_dof) / total_dof).tolist()
    return NeesStatistics(
        system=system,
        count=len(array),
        dof=round(float(total_dof) / len(array)),
        mean_nees=float(nees.mean()),
        scale=scale,
        robust_scale=robust,
        scale_low=low,
        scale_high=high,
        consistent=low <= scale <= high,
        position_scale=float(array[:, 2].sum() / array[:, 3].sum()),
        attitude_scale=float(array[:, 4].sum() / array[:, 5].sum()),
    )


def covariance_scales(
    statistics: Mapping[str, NeesStatistics], *, robust: bool = False, floor: float = 1.0
) -> dict[str, float]:
    """``FusionParams.covariance_scale`` from the statistics: ``scale`` (or ``robust_scale``),
    never below ``floor`` (default 1: calibration only inflates; a system that looks
    under-confident on a short run keeps its stated covariance)."""
    out = {}
    for system, stats in statistics.items():
        value = stats.robust_scale if robust else stats.scale
        if not math.isfinite(value) or value <= 0:
            raise ValueError(f"{system}: scale {value} is not a positive number")
        out[system] = max(value, floor)
    return out


# --- scale and model-error floor over the working range -----------------------------------------

#: Lever arm (m) tying the rotation floor to the position floor: a feature layout ~0.15 m across
#: turns by σ_p / 0.15 m when its points are off by σ_p.
FLOOR_LEVER_ARM_M = 0.15
_FLOORS_M = (0.0, 0.00025, 0.0005, 0.00075, 0.001, 0.0015, 0.002, 0.003, 0.005)
_SCALES = tuple(float(s) for s in np.geomspace(1.0, 30.0, 25))


@dataclass(frozen=True, slots=True)
class CovarianceCalibration:
    """What makes one system's covariances honest from near to far: ``scale`` × stated +
    ``floor`` (σ rotation rad, σ position m). ``bins``: per range band (upper edge m), the
    sample count and the mean NEES / dof before and after."""

    system: str
    scale: float
    floor: tuple[float, float]
    bins: tuple[tuple[float, int, float, float], ...]


def _ratio(samples, target, scale: float, floor: tuple[float, float]) -> float:
    total, dof = 0.0, 0
    for m, X_CT_true in samples:
        error = measurement_error(m, X_CT_true, target)
        cov = calibrated_covariance(m, scale, floor)
        total += float(error @ np.linalg.solve(cov, error))
        dof += len(error)
    return total / dof


def fit_scale_and_floor(
    samples: Iterable[tuple[Measurement, Pose]],
    target: TargetModel,
    *,
    range_edges_m: tuple[float, ...] = (0.8, 1.6, math.inf),
    min_samples: int = 20,
) -> dict[str, CovarianceCalibration]:
    """Per system, the (scale ≥ 1, floor) on a grid that brings the mean NEES per degree of
    freedom closest to 1 in every range band at once (minimax of |log ratio|); the smallest
    floor wins ties. Range: the target's true distance along the optical axis. Bands with fewer
    than ``min_samples`` valid measurements are ignored."""
    by_system: dict[str, list[list]] = {}
    for m, X_CT_true in samples:
        if not m.valid:
            continue
        bands = by_system.setdefault(m.system, [[] for _ in range_edges_m])
        depth = float(X_CT_true.p[2])
        band = next(i for i, edge in enumerate(range_edges_m) if depth <= edge)
        bands[band].append((m, X_CT_true))
    out = {}
    for system, bands in by_system.items():
        used = [
            (edge, band)
            for edge, band in zip(range_edges_m, bands, strict=True)
            if len(band) >= min_samples
        ]
        if not used:
            continue
        best = None
        for floor_m in _FLOORS_M:
            floor = (floor_m / FLOOR_LEVER_ARM_M, floor_m)
            for scale in _SCALES:
                worst = max(abs(math.log(_ratio(band, target, scale, floor))) for _, band in used)
                if best is None or worst < best[0] - 1e-3:
                    best = (worst, scale, floor)
        _, scale, floor = best
        bins = tuple(
            (
                edge,
                len(band),
                _ratio(band, target, 1.0, (0.0, 0.0)),
                _ratio(band, target, scale, floor),
            )
            for edge, band in used
        )
        out[system] = CovarianceCalibration(system, scale, floor, bins)
    return out
