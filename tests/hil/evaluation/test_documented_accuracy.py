"""The accuracy the docs claim, held by a test that a real fault fails (issue 13, point 7).

Each system tracks six frames of the default mock-up at 3 m and at 1.2 m (generic poses,
low noise, the prior a few millimetres and a fraction of a degree off the truth, as tracking
gives it). Asserted, per system and distance:

* the mean position and attitude errors within the documented figures (the upper end of the
  docs' range of per-case means) times 1.6 — the margin a six-frame mean needs for noise
  (its coefficient of variation is about 0.5/√6), not for a bug;
* no bias: the mean offset along each camera axis within max(0.2 mm, 0.2 σ) plus three
  standard errors of the mean (issue 13's bias limit, and the margin for six frames);
* honest covariances: the mean NEES within the 99.9 % interval of χ² with 6·dof degrees of
  freedom, divided by 6.

``test_a_half_pixel_shift_fails_the_accuracy_check`` shifts every frame by +0.5 px (every
observation with it) and requires the same check to fail, for each system: a check that
passes a half-pixel systematic error is no check (today's per-frame bounds passed it).
"""

from __future__ import annotations

import math
from functools import lru_cache

import cv2
import numpy as np
import pytest
from scipy.stats import chi2

from estimators.frame import Frame, GroundTruth
from estimators.geometry import Pose
from estimators.registry import build_estimator
from hil.evaluation.errors import measurement_error
from tests.estimators import rendered

FRAMES = 6
#: docs/corners_lines.md and docs/ellipses.md: the upper end of the low-noise per-case mean
#: errors (cm, degrees; the ellipse system's attitude is its normal's) — what is claimed.
DOCUMENTED = {
    ("corners", 3.0): (0.22, 0.30),
    ("corners", 1.2): (0.11, 0.19),
    ("lines", 3.0): (0.35, 0.19),
    ("lines", 1.2): (0.16, 0.18),
    ("ellipses", 3.0): (0.31, 1.48),
    ("ellipses", 1.2): (0.06, 0.12),
}
MEAN_MARGIN = 1.6
BIAS_LIMIT_M, BIAS_LIMIT_SIGMA = 0.0002, 0.2
#: Supersampling as in the documented matrices: corners and lines 2, ellipses 1.
SUPERSAMPLE = {"corners": 2, "lines": 2, "ellipses": 1}


def _offsets(distance_m: float) -> list[tuple[float, ...]]:
    """Generic poses about the nominal one: a few cm, a few degrees, every axis."""
    rng = np.random.default_rng(int(distance_m * 10))
    scale = np.array([0.03 * distance_m / 3] * 3 + [0.06, 0.06, 0.1])
    return [tuple(rng.uniform(-1, 1, 6) * scale) for _ in range(FRAMES)]


@lru_cache(maxsize=16)
def _run(system: str, distance_m: float, shift_px: float) -> dict:
    target = rendered.target()
    rng = np.random.default_rng(5)
    estimator = None
    errors, offsets, nees = [], [], []
    for k, offset in enumerate(_offsets(distance_m)):
        f = rendered.frame(distance_m, offset, seed=k, supersample=SUPERSAMPLE[system])
        image = f.image
        if shift_px:
            shift = np.float32([[1, 0, shift_px], [0, 1, 0]])
            image = cv2.warpAffine(image, shift, image.shape[::-1], flags=cv2.INTER_LINEAR)
        frame = Frame(image, f.stamp, f.info, f.seq, GroundTruth(f.truth.X_CT, f.truth.X_WC))
        if estimator is None:
            estimator = build_estimator(system, target, f.info)
        X = f.truth.X_CT
        prior = Pose.from_rotvec(rng.normal(0, 0.003, 3), rng.normal(0, 0.003, 3)) @ X
        m = estimator.estimate(frame, prior)
        assert m.valid, (system, distance_m, k, m.reason)
        e = measurement_error(m, X, target)
        if system == "ellipses":
            errors.append((e.center_m, e.normal_rad))
            nees.append((e.nees_circle, 5))
        else:
            errors.append((e.translation_m, e.rotation_rad))
            nees.append((e.nees_pose, 6))
        offsets.append(e.offset_C)
    return {"errors": np.array(errors), "offsets": np.array(offsets), "nees": nees}


def violations(system: str, distance_m: float, shift_px: float = 0.0) -> list[str]:
    """What of the documented accuracy the run breaks (empty when it holds)."""
    run = _run(system, distance_m, shift_px)
    found = []
    position_cm, attitude_deg = DOCUMENTED[(system, distance_m)]
    mean_position = 100 * float(run["errors"][:, 0].mean())
    mean_attitude = math.degrees(float(run["errors"][:, 1].mean()))
    if mean_position > MEAN_MARGIN * position_cm:
        found.append(f"mean position {mean_position:.3f} cm > {MEAN_MARGIN} × {position_cm}")
    if mean_attitude > MEAN_MARGIN * attitude_deg:
        found.append(f"mean attitude {mean_attitude:.3f}° > {MEAN_MARGIN} × {attitude_deg}")
    offsets = run["offsets"]
    mean, sd = offsets.mean(axis=0), offsets.std(axis=0, ddof=1)
    limit = np.maximum(BIAS_LIMIT_M, BIAS_LIMIT_SIGMA * sd) + 3 * sd / math.sqrt(len(offsets))
    for axis, (m, lim) in enumerate(zip(mean, limit, strict=True)):
        if abs(m) > lim:
            found.append(f"bias along {'xyz'[axis]} {1000 * m:+.2f} mm > {1000 * lim:.2f}")
    values = np.array([v for v, _ in run["nees"]])
    dof = run["nees"][0][1]
    low, high = chi2.ppf([0.0005, 0.9995], dof * len(values)) / len(values)
    if not low <= values.mean() <= high:
        found.append(f"mean NEES {values.mean():.1f} outside [{low:.1f}, {high:.1f}]")
    return found


@pytest.mark.parametrize("system", ["corners", "lines", "ellipses"])
@pytest.mark.parametrize("distance_m", [3.0, 1.2])
def test_documented_accuracy_holds(system, distance_m):
    assert violations(system, distance_m) == []


@pytest.mark.parametrize("system", ["corners", "lines", "ellipses"])
def test_a_half_pixel_shift_fails_the_accuracy_check(system):
    assert violations(system, 1.2, shift_px=0.5)
