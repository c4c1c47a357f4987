"""``hil.analysis.bench`` and ``bench_report``: the comparison rows and the markdown page, from a
tiny run (one frame, one distance) and from made-up rows — never from timing values."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimators.geometry import Pose
from hil.analysis.bench import (
    PRIOR_OFFSET_M,
    PRIOR_OFFSET_RAD,
    ComparisonRow,
    FullFrameRow,
    comparison_timings,
    offset_prior,
)
from hil.analysis.bench_report import MachineInfo, benchmarks_markdown, summary, verdicts

MACHINE = MachineInfo(
    "Test CPU @ 1 GHz", 2, 0.5, "3.11.0", "1.26.0", "4.9.0", "2026-01-01 00:00 UTC"
)


def _row(system="corners", width=640, height=480, tracking=5.0, acquisition=40.0, opencv=8.0):
    return ComparisonRow(
        system, "reference" if width == 640 else "oak_d_rgb", width, height, 2.0, "low", 3,
        tracking, tracking * 1.2, 3, acquisition, acquisition * 1.2, 3, opencv, opencv * 1.2, 3,
        0.002, 0.004, 0.01, 0.02,
    )  # fmt: skip


@pytest.fixture(scope="module")
def tiny_run():
    return comparison_timings(distances_m=(2.0,), frames=1)


def test_offset_prior_is_one_centimetre_and_one_degree_off():
    X_CT = Pose.from_rpy(0.1, -0.2, 0.3, np.array([0.02, -0.01, 2.0]))
    prior = offset_prior(X_CT, np.random.default_rng(5))
    assert np.linalg.norm(prior.p - X_CT.p) == pytest.approx(PRIOR_OFFSET_M)
    angle = np.arccos(np.clip((np.trace(prior.R @ X_CT.R.T) - 1) / 2, -1, 1))
    assert angle == pytest.approx(PRIOR_OFFSET_RAD, rel=1e-6)


def test_comparison_timings_rows_for_every_system(tiny_run):
    assert [r.system for r in tiny_run] == ["corners", "lines", "ellipses"]
    for r in tiny_run:
        assert (r.camera, r.width, r.height, r.distance_m, r.noise, r.frames) == (
            "reference", 640, 480, 2.0, "low", 1,
        )  # fmt: skip
        assert r.tracking_median_ms > 0 and r.acquisition_median_ms > 0
        assert r.opencv_median_ms > 0 and r.opencv_valid == 1
        assert r.tracking_valid == 1 and math.isfinite(r.position_accuracy_ratio)


def test_benchmarks_markdown_has_the_tables_of_a_tiny_run(tiny_run):
    full = [
        FullFrameRow("reference", 640, 480, mode, 30.0, 2.0, rate, p50, p50 * 1.5)
        for mode, rate, p50 in (("serial", 4.0, 250.0), ("concurrent", 9.0, 110.0))
    ]
    text = benchmarks_markdown(
        tiny_run, full, MACHINE, command="satgrasp bench report --frames 1", frames=1
    )
    assert "Test CPU @ 1 GHz, 2 cores" in text and "OpenCV 4.9.0" in text
    assert "```\nsatgrasp bench report --frames 1\n```" in text
    assert "## Camera `reference` (640×480)" in text
    for system in ("corners", "lines", "ellipses"):
        assert f"| {system} | 2.0 | low |" in text
    assert "| reference | 640×480 | concurrent | 9.0 | 30% | 110.0 | 165.0 |" in text
    assert "rough" in text  # few frames: said so
    assert "Full frame (three systems + fusion, concurrent) at 640×480 does not meet" in text


def test_verdicts_read_the_targets_from_the_numbers():
    rows = [
        _row("corners", tracking=5.0, acquisition=40.0, opencv=8.0),
        _row("lines", tracking=12.0, acquisition=60.0, opencv=8.0),
        _row("corners", 1280, 800, tracking=18.0, acquisition=90.0, opencv=20.0),
    ]
    full = [FullFrameRow("reference", 640, 480, "concurrent", 30.0, 10.0, 30.0, 14.0, 20.0)]
    lines = verdicts(rows, full)
    assert "corners tracking at 640×480 meets ≤ 10 ms: slowest cell median 5.0 ms." in lines
    assert "lines tracking at 640×480 does not meet ≤ 10 ms: slowest cell median 12.0 ms." in lines
    assert (
        "lines acquisition at 640×480 does not meet ≤ 50 ms: slowest cell median 60.0 ms." in lines
    )
    assert "corners tracking at 1280×800 meets ≤ 20 ms: slowest cell median 18.0 ms." in lines
    assert any(s.startswith('corners tracking at 640×480 meets "no slower') for s in lines)
    assert any(s.startswith('lines tracking at 640×480 does not meet "no slower') for s in lines)
    assert any("meets (and the 16 ms aim) ≤ 33 ms" in s for s in lines)


def test_summary_counts_the_targets_met():
    rows = [_row("corners", tracking=5.0, acquisition=40.0, opencv=8.0)]
    full = [FullFrameRow("reference", 640, 480, "concurrent", 30.0, 10.0, 30.0, 40.0, 50.0)]
    text = summary(rows, full)
    # tracking ≤ 10 ms, acquisition ≤ 50 ms, no slower than OpenCV: met; full frame: not.
    assert text.startswith("3 of 4 of issue 12's speed targets are met in this run.")
    assert "0.6–0.6× the OpenCV pipeline's time" in text and "in 1 of 1 cells" in text


def test_comparison_row_to_dict_has_ratios_and_no_nan():
    row = _row(tracking=4.0, opencv=8.0)
    values = row.to_dict()
    assert values["time_ratio"] == pytest.approx(0.5)
    assert values["position_accuracy_ratio"] == pytest.approx(5.0)
    blind = ComparisonRow(
        "blind", "reference", 640, 480, 2.0, "low", 1, 1.0, 1.0, 0, 1.0, 1.0, 0,
        math.nan, math.nan, 0, math.nan, math.nan, math.nan, math.nan,
    )  # fmt: skip
    assert blind.to_dict()["opencv_median_ms"] is None and blind.to_dict()["time_ratio"] is None
