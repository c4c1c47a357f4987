import html
import json
import math
import re

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from hil.analysis.report import make_report, report_json
from hil.analysis.trial_analysis import analyse
from hil.cli import app
from hil.logs.triallog import TrialLog, TrialLogError
from tests.hil.logs.synthetic_log import (
    CPU_SHARE,
    STANDOFF_ERROR,
    SYSTEMS,
    chunk_spans,
    flip_a_byte,
    make_trial,
    write_format1_log,
    write_trial,
)

runner = CliRunner()

#: Every key of ``satgrasp report --json`` (docs/trial_logs.md), and the nested ones.
JSON_KEYS = {
    "log",
    "complete",
    "corrupt",
    "incomplete",
    "success",
    "outcome",
    "phase",
    "abort_reason",
    "duration_s",
    "clock",
    "seed",
    "ticks",
    "control_period_ms",
    "tick_work_ms",
    "longest_tick_ms",
    "deadline_misses",
    "frames",
    "results_stale",
    "vision_latency_ms",
    "standoff_error_mm",
    "standoff_error_deg",
    "systems",
    "fused",
    "notes",
}
NESTED = {
    "control_period_ms": {"nominal", "p50", "p99", "max"},
    "tick_work_ms": {"p50", "p99", "max"},
    "longest_tick_ms": {"work", "cpu"},
    "frames": {"received", "processed", "dropped"},
    "vision_latency_ms": {"p50", "p95", "max"},
}


@pytest.fixture(scope="module")
def sim_log(tmp_path_factory):
    path = tmp_path_factory.mktemp("report") / "sim.mcap"
    trial = make_trial(seed=21)
    write_trial(path, trial)
    return path, trial


@pytest.fixture(scope="module")
def real_log(tmp_path_factory):
    path = tmp_path_factory.mktemp("report") / "real.mcap"
    trial = make_trial(seed=22, with_truth=False, abort_at_s=5.0)
    write_trial(path, trial)
    return path, trial


@pytest.fixture(scope="module")
def cut_log(tmp_path_factory):
    """A log cut at two thirds of its bytes, as a crash would leave it."""
    folder = tmp_path_factory.mktemp("cut")
    path = folder / "flushed.mcap"
    write_trial(path, make_trial(seed=23), trial_clock=True)  # flushed every trial second
    data = path.read_bytes()
    cut = folder / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    return cut


def _text(page: str) -> str:
    return html.unescape(re.sub(r"\s+", " ", re.sub(r"<[^>]+>", " ", page)))


def _json(result) -> dict:
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout)


@pytest.fixture(scope="module")
def sim_report(sim_log, tmp_path_factory):
    """``satgrasp report sim.mcap --out DIR``: (DIR, the CLI's output)."""
    path, _ = sim_log
    folder = tmp_path_factory.mktemp("page") / "r"
    result = runner.invoke(app, ["report", str(path), "--out", str(folder)])
    assert result.exit_code == 0, result.output
    return folder, result.output


def test_cli_report_writes_plots_and_a_summary_page(sim_log, sim_report):
    _, trial = sim_log
    folder, output = sim_report
    index = folder / "index.html"
    assert f"report: {index}" in output.replace("\n", "")
    page = index.read_text()
    for name in ("range", "errors", "results", "command", "timing"):
        image = cv2.imread(str(folder / f"{name}.png"))
        assert image is not None and image.shape[1] == 1000, name
        assert f'src="{name}.png"' in page
        assert image.std() > 10  # something was drawn
    text = _text(page)
    assert "outcome completed" in text and f"ticks {len(trial.ticks)}" in text
    assert "success yes" in text and "clock sim" in text
    status = trial.status["lines"]
    counts = [status.count(o) for o in ("rejected", "not_measured", "stale")]
    assert re.search(
        rf"lines 6-DOF {len(status)} \d+ % \d+ % {counts[0]} {counts[1]} {counts[2]} ", text
    )
    assert "ellipses 5-DOF circle" in text and "circle's centre and normal" in text
    assert re.search(r"below every estimator's result of the same frame translation \d+ %", text)
    assert "stand-off true depth / lateral offset 0.50" in text
    assert "stand-off true error when reached (outcome) 1.20 mm / 0.040°" in text
    assert "No ground truth" not in text
    assert "idle → acquire" in text  # events table


