import html
import re

import cv2
import pytest
from typer.testing import CliRunner

from hil.analysis.report import make_report
from hil.cli import app
from hil.logs.triallog import TrialLogError
from tests.hil.logs.synthetic_log import make_trial, write_trial

runner = CliRunner()


@pytest.fixture(scope="module")
def sim_log(tmp_path_factory):
    path = tmp_path_factory.mktemp("report") / "sim.mcap"
    trial = make_trial(seed=21)
    write_trial(path, trial)
    return path, trial


def _text(page: str) -> str:
    return html.unescape(re.sub(r"\s+", " ", re.sub(r"<[^>]+>", " ", page)))


def test_make_report_writes_plots_and_a_summary_page(sim_log, tmp_path):
    path, trial = sim_log
    index = make_report(path, tmp_path / "out")
    assert index == tmp_path / "out" / "index.html"
    page = index.read_text()
    for name in ("range", "errors", "measurements", "command"):
        image = cv2.imread(str(tmp_path / "out" / f"{name}.png"))
        assert image is not None and image.shape[1] == 1000, name
        assert f'src="{name}.png"' in page
        assert image.std() > 10  # something was drawn
    text = _text(page)
    assert "outcome completed" in text and f"ticks {len(trial.ticks)}" in text
    rejected = trial.status["lines"].count("rejected")
    lost = trial.status["lines"].count("lost")
    assert re.search(rf"lines 6-DOF {len(trial.ticks) - 6} \d+ % \d+ % {rejected} {lost} ", text)
    assert "ellipses 5-DOF circle" in text and "circle's centre and normal" in text
    assert re.search(
        r"fused error below every single estimator at the same tick translation \d+ %", text
    )
    assert "stand-off true depth / lateral offset 0.50" in text
    assert "No ground truth" not in text
    assert "idle → acquire" in text  # events table


def test_make_report_without_truth_skips_error_plots_and_says_so(tmp_path):
    path = tmp_path / "real.mcap"
    write_trial(path, make_trial(seed=22, with_truth=False, abort_at_s=5.0))
    index = make_report(path, tmp_path / "out")
    files = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert files == ["command.png", "index.html", "measurements.png", "range.png"]
    text = _text(index.read_text())
    assert "No ground truth in this log (real hardware): error plots and statistics skipped" in text
    assert "outcome aborted" in text
    assert "abort reason estimate too old: 0.41 s > 0.30 s" in text
    assert "translation error median" not in text and "stand-off not reached" in text


def test_make_report_on_a_log_cut_off_by_a_crash(sim_log, tmp_path):
    path = tmp_path / "flushed.mcap"
    write_trial(path, make_trial(seed=23), trial_clock=True)  # flushed every trial second
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    text = _text(make_report(cut, tmp_path / "out").read_text())
    assert "writer was killed" in text and "recovered (writer killed)" in text
    assert re.search(
        r"outcome cut off in phase approach \(the writer did not close the log\)", text
    )
    assert (tmp_path / "out" / "errors.png").exists()


def test_cli_report_prints_where_the_report_is(sim_log, tmp_path):
    path, _ = sim_log
    result = runner.invoke(app, ["report", str(path), "--out", str(tmp_path / "r")])
    assert result.exit_code == 0, result.output
    assert f"report: {tmp_path / 'r' / 'index.html'}" in result.output.replace("\n", "")
    assert (tmp_path / "r" / "errors.png").exists()


def test_cli_report_rejects_bad_files_naming_them(tmp_path):
    missing = runner.invoke(app, ["report", str(tmp_path / "none.mcap")])
    assert missing.exit_code == 2 and "none.mcap does not exist" in " ".join(missing.output.split())
    text = tmp_path / "notes.txt"
    text.write_text("not a log")
    bad = runner.invoke(app, ["report", str(text)])
    assert bad.exit_code == 2 and "notes.txt is not an MCAP file" in " ".join(bad.output.split())
    with pytest.raises(TrialLogError, match="empty"):
        (tmp_path / "empty.mcap").write_bytes(b"")
        make_report(tmp_path / "empty.mcap", tmp_path / "out")
