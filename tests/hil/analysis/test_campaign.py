"""The campaign's summary, read back from trial logs (launching trials is the runtime's)."""

import math

import numpy as np
import pytest

from hil.analysis.campaign import campaign_markdown, summarize_log
from tests.hil.logs.synthetic_log import STANDOFF_ERROR, SYSTEMS, make_trial, write_trial


@pytest.fixture(scope="module")
def rows(tmp_path_factory):
    folder = tmp_path_factory.mktemp("campaign")
    done, aborted = make_trial(seed=41), make_trial(seed=42, abort_at_s=5.0)
    write_trial(folder / "done.mcap", done)
    write_trial(folder / "aborted.mcap", aborted)
    return (
        summarize_log(folder / "done.mcap", 41, "low"),
        summarize_log(folder / "aborted.mcap", 42, "high"),
        done,
        aborted,
    )


def test_summarize_log_reads_the_outcome_event_and_the_analysis(rows):
    done, aborted, trial, _ = rows
    assert done.success and done.phase == "done" and done.abort_reason == ""
    assert done.standoff_error_m == pytest.approx(STANDOFF_ERROR[0])
    assert done.standoff_error_deg == pytest.approx(math.degrees(STANDOFF_ERROR[1]))
    assert done.duration_s == pytest.approx(trial.ticks[-1].t)
    assert done.deadline_misses == 6
    latency = np.concatenate([trial.latency_ms[s] for s in SYSTEMS])
    assert done.vision_latency_p95_ms == pytest.approx(np.percentile(latency, 95))
    best = min(np.nanmedian(trial.errors[s][0]) for s in SYSTEMS)
    assert done.best_single_position_median_m == pytest.approx(best)
    assert done.fused_position_median_m == pytest.approx(np.nanmedian(trial.errors["fused"][0]))
    assert not aborted.success and aborted.phase == "abort"
    assert aborted.abort_reason == "estimate too old: 0.41 s > 0.30 s"
    assert math.isnan(aborted.standoff_error_m) and math.isnan(aborted.standoff_error_deg)


def test_campaign_markdown_has_a_line_per_noise_and_per_trial(rows):
    done, aborted, _, _ = rows
    text = campaign_markdown([done, aborted])
    assert "| low | 1 | 1/1 (100 %) | 1.2 mm / 0.04° |" in text
    assert "| high | 1 | 0/1 (0 %) | – / – |" in text
    latency = f"{done.vision_latency_p95_ms:.0f} ms"
    assert "| low | 41 | success | 22.0 s | 1.2 mm / 0.04° |" in text
    assert f"| {latency} | 6 | done.mcap |" in text
    assert "| high | 42 | abort: estimate too old: 0.41 s > 0.30 s |" in text