def test_report_page_shows_the_figures_of_report_json(sim_log, sim_report):
    path, trial = sim_log
    figures = report_json(analyse(TrialLog.open(path)))
    text = _text((sim_report[0] / "index.html").read_text())
    period, latency = figures["control_period_ms"], figures["vision_latency_ms"]
    assert (
        f"control period nominal / p50 / p99 / max {period['nominal']:.2f} / "
        f"{period['p50']:.2f} / {period['p99']:.2f} / {period['max']:.2f} ms" in text
    )
    assert f"deadline misses {figures['deadline_misses']}" in text
    received, processed, dropped = trial.frame_counts
    assert f"frames received / processed / dropped {received} / {processed} / {dropped}" in text
    assert f"results discarded as stale {figures['results_stale']}" in text
    assert (
        f"vision latency capture → fusion p50 / p95 / max {latency['p50']:.1f} / "
        f"{latency['p95']:.1f} / {latency['max']:.1f} ms" in text
    )


def test_make_report_without_truth_skips_error_plots_and_says_so(real_log, tmp_path):
    path, _ = real_log
    index = make_report(path, tmp_path / "out")
    files = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert files == ["command.png", "index.html", "range.png", "results.png", "timing.png"]
    text = _text(index.read_text())
    assert "No ground truth in this log (real hardware): error plots and statistics skipped" in text
    assert "outcome aborted" in text and "success no" in text and "clock wall" in text
    assert "abort reason estimate too old: 0.41 s > 0.30 s" in text
    assert "translation error median" not in text and "stand-off not reached" in text
    assert "stand-off true error when reached (outcome) – / –" in text


def test_make_report_on_a_log_cut_off_by_a_crash(cut_log, tmp_path):
    text = _text(make_report(cut_log, tmp_path / "out").read_text())
    assert "writer was killed" in text and "recovered: no footer (writer killed" in text
    assert re.search(
        r"outcome cut off in phase approach \(the writer did not close the log\)", text
    )
    assert (tmp_path / "out" / "errors.png").exists()
    assert (tmp_path / "out" / "timing.png").exists()


def test_cli_report_json_has_every_key_and_the_injected_figures(sim_log):
    path, trial = sim_log
    result = runner.invoke(app, ["report", str(path), "--json"])
    figures = _json(result)
    assert set(figures) == JSON_KEYS
    for key, keys in NESTED.items():
        assert set(figures[key]) == keys, key
    assert not path.with_name(f"{path.stem}_report").exists()  # --json alone writes no page
    assert figures["success"] is True and figures["outcome"] == "completed"
    assert figures["abort_reason"] is None and figures["phase"] == "done"
    assert figures["complete"] is True and figures["incomplete"] is None
    assert figures["clock"] == "sim" and figures["seed"] == 21
    assert figures["duration_s"] == pytest.approx(trial.ticks[-1].t)
    assert figures["ticks"] == len(trial.ticks)
    period = figures["control_period_ms"]
    periods = trial.period_ms[1:]  # the first tick has no period
    assert period["nominal"] == pytest.approx(1000.0 / trial.rate_hz)
    assert period["p50"] == pytest.approx(np.percentile(periods, 50))
    assert period["p99"] == pytest.approx(np.percentile(periods, 99))
    assert period["max"] == pytest.approx(periods.max())
    assert figures["tick_work_ms"]["p99"] == pytest.approx(np.percentile(trial.work_ms, 99))
    longest = figures["longest_tick_ms"]
    assert longest["work"] == pytest.approx(trial.work_ms.max())
    assert longest["cpu"] == pytest.approx(CPU_SHARE * trial.work_ms.max())
    assert figures["deadline_misses"] == int(trial.deadline_miss.sum()) == 6
    received, processed, dropped = trial.frame_counts
    assert figures["frames"] == {"received": received, "processed": processed, "dropped": dropped}
    assert figures["results_stale"] == sum(r.outcome == "stale" for r in trial.vision)
    latency = np.concatenate([trial.latency_ms[s] for s in SYSTEMS])
    assert figures["vision_latency_ms"]["p50"] == pytest.approx(np.percentile(latency, 50))
    assert figures["vision_latency_ms"]["p95"] == pytest.approx(np.percentile(latency, 95))
    assert figures["standoff_error_mm"] == pytest.approx(1000.0 * STANDOFF_ERROR[0])
    assert figures["standoff_error_deg"] == pytest.approx(math.degrees(STANDOFF_ERROR[1]))
    assert list(figures["systems"]) == list(SYSTEMS)
    for system in SYSTEMS:
        row = figures["systems"][system]
        processing = np.percentile(trial.processing_ms[system], [50, 95])
        assert [row["processing_ms"]["p50"], row["processing_ms"]["p95"]] == pytest.approx(
            processing
        )
        assert row["results"] == len(trial.status[system])
        assert row["position_error_mm"]["median"] == pytest.approx(
            1000.0 * np.nanmedian(trial.errors[system][0])
        )
    assert figures["fused"]["with_estimate"] == np.isfinite(trial.errors["fused"][0]).sum()


