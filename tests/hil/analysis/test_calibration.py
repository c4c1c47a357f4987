"""Covariance calibration: NEES statistics on synthetic measurements whose true errors are known
multiples of their stated covariances."""

from __future__ import annotations

import numpy as np
import pytest

from estimators.fusion import FusionParams
from estimators.geometry import Pose
from estimators.measurement import Measurement
from estimators.so3 import exp_so3
from hil.analysis.calibration import covariance_scales, nees_statistics
from tests.estimators.fusion_sim import covariance, make_target, sample_circle, sample_pose

TARGET = make_target()
RING = TARGET.circle("ring_outer")


def poses(rng, count):
    for _ in range(count):
        yield Pose(exp_so3(rng.normal(size=3)), np.array([0.0, 0.0, 2.0]) + rng.normal(0, 0.3, 3))


def pose_samples(rng, system, count, stated, truth_scale=(1.0, 1.0), outliers=0.0):
    """(measurement, X_CT_true) pairs; the true error covariance is the stated one with its
    rotation block × truth_scale[0] and translation block × truth_scale[1]."""
    D = np.diag(np.sqrt([truth_scale[0]] * 3 + [truth_scale[1]] * 3))
    true_cov = D @ stated @ D
    out = []
    for i, X_CT in enumerate(poses(rng, count)):
        X = sample_pose(rng, X_CT, true_cov)
        if rng.random() < outliers:  # a lost track reported as tracking: 30 cm off
            X = Pose(X.R, X.p + [0.3, 0.0, 0.0])
        m = Measurement(system, "tracking", 0.0, i, X_CT=X, covariance=stated)
        out.append((m, X_CT))
    return out


def circle_samples(rng, count, stated, truth_scale=1.0, flipped=0.0):
    out = []
    for i, X_CT in enumerate(poses(rng, count)):
        center, normal = sample_circle(rng, X_CT, RING, stated, truth_scale)
        if rng.random() < flipped:  # the wrong branch of the two-fold ambiguity
            normal = -normal
        m = Measurement(
            "ellipses",
            "tracking",
            0.0,
            i,
            circle="ring_outer",
            center_C=center,
            normal_C=normal,
            covariance_5dof=stated,
        )
        out.append((m, X_CT))
    return out


def sigmas6():
    return np.concatenate([np.radians([1.0, 1.0, 0.4]), [0.004, 0.004, 0.012]])


def sigmas5():
    return np.concatenate([[0.002, 0.002, 0.006], np.radians([0.6, 0.6])])


def test_nees_statistics_honest_covariances_are_consistent():
    rng = np.random.default_rng(0)
    samples = pose_samples(rng, "corners", 1500, covariance(rng, sigmas6()))
    samples += circle_samples(rng, 1500, covariance(rng, sigmas5()))
    stats = nees_statistics(samples, TARGET)
    assert stats["corners"].dof == 6 and stats["ellipses"].dof == 5
    for s in stats.values():
        assert s.count == 1500
        assert s.consistent, s
        assert s.scale == pytest.approx(1.0, abs=0.06)
        assert s.robust_scale == pytest.approx(1.0, abs=0.1)
        assert s.scale_low < 1.0 < s.scale_high


def test_nees_statistics_finds_the_factor_of_overconfident_systems():
    rng = np.random.default_rng(1)
    stated6 = covariance(rng, sigmas6())
    stated5 = covariance(rng, sigmas5())
    samples = pose_samples(rng, "lines", 1500, stated6, truth_scale=(4.0, 4.0))
    samples += circle_samples(rng, 1500, stated5, truth_scale=9.0)
    stats = nees_statistics(samples, TARGET)
    assert stats["lines"].scale == pytest.approx(4.0, rel=0.08)
    assert stats["ellipses"].scale == pytest.approx(9.0, rel=0.08)
    assert not stats["lines"].consistent and not stats["ellipses"].consistent

    # Applying the scales found makes both consistent.
    scales = covariance_scales(stats)
    rescaled = []
    for m, X in samples:
        factor = scales[m.system]
        if m.X_CT is not None:
            fixed = Measurement(
                m.system, m.status, 0.0, m.seq, X_CT=m.X_CT, covariance=factor * m.covariance
            )
        else:
            fixed = Measurement(
                m.system,
                m.status,
                0.0,
                m.seq,
                circle=m.circle,
                center_C=m.center_C,
                normal_C=m.normal_C,
                covariance_5dof=factor * m.covariance_5dof,
            )
        rescaled.append((fixed, X))
    for s in nees_statistics(rescaled, TARGET).values():
        assert s.consistent and s.scale == pytest.approx(1.0, abs=0.01)
    params = FusionParams(covariance_scale=scales)
    assert params.scale_for("lines") == pytest.approx(stats["lines"].scale)


