"""Our accuracy targets per system and case (the issues' "must show" tables), and what counts
as a correct pose and as a wrong lock when the matrix judges a frame.

Targets are mean errors over a case's frames at low noise; high noise may be 1.5× larger. At
the 0.5 m stand-off (issue 13: acquisition over the whole approach) the 1.2 m targets hold.
A frame is *correct* when its error is within 3× the target; a valid frame is a *wrong lock*
when its error is gross — the estimator locked onto the wrong thing (a quarter turn of the
panel, the planar flip of a tilted target, another quadrilateral) rather than measured noisily.
"""

from __future__ import annotations

import math

import numpy as np

from hil.evaluation.errors import MeasurementError

_CM = 0.01
_DEG = math.pi / 180.0

#: system → distance (m) → (translation m, rotation rad): mean error at low noise.
ACCURACY_TARGETS: dict[str, dict[float, tuple[float, float]]] = {
    "corners": {
        3.0: (1.5 * _CM, 2.0 * _DEG),
        2.0: (0.8 * _CM, 1.0 * _DEG),
        1.2: (0.3 * _CM, 0.4 * _DEG),
        0.5: (0.3 * _CM, 0.4 * _DEG),
    },
    "lines": {
        3.0: (1.5 * _CM, 2.0 * _DEG),
        2.0: (0.8 * _CM, 1.0 * _DEG),
        1.2: (0.3 * _CM, 0.4 * _DEG),
        0.5: (0.3 * _CM, 0.4 * _DEG),
    },
    # Circle centre and normal (issue 4); judged on the 5-DOF circle pose even when the
    # thruster also gives 6-DOF (roll has its own target, ROLL_TARGET_RAD).
    "ellipses": {
        3.0: (1.0 * _CM, 2.0 * _DEG),
        2.0: (1.0 * _CM, 1.5 * _DEG),
        1.2: (1.0 * _CM, 1.0 * _DEG),
        0.5: (1.0 * _CM, 1.0 * _DEG),
    },
}
ROLL_TARGET_RAD = 3.0 * _DEG
NOISE_FACTOR = {"none": 1.0, "low": 1.0, "high": 1.5}
CORRECT_FACTOR = 3.0
#: A valid pose this far off (rotation, or translation as a fraction of the range) is a wrong
#: lock, not noise: locks on the wrong thing are 90° or 180° off (a quarter turn of the square
#: panel) or metres off (another quadrilateral), while the noisiest estimate in the matrix (the
#: panel's tilt from its edges at 3 m, high noise: 7.7° per axis) stays within ~30° at 3σ.
WRONG_LOCK_ROTATION_RAD = 45.0 * _DEG
WRONG_LOCK_RANGE_FRACTION = 0.10
#: Beyond these a valid pose is also a wrong lock unless its own covariance covers the error
#: (NEES within the 99.9 % χ² quantile): a noisy answer that says it is noisy is not a lock on
#: the wrong thing, an over-confident gross one is.
GROSS_POSITION_M = 0.05
GROSS_ROTATION_RAD = 10.0 * _DEG
NEES_COVERS = {6: 22.46, 5: 20.52}


def accuracy_target(system: str, distance_m: float, noise: str) -> tuple[float, float] | None:
    """(translation m, rotation rad) mean-error target of a case, or None if none is set."""
    by_distance = ACCURACY_TARGETS.get(system)
    if by_distance is None:
        return None
    for distance, (position, attitude) in by_distance.items():
        if abs(distance - distance_m) < 1e-6:
            factor = NOISE_FACTOR.get(noise, 1.0)
            return position * factor, attitude * factor
    return None


def target_along_approach(system: str, distance_m: float, noise: str) -> tuple[float, float] | None:
    """The target of the nearest reference distance at or beyond ``distance_m`` (the farthest
    one beyond them all): a frame between two reference distances is held to the looser."""
    by_distance = ACCURACY_TARGETS.get(system)
    if by_distance is None:
        return None
    beyond = [d for d in by_distance if d >= distance_m - 1e-9]
    return accuracy_target(system, min(beyond) if beyond else max(by_distance), noise)


def judged_errors(system: str, error: MeasurementError) -> tuple[float, float]:
    """(position m, attitude rad) a case's target is about: the circle's centre and normal for
    the ellipse system, the pose's translation and rotation otherwise."""
    if system == "ellipses" and not math.isnan(error.center_m):
        return error.center_m, error.normal_rad
    return error.position_m, error.attitude_rad


def is_correct(
    position_m: float, attitude_rad: float, target: tuple[float, float] | None
) -> bool | None:
    """Within ``CORRECT_FACTOR`` × the target (None without a target or an estimate)."""
    if target is None or math.isnan(position_m) or math.isnan(attitude_rad):
        return None
    return position_m <= CORRECT_FACTOR * target[0] and attitude_rad <= CORRECT_FACTOR * target[1]


def is_wrong_lock(error: MeasurementError, distance_m: float, *, ambiguous: bool = False) -> bool:
    """A valid answer that is wrong and does not say so: catastrophically off (a quarter turn,
    a planar flip, another quadrilateral: > 45° or > 10 % of the range), or grossly off (> 5 cm
    or > 10°) beyond what its own covariance admits. An answer flagged ``ambiguous`` is counted
    separately, not as a wrong lock."""
    position, attitude = error.position_m, error.attitude_rad
    if ambiguous or math.isnan(position):
        return False
    catastrophic = (
        position > WRONG_LOCK_RANGE_FRACTION * distance_m or attitude > WRONG_LOCK_ROTATION_RAD
    )
    gross = position > GROSS_POSITION_M or attitude > GROSS_ROTATION_RAD
    if math.isfinite(error.nees_pose):
        covered = error.nees_pose <= NEES_COVERS[6]
    else:
        covered = error.nees_circle <= NEES_COVERS[5]  # False when NaN: no covariance, no cover
    return bool(catastrophic or (gross and not covered))


def target_text(system: str, distance_m: float) -> str:
    target = accuracy_target(system, distance_m, "low")
    if target is None:
        return "–"
    return f"{target[0] / _CM:.1f} cm / {np.degrees(target[1]):.1f}°"
