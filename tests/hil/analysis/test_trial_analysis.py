import copy
import math

import numpy as np
import pytest

from estimators.geometry import Pose
from hil.analysis.trial_analysis import FUSED, analyse, phase_spans, target_from_header
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


def test_analyse_measures_exactly_the_injected_errors(trial, analysis):
    assert analysis.systems == SYSTEMS and analysis.has_truth
    for name in (*SYSTEMS, FUSED):
        injected_p, injected_a = trial.errors[name]
        measured_p = analysis.position_error_m[name]
        assert np.array_equal(np.isnan(measured_p), np.isnan(injected_p)), name
        assert np.allclose(measured_p, injected_p, atol=1e-9, equal_nan=True), name
        measured_a = analysis.attitude_error_rad[name]
        if name == "ellipses":  # the normal was turned by exactly the injected angle
            assert np.allclose(measured_a, injected_a, atol=1e-9, equal_nan=True)
        else:  # roll/pitch/yaw norm of a rotation vector's rotation: equal to first order
            small = injected_a < 0.05
            assert np.allclose(measured_a[small], injected_a[small], rtol=0.02)
    assert analysis.five_dof == {"ellipses"}
    for system in SYSTEMS:
        assert list(analysis.status[system]) == trial.status[system]


def test_analyse_summary_counts_rates_and_fused_comparison(trial, analysis):
    for summary in analysis.summaries:
        status = np.array(trial.status[summary.name])
        ran = status != "absent"
        assert summary.ticks == ran.sum()
        assert summary.lost == (status == "lost").sum()
        assert summary.rejected == (status == "rejected").sum()
        assert summary.accepted_rate == pytest.approx((status == "accepted").sum() / ran.sum())
        p = trial.errors[summary.name][0]
        assert summary.position_m.median == pytest.approx(np.nanmedian(p))
    best = np.fmin.reduce([trial.errors[s][0] for s in SYSTEMS])  # NaN-ignoring minimum
    fused = trial.errors[FUSED][0]
    compared = np.isfinite(best) & np.isfinite(fused)
    fraction, _, count = analysis.fused_below_all
    assert count == compared.sum() and fraction == np.mean(fused[compared] < best[compared])
    assert analysis.outcome == "completed" and analysis.abort_reason is None
    assert analysis.duration_s == pytest.approx(trial.ticks[-1]["t"])
    standoff = analysis.standoff
    last = max(i for i, t in enumerate(trial.ticks) if t["phase"] == "standoff")
    X_CT = trial.ticks[last]["truth"]["X_CT"]
    assert standoff.t == trial.ticks[last]["t"] and standoff.true_depth_m == pytest.approx(
        0.5, abs=0.01
    )
    assert standoff.true_lateral_m == pytest.approx(np.hypot(*X_CT.p[:2]))
    assert standoff.fused_position_error_m == pytest.approx(trial.errors[FUSED][0][last])


def test_analyse_counts_ticks_where_fusion_was_worse(trial, tmp_path):
    worse = copy.copy(trial)
    worse.ticks = [dict(t) for t in trial.ticks]
    spoiled = range(100, 110)
    for i in spoiled:  # the fused estimate 0.3 m off for ten ticks
        X = worse.ticks[i]["truth"]["X_CT"]
        worse.ticks[i]["estimate"] = {
            **worse.ticks[i]["estimate"],
            "X_CT": Pose(X.R, X.p + np.array([0.3, 0.0, 0.0])),
        }
    path = tmp_path / "worse.mcap"
    write_trial(path, worse)
    result = analyse(TrialLog.open(path))
    fraction, _, count = result.fused_below_all
    assert np.allclose(result.position_error_m[FUSED][list(spoiled)], 0.3)
    assert fraction == pytest.approx((count - len(spoiled)) / count)


def test_analyse_an_aborted_trial_without_truth(tmp_path):
    path = tmp_path / "real.mcap"
    write_trial(path, make_trial(seed=12, with_truth=False, abort_at_s=6.0))
    result = analyse(TrialLog.open(path))
    assert not result.has_truth and result.position_error_m == {}
    assert result.outcome == "aborted"
    assert result.abort_reason == "estimate too old: 0.41 s > 0.30 s"
    assert result.standoff is None and result.true_depth_m is None
    assert any("No ground truth" in note for note in result.notes)
    assert math.isnan(result.fused_below_all[0])
    assert result.stop[-1] and result.phases[-1] == "abort"


def test_analyse_without_mockup_geometry_judges_only_6dof_measurements(trial, tmp_path):
    no_mockup = copy.copy(trial)
    no_mockup.header = {**trial.header, "config": {"camera": "reference"}}
    path = tmp_path / "nomockup.mcap"
    write_trial(path, no_mockup)
    result = analyse(TrialLog.open(path))
    assert np.isnan(result.position_error_m["ellipses"]).all()
    assert np.allclose(
        result.position_error_m["corners"], trial.errors["corners"][0], equal_nan=True
    )
    assert any("config.mockup" in note for note in result.notes)
    assert target_from_header(trial.header).has_circle("ring_outer")


def test_phase_spans_cover_consecutive_runs():
    t = np.array([0.0, 0.1, 0.2, 0.3, 0.4])
    spans = phase_spans(t, ["idle", "idle", "approach", "approach", "abort"])
    assert spans == [("idle", 0.0, 0.2), ("approach", 0.2, 0.4), ("abort", 0.4, 0.4)]
