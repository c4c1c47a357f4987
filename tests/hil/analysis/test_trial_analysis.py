import copy
import dataclasses
import math

import numpy as np
import pytest

from estimators.geometry import Pose, translation_error
from hil.analysis.trial_analysis import (
    FUSED,
    Spread,
    analyse,
    nominal_period_s,
    phase_spans,
    target_from_header,
)
from hil.logs.triallog import TrialLog
from tests.hil.logs.synthetic_log import SYSTEMS, make_trial, write_trial


@pytest.fixture(scope="module")
def trial():
    return make_trial(seed=11)


@pytest.fixture(scope="module")
def analysis(trial, tmp_path_factory):
    path = tmp_path_factory.mktemp("analysis") / "run.mcap"
    write_trial(path, trial)
    return analyse(TrialLog.open(path))


def _expected_fused_below_all(trial, fused_position: np.ndarray) -> tuple[float, int]:
    """From what was injected: per frame, the fused error at the tick nearest its capture
    (ticks at k / rate; captures never half-way) against the best error of its results."""
    best: dict[int, float] = {}
    for system in SYSTEMS:
        results = sorted((r for r in trial.vision if r.system == system), key=lambda r: r.seq)
        for r, error in zip(results, trial.errors[system][0], strict=True):
            best[r.seq] = np.fmin(best.get(r.seq, math.inf), error)
    captures = {seq: capture for seq, capture, _, _ in trial.frames}
    wins = []
    for seq, error in best.items():
        tick = round(captures[seq] * trial.rate_hz)
        fused = fused_position[tick] if tick < len(fused_position) else math.nan
        if math.isfinite(error) and math.isfinite(fused):
            wins.append(fused < error)
    return float(np.mean(wins)), len(wins)


def test_analyse_judges_each_result_against_the_truth_at_its_capture(trial, analysis):
    assert analysis.systems == SYSTEMS and analysis.has_truth
    for system in SYSTEMS:
        s = analysis.series[system]
        injected_p, injected_a = trial.errors[system]
        assert list(s.outcome) == trial.status[system], system
        assert np.array_equal(np.isnan(s.position_error_m), np.isnan(injected_p)), system
        assert np.allclose(s.position_error_m, injected_p, atol=1e-9, equal_nan=True), system
        if system == "ellipses":  # the normal was turned by exactly the injected angle
            assert np.allclose(s.attitude_error_rad, injected_a, atol=1e-9, equal_nan=True)
        else:  # roll/pitch/yaw norm of a rotation vector's rotation: equal to first order
            small = injected_a < 0.05
            assert np.allclose(s.attitude_error_rad[small], injected_a[small], rtol=0.02)
    assert analysis.five_dof == {"ellipses"}
    # The camera moved between capture and fusion by far more than the injected errors: an
    # exact match means every result was judged against the truth of its capture instant.
    moving = next(r for r in trial.vision if r.capture_t > 8.0 and r.outcome == "accepted")
    tick_after = next(t for t in trial.ticks if t.t >= moving.t)
    assert translation_error(moving.truth_X_CT, tick_after.truth.X_CT) > 0.02
    injected_fused_p, injected_fused_a = trial.errors[FUSED]
    assert np.allclose(analysis.fused_position_error_m, injected_fused_p, atol=1e-9, equal_nan=True)
    small = injected_fused_a < 0.05
    assert np.allclose(analysis.fused_attitude_error_rad[small], injected_fused_a[small], rtol=0.02)