def test_nees_statistics_blocks_tell_rotation_from_translation():
    rng = np.random.default_rng(2)
    samples = pose_samples(rng, "corners", 1500, covariance(rng, sigmas6()), truth_scale=(6.0, 1.0))
    s = nees_statistics(samples, TARGET)["corners"]
    assert s.attitude_scale == pytest.approx(6.0, rel=0.1)
    assert s.position_scale == pytest.approx(1.0, rel=0.1)


def test_nees_statistics_robust_scale_ignores_lost_track_outliers():
    rng = np.random.default_rng(3)
    samples = pose_samples(rng, "corners", 1000, covariance(rng, sigmas6()), outliers=0.05)
    samples += circle_samples(rng, 1000, covariance(rng, sigmas5()), flipped=0.05)
    stats = nees_statistics(samples, TARGET)
    for s in stats.values():
        assert s.scale > 20.0  # a few gross errors dominate the mean
        assert s.robust_scale == pytest.approx(1.0, abs=0.15)
    assert covariance_scales(stats, robust=True)["corners"] < 1.2


def test_nees_statistics_skips_lost_and_uses_the_pose_of_pose_and_circle_measurements():
    rng = np.random.default_rng(4)
    stated = covariance(rng, sigmas6())
    samples = pose_samples(rng, "ellipses", 400, stated)
    both = []
    for m, X in samples:
        both.append(
            (
                Measurement(
                    "ellipses",
                    "tracking",
                    0.0,
                    m.seq,
                    X_CT=m.X_CT,
                    covariance=stated,
                    circle="ring_outer",
                    center_C=X.p,
                    normal_C=-(X.R @ RING.normal_T),  # nonsense: must not be used
                    covariance_5dof=np.eye(5) * 1e-12,
                ),
                X,
            )
        )
    lost = Measurement("ellipses", "lost", 0.0, 0, reason="no ellipse")
    s = nees_statistics([*both, (lost, Pose.identity())], TARGET)["ellipses"]
    assert s.count == 400 and s.dof == 6 and s.consistent


def test_nees_statistics_and_scales_reject_bad_input_clearly():
    rng = np.random.default_rng(5)
    (m, X), *_ = circle_samples(rng, 1, covariance(rng, sigmas5()))
    unknown = Measurement(
        "ellipses",
        "tracking",
        0.0,
        0,
        circle="nozzle",
        center_C=m.center_C,
        normal_C=m.normal_C,
        covariance_5dof=m.covariance_5dof,
    )
    with pytest.raises(ValueError, match=r"sample 1 \(ellipses\).*nozzle"):
        nees_statistics([(m, X), (unknown, X)], TARGET)
    with pytest.raises(ValueError, match="probability"):
        nees_statistics([(m, X)], TARGET, probability=1.5)
    stats = nees_statistics(pose_samples(rng, "lines", 50, np.eye(6), (1e-4, 1e-4)), TARGET)
    # stated far too large: the scale would shrink it; the floor keeps the stated covariance
    assert stats["lines"].scale < 0.01
    assert covariance_scales(stats)["lines"] == 1.0
    assert covariance_scales(stats, floor=0.0)["lines"] == pytest.approx(stats["lines"].scale)


def test_calibrated_covariance_adds_the_floor_in_each_measurement_order():
    from estimators.fusion import calibrated_covariance

    pose = Measurement("a", "tracking", 0.0, 0, X_CT=Pose.identity(), covariance=np.eye(6) * 1e-8)
    cov = calibrated_covariance(pose, 2.0, (0.01, 0.002))
    assert np.allclose(np.diag(cov), [2e-8 + 1e-4] * 3 + [2e-8 + 4e-6] * 3)
    circle = Measurement(
        "e",
        "tracking",
        0.0,
        0,
        circle="ring_outer",
        center_C=np.zeros(3),
        normal_C=np.array([0.0, 0.0, 1.0]),
        covariance_5dof=np.eye(5) * 1e-8,
    )
    cov = calibrated_covariance(circle, 1.0, (0.01, 0.002))
    assert np.allclose(np.diag(cov), [1e-8 + 4e-6] * 3 + [1e-8 + 1e-4] * 2)
    with pytest.raises(ValueError, match="covariance_floor"):
        FusionParams(covariance_floor={"a": (-1.0, 0.0)})


