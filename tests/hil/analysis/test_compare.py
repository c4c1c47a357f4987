"""satgrasp compare: campaigns cell by cell with a Mann–Whitney test, trials system by system."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from configuration.campaign import CampaignConfig
from configuration.files import parse_yaml_text
from hil.analysis.campaigns.compare import compare_campaigns, compare_trials, mann_whitney
from hil.analysis.campaigns.spec import expand
from hil.analysis.campaigns.stats import Series
from hil.analysis.campaigns.trials import RESULT_VERSION, result_path, write_atomic
from hil.cli import app
from tests.hil.logs.synthetic_log import make_trial, write_trial

CAMPAIGN = (
    "name: t\nparts:\n- {name: p, kind: path, axes: {system: [lines]}, seeds: [1, 2, 3, 4]}\n"
)


def _campaign(folder, scale: float, seed: int) -> None:
    rng = np.random.default_rng(seed)
    for trial in expand(parse_yaml_text(CAMPAIGN, CampaignConfig, "t.yaml")):
        errors = scale * (1.0 + 0.1 * rng.standard_normal(20))
        series = Series(tuple(np.arange(20) / 30), (True,) * 20, tuple(errors), tuple(errors))
        result = {
            "version": RESULT_VERSION,
            "trial": trial.to_dict(),
            "rows": [{"cell": {**trial.cell, "system": "lines"}, "series": series.to_dict()}],
            "extra": {},
            "timing": {},
        }
        write_atomic(result_path(folder, trial), json.dumps(result))


def test_compare_campaigns_finds_a_doubled_error_significant_on_trial_means(tmp_path):
    _campaign(tmp_path / "a", 0.001, 1)
    _campaign(tmp_path / "b", 0.002, 2)
    _campaign(tmp_path / "c", 0.001, 3)
    doubled = compare_campaigns(tmp_path / "a", tmp_path / "b")[0]
    assert doubled.ratio == pytest.approx(2.0, rel=0.1)
    assert doubled.p < 0.05 and doubled.basis == "trial means (4/4)"
    same = compare_campaigns(tmp_path / "a", tmp_path / "c")[0]
    assert same.p > 0.05


def test_mann_whitney_needs_two_values_a_side():
    assert np.isnan(mann_whitney([1.0], [1.0, 2.0]))


def test_compare_trials_aligns_systems_and_the_fused_estimate(tmp_path):
    write_trial(tmp_path / "a.mcap", make_trial(seed=1))
    write_trial(tmp_path / "b.mcap", make_trial(seed=2))
    differences, a, b = compare_trials(tmp_path / "a.mcap", tmp_path / "b.mcap")
    labels = {d.label for d in differences}
    assert {"corners", "lines", "ellipses", "fused", "trial"} <= labels
    assert set(a) == set(b) and len(a["fused"][0]) > 100
    result = CliRunner().invoke(
        app,
        [
            "compare",
            str(tmp_path / "a.mcap"),
            str(tmp_path / "b.mcap"),
            "--out",
            str(tmp_path / "o"),
        ],
    )
    assert result.exit_code == 0, result.output
    assert (tmp_path / "o" / "compare.png").stat().st_size > 1000
    mixed = CliRunner().invoke(app, ["compare", str(tmp_path / "a.mcap"), str(tmp_path)])
    assert mixed.exit_code == 2 and "not one of each" in mixed.output
