"""``satgrasp approach`` on every way out (issue 10): SIGINT and SIGTERM in a real subprocess
(simulated and wall clock), an exception in a driver call, a log that cannot be written, bad
output paths, relative paths inside a config, enum-like options. Each ends with the devices
stopped, one line saying why, and a log the report reads.

A small camera and a ground-truth estimator keep the trials short; the config sits in its own
folder and names its camera by a relative path, and the command runs from another folder.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from drivers.track_modbus import ModbusTrack
from hil.analysis.bench_rig import SHARED_MACHINE_STALL_S
from hil.cli import CODEC_NAMES, app
from hil.evaluation.recording import CODECS
from hil.logs.triallog import TrialLog, TrialLogError
from tests.hil.runtime.test_ways_out import small_disks

REPO = Path(__file__).resolve().parents[2]
ORACLE = "tests.hil.fake_estimators:build_oracle"
PERIOD_S = 1.0 / 125
runner = CliRunner()


def small_config(folder: Path, **changes) -> Path:
    """A sim config in ``folder/config`` naming its camera by a path relative to itself."""
    config_dir = folder / "config"
    (config_dir / "cameras").mkdir(parents=True)
    (config_dir / "cameras" / "small.yaml").write_text(
        "name: small\nwidth: 160\nheight: 120\nhfov_deg: 70\n"
    )
    data = {
        "name": "ways-out",
        "camera": "cameras/small.yaml",
        "systems": [ORACLE],
        "noise": {"preset": "none"},
        "vision": {"log_frames_every_s": 0},
        # These trials test the ways out, not the tick deadline (test_supervisor, test_loop):
        # on the shared machine a tick of the wall-clock trial's first second once took 34 ms
        # and the approach aborted on its 24 ms deadline before Ctrl-C could be sent.
        "approach": {"supervisor": {"max_tick_s": SHARED_MACHINE_STALL_S}},
        **changes,
    }
    path = config_dir / "sim.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def start_approach(tmp_path: Path, *args: str, new_session: bool = False) -> subprocess.Popen:
    """``satgrasp approach`` with the small config, run from a folder of its own."""
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    command = [sys.executable, "-c", "from hil.cli import main; main()", "approach"]
    command += ["--config", str(small_config(tmp_path)), "--log-dir", str(tmp_path / "runs")]
    return subprocess.Popen(
        [*command, *args],
        cwd=elsewhere,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=new_session,
    )


def wait_for_the_approach(process: subprocess.Popen, log_dir: Path, timeout_s=120.0) -> Path:
    """The trial log, once it shows a tick in phase approach (the log is flushed about once
    a second, so the arm and the track are moving by then)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise AssertionError(f"approach ended early: {process.communicate()}")
        for path in log_dir.glob("*.mcap"):
            try:
                if any(tick.phase == "approach" for tick in TrialLog.open(path).ticks()):
                    return path
            except (TrialLogError, FileNotFoundError):
                pass
        time.sleep(0.3)
    process.kill()
    raise AssertionError("the approach did not begin in time")


def the_stop(log_path: Path) -> tuple[dict, list]:
    """The log's stop event and its ticks; checks the arm and the track were commanded to stop
    within one control period of the request and never commanded to move after it."""
    log = TrialLog.open(log_path)
    assert log.complete and not log.recovered and not log.corrupt
    stop = next(e for e in log.events() if e["kind"] == "stop")
    ticks = list(log.ticks())
    asked = stop["data"]["asked_t"]
    assert 0.0 <= stop["data"]["reaction_s"] <= PERIOD_S + 1e-9, stop
    after = [tick for tick in ticks if tick.t >= asked and tick.command.stop]
    assert after and after[0].t - asked <= PERIOD_S + 1e-9, (after[:1], asked)
    assert all(tick.command.track_velocity == 0.0 for tick in ticks if tick.t > after[0].t)
    return stop, ticks