def test_fit_scale_and_floor_recovers_a_model_error_floor_over_range():
    """Stated covariances that shrink with range as a fit's do, true errors with an extra fixed
    millimetre: the fit finds that floor, and makes every range band honest."""
    from hil.analysis.calibration import FLOOR_LEVER_ARM_M, fit_scale_and_floor

    rng = np.random.default_rng(8)
    samples = []
    floor_m = 0.001
    for i in range(600):
        depth = rng.uniform(0.4, 3.0)
        X_CT = Pose(exp_so3(rng.normal(size=3) * 0.1), np.array([0.0, 0.0, depth]))
        stated = np.diag([(2e-4 * depth) ** 2] * 3 + [(2e-4 * depth**2) ** 2] * 3)
        true = stated + np.diag([(floor_m / FLOOR_LEVER_ARM_M) ** 2] * 3 + [floor_m**2] * 3)
        X = sample_pose(rng, X_CT, true)
        samples.append(
            (Measurement("corners", "tracking", 0.0, i, X_CT=X, covariance=stated), X_CT)
        )
    result = fit_scale_and_floor(samples, TARGET)["corners"]
    assert result.floor[1] == pytest.approx(floor_m, rel=0.3)
    assert result.scale < 1.6
    for _, count, _before, after in result.bins:
        assert count >= 20 and 0.7 < after < 1.4
    assert result.bins[0][2] > 5  # near range: the stated covariance alone was far too small


def test_samples_with_truth_pair_each_valid_result_with_the_truth_at_its_capture():
    from hil.analysis.calibration import samples_with_truth
    from tests.hil.logs.synthetic_log import make_trial

    trial = make_trial(seed=31, rate_hz=10.0)
    samples = samples_with_truth(trial.vision)
    valid = [r for r in trial.vision if r.measurement.valid]
    assert len(samples) == len(valid) < len(trial.vision)
    for (m, X_CT), r in zip(samples, valid, strict=True):
        assert m is r.measurement and X_CT is r.truth_X_CT
    assert any(r.outcome in ("stale", "rejected") for r in valid)  # kept: fusion's verdict
    assert samples_with_truth(make_trial(seed=31, rate_hz=10.0, with_truth=False).vision) == []


def test_cli_calibrate_fits_from_the_vision_records_of_a_log(tmp_path):
    """Honest synthetic covariances, judged against the truth at capture: scale ≈ 1 (against
    the truth of the tick that received them, 150 ms later, it would be far above)."""
    import dataclasses

    from typer.testing import CliRunner

    from hil.cli import app
    from tests.hil.logs.synthetic_log import make_trial, write_trial

    trial = make_trial(seed=32, rate_hz=10.0, camera_hz=5.0, outlier_probability=0.0)
    trial = dataclasses.replace(trial, vision=[r for r in trial.vision if r.system == "corners"])
    write_trial(tmp_path / "run.mcap", trial)
    result = CliRunner().invoke(
        app, ["calibrate", str(tmp_path / "run.mcap"), "--out", str(tmp_path / "fusion.yaml")]
    )
    assert result.exit_code == 0, result.output
    lines = result.stdout.splitlines()
    scale = float(lines[0].split("scale ")[1].split(",")[0])
    assert lines[0].startswith("corners: scale") and scale < 1.3
    counts = [int(line.split(": ")[1].split()[0]) for line in lines[1:] if "range ≤" in line]
    assert sum(counts) == sum(r.measurement.valid for r in trial.vision)
    written = (tmp_path / "fusion.yaml").read_text()
    assert written.startswith("fusion:\n  covariance_scale:\n    corners:")
    empty = CliRunner().invoke(app, ["calibrate", str(tmp_path / "run.mcap"), str(tmp_path / "x")])
    assert empty.exit_code == 2 and "x does not exist" in " ".join(empty.output.split())
