"""``satgrasp faults``: one fault trial run through the command, and its refusals."""

from typer.testing import CliRunner

from hil.cli import app
from hil.logs.triallog import TrialLog

runner = CliRunner()


def test_cli_faults_runs_a_fault_and_prints_its_row(tmp_path):
    result = runner.invoke(app, ["faults", "--only", "track_fault", "--out-dir", str(tmp_path)])
    assert result.exit_code == 0, result.output
    row = next(line for line in result.output.splitlines() if line.startswith("| track_fault"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    fault, injected, effect, stop, reaction, final, readable, reason, passed = cells
    assert fault == "track_fault" and float(effect) == float(injected)
    assert readable.startswith("yes")
    assert float(stop) - float(injected) <= 0.008 + 1e-9  # the very next tick
    assert reaction == "0" and passed == "yes"
    assert final == "abort: track_fault: drive fault" and reason == "track_fault: drive fault"
    logs = list(tmp_path.glob("fault_track_fault_*.mcap"))
    assert len(logs) == 1 and TrialLog.open(logs[0]).tick_count > 100


def test_cli_faults_refuses_an_unknown_fault_in_one_line(tmp_path):
    result = runner.invoke(app, ["faults", "--only", "gremlins", "--out-dir", str(tmp_path)])
    assert result.exit_code == 2
    assert "unknown fault 'gremlins'" in result.output
    assert "Traceback" not in result.output