@pytest.mark.parametrize(
    ("name", "code", "report"), [("SIGINT", 130, True), ("SIGTERM", 143, False)]
)
def test_approach_stopped_by_a_signal_says_why_and_closes_its_log(tmp_path, name, code, report):
    process = start_approach(tmp_path, *([] if report else ["--no-report"]))
    log_path = wait_for_the_approach(process, tmp_path / "runs")
    process.send_signal(getattr(signal, name))
    stdout, stderr = process.communicate(timeout=120)
    assert process.returncode == code, stderr
    assert "Traceback" not in stderr
    line = f"interrupted by {name} in phase approach; arm and track stopped; log {log_path}"
    assert line in stdout.splitlines(), stdout
    stop, ticks = the_stop(log_path)
    assert stop["message"] == f"interrupted by {name} in phase approach; arm and track stopped"
    assert ticks[-1].phase == "abort"
    index = log_path.with_name(log_path.stem + "_report") / "index.html"
    assert index.is_file() == report
    if report:  # what report --json says of the interrupted trial
        result = runner.invoke(app, ["report", str(log_path), "--json"])
        figures = json.loads(result.stdout)
        assert figures["abort_reason"] == f"interrupted by {name} in phase approach"
        assert figures["complete"] is True and figures["outcome"] == "aborted"


def _descendants(pid: int) -> list[int]:
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
            except OSError:
                continue
            parent = int(stat.rsplit(")", 1)[1].split()[1])
            children.setdefault(parent, []).append(int(entry))
    found, todo = [], [pid]
    while todo:
        kids = children.get(todo.pop(), [])
        found += kids
        todo += kids
    return found


@pytest.mark.wall_clock
def test_approach_on_the_wall_clock_stopped_by_ctrl_c_leaves_no_process_behind(tmp_path):
    """Ctrl-C in a terminal signals the whole process group: the world, camera, vision and
    estimator processes ignore it, the control process stops the arm and the track, then
    ends each of them."""
    process = start_approach(tmp_path, "--clock", "wall", "--no-report", new_session=True)
    log_path = wait_for_the_approach(process, tmp_path / "runs")
    children = _descendants(process.pid)
    assert len(children) >= 4  # world, camera, vision, its worker (and multiprocessing's)
    os.killpg(process.pid, signal.SIGINT)
    stdout, stderr = process.communicate(timeout=60)
    assert process.returncode == 130, stderr
    assert "Traceback" not in stderr and "KeyboardInterrupt" not in stderr
    # In phase approach, or acquire when a loaded machine made the supervisor stop and re-lock.
    said = re.search(
        r"^interrupted by SIGINT in phase (\w+); arm and track stopped; log ", stdout, re.M
    )
    assert said and said.group(1) in ("approach", "acquire"), stdout
    the_stop(log_path)
    deadline = time.monotonic() + 10.0
    while (alive := [p for p in children if Path(f"/proc/{p}").exists()]) and (
        time.monotonic() < deadline
    ):
        time.sleep(0.1)
    assert not alive, alive


def _limit_the_track_device(monkeypatch, max_speed: float) -> None:
    """The track device reports a lower speed limit than the rig configuration's."""
    connect = ModbusTrack.connect

    def connect_to_a_slower_axis(self) -> None:
        connect(self)
        self.max_speed = max_speed

    monkeypatch.setattr(ModbusTrack, "connect", connect_to_a_slower_axis)


def test_approach_ended_by_a_driver_error_prints_one_line_and_writes_the_report(
    tmp_path, monkeypatch
):
    _limit_the_track_device(monkeypatch, 0.05)
    log_dir = tmp_path / "runs"
    result = runner.invoke(
        app, ["approach", "--config", str(small_config(tmp_path)), "--log-dir", str(log_dir)]
    )
    assert result.exit_code == 3, result.output
    assert result.exception is None or isinstance(result.exception, SystemExit)
    (log_path,) = log_dir.glob("*.mcap")
    lines = [line for line in result.stdout.splitlines() if line.startswith("ERROR")]
    assert len(lines) == 1, result.stdout
    assert lines[0].startswith("ERROR: trial ended by ValueError: track velocity")
    assert lines[0].endswith(
        f"(max_speed) in phase approach; arm and track stopped; log {log_path}"
    )
    assert f"report: {log_path.with_name(log_path.stem + '_report')}" in result.stdout
    log = TrialLog.open(log_path)
    assert log.complete
    assert any("traceback" in e["data"] for e in log.events() if e["kind"] == "abort")