def test_cli_report_json_on_hardware_gives_null_standoff_and_the_abort(real_log, tmp_path):
    path, trial = real_log
    figures = _json(runner.invoke(app, ["report", str(path), "--json", "--out", str(tmp_path)]))
    assert set(figures) == JSON_KEYS and (tmp_path / "index.html").exists()
    assert figures["success"] is False and figures["outcome"] == "aborted"
    assert figures["abort_reason"] == "estimate too old: 0.41 s > 0.30 s"
    assert figures["standoff_error_mm"] is None and figures["standoff_error_deg"] is None
    assert figures["clock"] == "wall"
    assert "position_error_mm" not in figures["systems"]["corners"]
    assert figures["deadline_misses"] == int(trial.deadline_miss.sum())
    assert figures["vision_latency_ms"]["p50"] > 100.0


def test_cli_report_json_on_a_log_cut_off_by_a_crash_says_it_is_incomplete(cut_log):
    result = runner.invoke(app, ["report", str(cut_log), "--json"])
    figures = _json(result)
    assert set(figures) == JSON_KEYS
    assert figures["complete"] is False and figures["success"] is False
    assert figures["corrupt"] is False  # a cut-off tail is a killed writer, not a corrupt file
    assert figures["incomplete"].startswith("The log has no footer (its writer was killed")
    assert figures["outcome"].startswith("cut off in phase approach")
    assert figures["ticks"] > 100 and figures["frames"]["received"] > 10
    assert figures["vision_latency_ms"]["p50"] > 100.0 and figures["standoff_error_mm"] is None
    warning = " ".join(result.stderr.split())
    assert f"warning: {cut_log} is incomplete: The log has no footer" in warning


def test_cli_report_tells_a_corrupt_log_from_a_killed_writer(tmp_path):
    """One flipped byte in a chunk of a complete log: the report says the file is corrupt and
    what it lost, and reads the rest (before, every record after the bad chunk was dropped
    and the log taken for one whose writer was killed)."""
    path = write_trial(tmp_path / "whole.mcap", make_trial(seed=23), trial_clock=True).path
    offset, length = chunk_spans(path)[3]
    bad = flip_a_byte(path, tmp_path / "bad.mcap", offset + length // 3)
    result = runner.invoke(app, ["report", str(bad), "--json", "--out", str(tmp_path / "page")])
    figures = _json(result)
    assert figures["corrupt"] is True and figures["complete"] is True
    assert figures["incomplete"].startswith("The log is corrupt: 1 unreadable part: chunk at")
    assert "writer was killed" not in figures["incomplete"]
    assert figures["outcome"] == "completed"  # the end of the trial was read
    whole = len(list(TrialLog.open(path).ticks()))
    assert 0 < whole - figures["ticks"] < whole // 4
    page = _text((tmp_path / "page" / "index.html").read_text())
    assert "log corrupt, complete" in page and "The log is corrupt" in page


def test_cli_report_rejects_bad_files_naming_them(tmp_path):
    missing = runner.invoke(app, ["report", str(tmp_path / "none.mcap")])
    assert missing.exit_code == 2 and "none.mcap does not exist" in " ".join(missing.output.split())
    text = tmp_path / "notes.txt"
    text.write_text("not a log")
    bad = runner.invoke(app, ["report", str(text), "--json"])
    assert bad.exit_code == 2 and "notes.txt is not an MCAP file" in " ".join(bad.output.split())
    assert bad.stdout == ""
    with pytest.raises(TrialLogError, match="empty"):
        (tmp_path / "empty.mcap").write_bytes(b"")
        make_report(tmp_path / "empty.mcap", tmp_path / "out")


def test_cli_report_on_a_format_1_log_says_so_in_one_line(tmp_path):
    path = write_format1_log(tmp_path / "old.mcap")
    for extra in ([], ["--json"]):
        result = runner.invoke(app, ["report", str(path), *extra])
        assert result.exit_code == 2 and "Traceback" not in result.output
        (line,) = result.stderr.strip().splitlines()
        assert "trial log format 1, written before the typed records" in line
        assert line.endswith("re-run the trial to analyse it")


def test_report_of_a_log_without_records_says_so(tmp_path):
    from hil.logs.triallog import TrialLogWriter

    path = tmp_path / "empty.mcap"
    TrialLogWriter(path, {"config": {}, "seed": None}).close()
    figures = _json(runner.invoke(app, ["report", str(path), "--json"]))
    assert set(figures) == JSON_KEYS and figures["ticks"] == 0 and not figures["success"]
    assert figures["control_period_ms"] == dict.fromkeys(("nominal", "p50", "p99", "max"))
    assert figures["frames"] == {"received": 0, "processed": 0, "dropped": 0}
    text = _text(make_report(path, tmp_path / "out").read_text())
    assert "The log holds no ticks." in text and "outcome ended in phase none" in text
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["index.html"]
