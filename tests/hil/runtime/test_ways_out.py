"""Every way a trial can end early, on the real simulated rig (SimArm, the Modbus track driver,
renderer, vision pipeline, trial log): a stop request, an exception in a driver call, a log
that cannot be written. Each time the arm and the track come to rest, the log says why, and
what was written can be read.

(Signals reach ``request_stop`` through ``hil.runtime.signals``; the signal path itself is
tested in real subprocesses in ``tests/hil/test_cli_ways_out.py``.)
"""

from __future__ import annotations

import builtins
import errno

import numpy as np
import pytest

from hil.analysis.report import make_report
from hil.analysis.trial_analysis import analyse
from hil.logs import triallog
from hil.logs.triallog import TrialLog
from hil.runtime.compose import Trial
from tests.hil.runtime.test_sim_faults import small_sim

#: Long enough for the arm (2 m/s² from ≤ 0.25 m/s) and the track (0.5 m/s² from ≤ 0.3 m/s)
#: to come to rest after a stop.
AT_REST_AFTER_S = 0.7


def at_rest(trial: Trial) -> tuple[float, float]:
    """Step the world on (nothing commanded any more) and return the arm's flange speed and
    the track's speed."""
    trial.world.advance(AT_REST_AFTER_S)
    arm, track = trial.world.arm.state(), trial.world.track.state()
    return float(np.linalg.norm(arm.V_BE[:3])), abs(track.velocity)


def once_in_the_approach(action, after_s: float = 1.0):
    """An ``on_tick`` observer running ``action`` once, at the first approach tick past
    ``after_s``; the list it returns gets that tick's time."""
    seen: list[float] = []

    def observer(record) -> None:
        if not seen and record.phase == "approach" and record.t >= after_s:
            seen.append(record.t)
            action(record)

    return observer, seen


def test_trial_stop_request_brings_arm_and_track_to_rest(tmp_path):
    log_path = tmp_path / "trial.mcap"
    trial = Trial(small_sim(tmp_path), seed=2, log_path=log_path)
    observer, asked = once_in_the_approach(
        lambda record: trial.loop.request_stop("interrupted by SIGTERM")
    )
    trial._on_tick = observer
    with trial:
        result = trial.run()
        arm_speed, track_speed = at_rest(trial)
    assert asked and result.outcome.abort_reason == "interrupted by SIGTERM in phase approach"
    assert arm_speed < 1e-3 and track_speed < 1e-3, (arm_speed, track_speed)
    log = TrialLog.open(log_path)
    assert log.complete and not log.corrupt
    stop = next(e for e in log.events() if e["kind"] == "stop")
    assert stop["message"].endswith("; arm and track stopped")
    assert stop["data"]["reaction_s"] <= trial.loop.period_s


def test_trial_stops_arm_and_track_when_the_track_driver_raises(tmp_path):
    """Issue 10's case: the track driver refuses (ValueError) a speed above what it read from
    the device, while the sequencer limits the track by the rig configuration's speed."""
    log_path = tmp_path / "trial.mcap"
    with Trial(small_sim(tmp_path), seed=2, log_path=log_path) as trial:
        trial.world.track.max_speed = 0.05  # the device reports a slower axis than the config
        with pytest.raises(ValueError, match="max_speed"):
            trial.run()
        arm_speed, track_speed = at_rest(trial)
    assert arm_speed < 1e-3 and track_speed < 1e-3, (arm_speed, track_speed)
    log = TrialLog.open(log_path)
    assert log.complete
    aborts = [e for e in log.events() if e["kind"] == "abort"]
    assert len(aborts) == 1, aborts  # the loop logged it; the trial does not repeat it
    assert aborts[0]["message"].startswith("trial ended by ValueError: track velocity")
    assert aborts[0]["message"].endswith("; arm and track stopped")
    assert "move_velocity" in aborts[0]["data"]["traceback"]
    assert analyse(log).abort_reason == aborts[0]["message"]


class SmallDisk:
    """A file on a disk that fills up: once ``capacity`` is set, writes beyond it store what
    fits and fail with ENOSPC, as a full filesystem does."""

    def __init__(self, file, capacity: int | None = None):
        self.file = file
        self.written = 0
        self.capacity = capacity

    def write(self, data) -> int:
        if self.capacity is not None and self.written + len(data) > self.capacity:
            room = max(0, self.capacity - self.written)
            self.file.write(bytes(data[:room]))
            self.written += room
            raise OSError(errno.ENOSPC, "No space left on device")
        self.written += len(data)
        return self.file.write(data)

    def __getattr__(self, name):
        return getattr(self.file, name)


def small_disks(monkeypatch, capacity: int | None = None) -> list[SmallDisk]:
    """Trial logs open their files on a ``SmallDisk`` from now on; the list gets each one."""
    disks: list[SmallDisk] = []

    def small_disk_open(path, mode):
        file = builtins.open(path, mode)  # noqa: SIM115 — the log writer closes it
        disks.append(SmallDisk(file, capacity))
        return disks[-1]

    monkeypatch.setattr(triallog, "open", small_disk_open, raising=False)
    return disks


def test_trial_stops_when_its_log_cannot_be_written_and_the_log_still_reads(tmp_path, monkeypatch):
    disks = small_disks(monkeypatch)
    log_path = tmp_path / "trial.mcap"

    filled: list[float] = []

    def observer(record) -> None:
        # The writer flushes by the wall clock: wait until ticks reached the disk (header is
        # flush 1) so the test does not depend on how fast this machine runs the simulation.
        flushed = trial.log.flush_count >= 2
        if not filled and record.phase == "approach" and record.t >= 1.0 and flushed:
            filled.append(record.t)
            disks[0].capacity = disks[0].written + 2000

    with Trial(small_sim(tmp_path), seed=2, log_path=log_path, on_tick=observer) as trial:
        result = trial.run()
        arm_speed, track_speed = at_rest(trial)
        error_t = trial.log.error_t
    assert filled
    assert result.log_error == "OSError: [Errno 28] No space left on device"
    assert result.outcome.abort_reason.startswith(
        "trial log cannot be written (OSError: [Errno 28] No space left on device)"
    )
    assert arm_speed < 1e-3 and track_speed < 1e-3, (arm_speed, track_speed)
    # Stopped in the control period in which the write failed.
    assert result.outcome.duration_s - error_t <= trial.loop.period_s + 1e-9
    log = TrialLog.open(log_path)  # what was flushed before the disk filled
    assert log.recovered and not log.complete and not log.corrupt
    ticks = list(log.ticks())
    assert ticks and ticks[-1].t <= filled[0]
    analysis = analyse(log)
    assert "could not write" in analysis.incomplete
    assert make_report(log_path, tmp_path / "report").is_file()  # no traceback either