def test_analyse_summary_counts_rates_and_fused_comparison(trial, analysis):
    for summary in analysis.summaries:
        status = np.array(trial.status[summary.name])
        assert summary.results == len(status)
        mine = [r for r in trial.vision if r.system == summary.name]
        assert summary.valid == sum(r.measurement.valid for r in mine) < len(status)
        assert summary.not_measured == (status == "not_measured").sum()
        assert summary.rejected == (status == "rejected").sum()
        assert summary.stale == (status == "stale").sum()
        assert summary.accepted_rate == pytest.approx((status == "accepted").sum() / len(status))
        assert summary.position_m.median == pytest.approx(
            np.nanmedian(trial.errors[summary.name][0])
        )
        latency = trial.latency_ms[summary.name]
        assert summary.latency_ms.median == pytest.approx(np.median(latency))
        assert summary.latency_ms.count == len(latency) == len(status) - summary.stale
        assert summary.processing_ms.p95 == pytest.approx(
            np.percentile(trial.processing_ms[summary.name], 95)
        )
    assert sum(s.stale for s in analysis.summaries) >= 2  # the trial does exercise them
    fraction, _, count = analysis.fused_below_all
    expected, frames = _expected_fused_below_all(trial, trial.errors[FUSED][0])
    assert count == frames and fraction == pytest.approx(expected)
    assert 0.5 < analysis.fused_below_all_1s[0] <= 1.0 and analysis.fused_below_all_1s[2] >= 19
    assert analysis.outcome == "completed" and analysis.abort_reason is None
    assert analysis.duration_s == pytest.approx(trial.ticks[-1].t)
    standoff = analysis.standoff
    last = max(i for i, t in enumerate(trial.ticks) if t.phase == "standoff")
    X_CT = trial.ticks[last].truth.X_CT
    assert standoff.t == trial.ticks[last].t
    assert standoff.true_depth_m == pytest.approx(0.5, abs=0.01)
    assert standoff.true_lateral_m == pytest.approx(np.hypot(*X_CT.p[:2]))
    assert standoff.fused_position_error_m == pytest.approx(trial.errors[FUSED][0][last])
    fused = analysis.fused
    assert fused.valid == np.isfinite(trial.errors[FUSED][0]).sum()


def test_analyse_timing_frames_latency_and_outcome(trial, analysis):
    timing = analysis.timing
    assert timing.nominal_period_ms == pytest.approx(1000.0 / trial.rate_hz)
    periods = trial.period_ms[1:]
    assert timing.period_ms.count == len(periods) == len(trial.ticks) - 1
    for got, q in ((timing.period_ms.median, 50), (timing.period_ms.p99, 99)):
        assert got == pytest.approx(np.percentile(periods, q))
    assert timing.period_ms.max == pytest.approx(periods.max())
    assert timing.period_ms.max > 2.4 * timing.nominal_period_ms  # an injected miss
    assert timing.work_ms.p99 == pytest.approx(np.percentile(trial.work_ms, 99))
    assert timing.deadline_misses == trial.deadline_miss.sum() == 6
    assert np.array_equal(analysis.deadline_miss, trial.deadline_miss)
    vision = analysis.vision
    received, processed, dropped = trial.frame_counts
    assert (vision.frames_received, vision.frames_processed, vision.frames_dropped) == (
        received,
        processed,
        dropped,
    )
    assert received == processed + dropped and dropped > 10
    stale = sum(r.outcome == "stale" for r in trial.vision)
    assert vision.results_stale == vision.stale_records == stale
    latency = np.concatenate([trial.latency_ms[s] for s in SYSTEMS])
    assert vision.latency_ms.count == len(latency)
    assert vision.latency_ms.median == pytest.approx(np.percentile(latency, 50))
    assert vision.latency_ms.p95 == pytest.approx(np.percentile(latency, 95))
    assert 110.0 + 24.0 < vision.latency_ms.median < 130.0 + 72.0  # latency + processing
    assert analysis.success and analysis.outcome_data["clock"] == "sim"
    assert analysis.outcome_data["standoff_error_m"] == pytest.approx(0.0012)
    assert analysis.incomplete is None and analysis.notes == []


def test_spread_of_ignores_nan_and_says_when_empty():
    spread = Spread.of([3.0, math.nan, 1.0, 2.0, math.inf])
    assert (spread.count, spread.median, spread.max) == (3, 2.0, 3.0)
    assert spread.p99 == pytest.approx(np.percentile([1.0, 2.0, 3.0], 99))
    empty = Spread.of(np.array([math.nan]))
    assert empty.count == 0 and math.isnan(empty.median) and math.isnan(empty.max)