def test_approach_whose_log_disk_fills_stops_and_says_the_log_is_incomplete(tmp_path, monkeypatch):
    small_disks(monkeypatch, capacity=120_000)  # the header and a second or two of ticks
    log_dir = tmp_path / "runs"
    result = runner.invoke(
        app, ["approach", "--config", str(small_config(tmp_path)), "--log-dir", str(log_dir)]
    )
    assert result.exit_code == 3, result.output
    (log_path,) = log_dir.glob("*.mcap")
    assert "abort reason: trial log cannot be written (OSError: [Errno 28]" in result.stdout
    assert f"trial log: {log_path}" in result.stdout
    assert "trial log incomplete: writing failed at t = " in result.stdout
    assert "report: " in result.stdout  # what was flushed reads, without a traceback
    assert not TrialLog.open(log_path).complete


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["approach", "--log-dir", "{file}"],
            "--log-dir {file}: {file} is a file, not a directory",
        ),
        (["approach", "--log-dir", "{file}/runs"], "cannot create the directory {file}/runs"),
        (["approach", "--log-dir", "/sys/satgrasp"], "--log-dir /sys/satgrasp: cannot create"),
        (["estimate", "--overlay", "/proc/satgrasp", "x.png"], "--overlay /proc/satgrasp: cannot"),
        (["render", "--out", "{file}/f.png"], "--out {file}/f.png: {file} is a file, not a"),
        (["render", "--out", "{dir}"], "--out {dir}: is a directory; give a file name"),
        (["matrix", "--system", "corners", "--out", "/proc/x/t.md"], "--out /proc/x/t.md: cannot"),
        (
            ["path", "--system", "corners", "--out", "{file}/p.md"],
            "--out {file}/p.md: {file} is a file",
        ),
        (
            ["calibrate", "x.mcap", "--out", "{file}/c.yaml"],
            "--out {file}/c.yaml: {file} is a file",
        ),
        (["demo", "--out-dir", "{file}"], "--out-dir {file}: {file} is a file, not a directory"),
    ],
)
def test_bad_output_paths_get_one_line_naming_the_option(tmp_path, args, message):
    taken = tmp_path / "a_file"
    taken.write_text("not a directory")
    names = {"file": str(taken), "dir": str(tmp_path)}
    result = runner.invoke(app, [a.format(**names) for a in args])
    assert result.exit_code == 2, result.output
    assert result.exception is None or isinstance(result.exception, SystemExit)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    assert message.format(**names) in lines[0]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["approach", "--links", "udp"], "Invalid value for '--links': 'udp' is not one of"),
        (["approach", "--clock", "fast"], "Invalid value for '--clock': 'fast' is not one of"),
        (["approach", "--noise", "loud"], "Invalid value for '--noise': 'loud' is not one of"),
        (["approach", "--systems", "sonar"], "systems: unknown estimator 'sonar'"),
        (["render", "--noise", "loud"], "Invalid value for '--noise': 'loud' is not one of"),
        (["matrix", "--system", "corners", "--noise", "low,loud"], "Invalid value for '--noise'"),
        (["campaign", "--noise", "loud"], "Invalid value for '--noise': 'loud' is not one of"),
        (["record", "--out", "{dir}", "--codec", "h264"], "Invalid value for '--codec'"),
        (["approach", "--seed", "one"], "Invalid value for '--seed'"),
    ],
)
def test_enum_like_options_get_the_same_one_line_error(tmp_path, args, message):
    result = runner.invoke(app, [a.format(dir=tmp_path) for a in args])
    assert result.exit_code == 2, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    assert message in lines[0]


def test_help_lists_the_values_of_enum_like_options():
    text = " ".join(runner.invoke(app, ["approach", "--help"]).stdout.split())
    for values in ("direct|tcp", "sim|wall", "none|low|high|sensor"):
        assert values in text, values
    assert tuple(CODECS) == CODEC_NAMES


def test_approach_config_naming_a_missing_file_gets_one_line(tmp_path):
    config = small_config(tmp_path, mockup="my_mockup.yaml")
    result = runner.invoke(app, ["approach", "--config", str(config)])
    assert result.exit_code == 2
    expected = config.parent / "my_mockup.yaml"
    assert f"mockup: file not found: {expected}" in " ".join(result.stderr.split())