def test_analyse_counts_frames_where_fusion_was_worse(trial, tmp_path):
    worse = copy.copy(trial)
    worse.ticks = list(trial.ticks)
    spoiled = range(200, 225)  # the fused estimate 0.3 m off for a second
    for i in spoiled:
        tick = worse.ticks[i]
        X = tick.truth.X_CT
        worse.ticks[i] = dataclasses.replace(
            tick,
            estimate=dataclasses.replace(
                tick.estimate, X_CT=Pose(X.R, X.p + np.array([0.3, 0.0, 0.0]))
            ),
        )
    path = tmp_path / "worse.mcap"
    write_trial(path, worse)
    result = analyse(TrialLog.open(path))
    fraction, _, count = result.fused_below_all
    assert np.allclose(result.fused_position_error_m[list(spoiled)], 0.3)
    fused = trial.errors[FUSED][0].copy()
    fused[list(spoiled)] = 0.3
    expected, frames = _expected_fused_below_all(trial, fused)
    assert count == frames and fraction == pytest.approx(expected)
    unspoiled, _ = _expected_fused_below_all(trial, trial.errors[FUSED][0])
    assert fraction < unspoiled - 0.03  # ten frames of 190 lost


def test_analyse_an_aborted_trial_without_truth(tmp_path):
    path = tmp_path / "real.mcap"
    trial = make_trial(seed=12, with_truth=False, abort_at_s=6.0)
    write_trial(path, trial)
    result = analyse(TrialLog.open(path))
    assert not result.has_truth
    assert np.isnan(result.fused_position_error_m).all()
    assert all(np.isnan(s.position_error_m).all() for s in result.series.values())
    assert result.outcome == "aborted" and not result.success
    assert result.abort_reason == "estimate too old: 0.41 s > 0.30 s"
    assert result.outcome_data["standoff_error_m"] is None
    assert result.standoff is None and result.true_depth_m is None
    assert any("No ground truth" in note for note in result.notes)
    assert math.isnan(result.fused_below_all[0])
    assert result.stop[-1] and result.phases[-1] == "abort"
    assert result.timing.deadline_misses == trial.deadline_miss.sum()
    assert result.vision.frames_received == trial.frame_counts[0]
    assert result.summaries[0].latency_ms.count > 0  # timing needs no truth


def test_analyse_without_mockup_geometry_judges_only_6dof_measurements(trial, tmp_path):
    no_mockup = copy.copy(trial)
    no_mockup.header = {**trial.header, "config": {"camera": "reference"}}
    path = tmp_path / "nomockup.mcap"
    write_trial(path, no_mockup)
    result = analyse(TrialLog.open(path))
    assert np.isnan(result.series["ellipses"].position_error_m).all()
    assert np.allclose(
        result.series["corners"].position_error_m, trial.errors["corners"][0], equal_nan=True
    )
    valid = sum(r.measurement.valid for r in trial.vision if r.system == "ellipses")
    assert f"{valid} circle (5-DOF) measurements not judged" in " ".join(result.notes)
    assert target_from_header(trial.header).has_circle("ring_outer")
    assert result.timing.nominal_period_ms == pytest.approx(40.0)  # from the outcome event


def test_nominal_period_from_the_outcome_event_else_the_configuration():
    header = {"config": {"approach": {"servo": {"control_rate_hz": 125.0}}}}
    assert nominal_period_s(header, {"control_period_s": 0.002}) == 0.002
    assert nominal_period_s(header, {}) == pytest.approx(0.008)
    assert math.isnan(nominal_period_s({"config": {}}, {"control_period_s": None}))


def test_phase_spans_cover_consecutive_runs():
    t = np.array([0.0, 0.1, 0.2, 0.3, 0.4])
    spans = phase_spans(t, ["idle", "idle", "approach", "approach", "abort"])
    assert spans == [("idle", 0.0, 0.2), ("approach", 0.2, 0.4), ("abort", 0.4, 0.4)]
