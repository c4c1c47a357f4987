"""Fault injection on the real simulated rig (SimArm, Modbus track and gripper drivers, renderer,
vision pipeline with camera latency, fusion, trial log): each fault ends with the arm commanded
to stop in the tick that sees it, the arm at rest soon after, and a trial log that opens and
records why.

A small camera and a ground-truth estimator keep these fast; the estimators themselves are
tested elsewhere.
"""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from configuration.rig import load_rig
from configuration.simulation import SimulationConfig
from drivers.base import DeviceTimeout
from estimators.frame import Frame
from hil.logs.triallog import TrialLog
from hil.runtime.compose import Trial
from sim_backends.rig_geometry import track_position_at_distance
from tests.hil.runtime.loop_fakes import TruthEstimator

ORACLE = "tests.hil.fake_estimators:build_oracle"
#: Camera latency, the oracle's modelled processing time and a frame period: the longest a
#: vision fault can take to reach the loop.
VISION_DELAY_S = 0.12 + 0.01 + 0.04 + 1.0 / 15.0


def small_sim(tmp_path: Path, **changes) -> SimulationConfig:
    camera = tmp_path / "small_camera.yaml"
    camera.write_text("name: small\nwidth: 160\nheight: 120\nhfov_deg: 70\n")
    data = {
        "name": "fault-test",
        "camera": str(camera),
        "systems": [ORACLE],
        "noise": {"preset": "none"},
        "vision": {"log_frames_every_s": 0},
        "fusion": {"coast_timeout_s": 0.4},
        "approach": {"supervisor": {"acquire_timeout_s": 1.5}},
    }
    data.update(changes)
    return SimulationConfig.model_validate(data)


def step(trial: Trial, seconds: float) -> None:
    loop = trial.loop
    for _ in range(round(seconds / loop.period_s)):  # ticks go on after an abort: time passes
        loop.tick()
        loop.clock.sleep_until(loop.clock.now() + loop.period_s)


def into_the_approach(trial: Trial) -> None:
    trial.loop.start()
    step(trial, 2.0)
    assert trial.loop.sequencer.phase == "approach"
    assert np.linalg.norm(trial.world.arm.state().V_BE[:3]) > 0.01, "the arm should be moving"


def _raise_timeout(timeout_s: float = 1.0) -> Frame:
    raise DeviceTimeout("no frame from the camera")


def _corrupt_once(trial: Trial):
    real_read = trial.world.camera.read
    done = []

    def read(timeout_s: float = 1.0) -> Frame:
        frame = real_read(timeout_s)
        if not done:
            done.append(True)
            return Frame(frame.image[:10, :10], frame.stamp, frame.info, frame.seq)
        return frame

    return read


def _estimator(trial: Trial, **flags) -> None:
    estimator = TruthEstimator("injected")
    for name, value in flags.items():
        setattr(estimator, name, value)
    trial.vision.workers.estimators[ORACLE] = estimator


def _shrink_workspace(trial: Trial) -> None:
    p = trial.world.arm.state().X_BE.p
    supervisor = trial.loop.config.supervisor.model_copy(
        update={"workspace_max_B": tuple(p - 0.001)}
    )
    trial.loop.config = trial.loop.config.model_copy(update={"supervisor": supervisor})


def _stall(trial: Trial) -> None:
    trial.world.advance(0.3)  # the loop misses its deadlines: nothing is streamed for 0.3 s


FAULTS = {
    "camera frames stop": (
        lambda t: setattr(t.world.camera, "read", _raise_timeout),
        "no usable frame",
        0.4 + 0.01,
    ),
    "corrupt frame": (
        lambda t: setattr(t.world.camera, "read", _corrupt_once(t)),
        "corrupt frame",
        VISION_DELAY_S,
    ),
    "frozen camera": (lambda t: t.world.camera.inject_freeze(), "frozen camera", VISION_DELAY_S),
    "estimator raises": (lambda t: _estimator(t, raise_error=True), "raised", VISION_DELAY_S),
    "NaN pose": (lambda t: _estimator(t, nan=True), "non-finite", VISION_DELAY_S),
    "protective stop": (lambda t: t.world.arm.inject_protective_stop(), "protective stop", 0.01),
    "workspace limit": (_shrink_workspace, "outside the workspace", 0.01),
    "command watchdog missed": (_stall, "watchdog", 0.3 + 0.01),
    "track drive fault": (lambda t: t.world.track_model.inject_drive_fault(), "track", 0.01),
}


@pytest.mark.parametrize("fault", list(FAULTS))
def test_fault_stops_the_arm_and_leaves_a_readable_log(tmp_path, fault):
    inject, reason, within_s = FAULTS[fault]
    log_path = tmp_path / "trial.mcap"
    with Trial(small_sim(tmp_path), seed=2, log_path=log_path) as trial:
        into_the_approach(trial)
        fault_t = trial.world.clock.now() - trial.loop.t0
        inject(trial)
        while trial.loop.sequencer.phase == "approach":  # until the supervisor reacts
            step(trial, trial.loop.period_s)
        # Before a recoverable fault's re-lock (≥ lock_s = 0.3 s later) lets it move again.
        step(trial, 0.25)
        arm = trial.world.arm.state()
        still_moving = np.linalg.norm(arm.V_BE[:3])
        step(trial, 2.0)
    log = TrialLog.open(log_path)
    ticks, events = list(log.ticks()), list(log.events())
    messages = [e["message"] for e in events if e["kind"] in ("fault", "abort")]
    assert any(reason in m for m in messages), (fault, messages)
    # The first tick that knew about the fault sent a stop: device faults at the next tick;
    # vision faults once a frame showing them has come through latency and processing.
    first_stop = next(t for t in ticks if t.t >= fault_t - 1e-9 and t.command.stop)
    assert first_stop.t - fault_t <= within_s + 1.0 / 125.0, (first_stop.t - fault_t, within_s)
    # Decelerating at 2 m/s² from ≤ 0.25 m/s, the arm is at rest well within 0.25 s.
    assert still_moving < 1e-3, f"{fault}: the arm still moves at {still_moving:.3f} m/s"


def test_all_measurements_stopping_coasts_then_stops_the_arm(tmp_path):
    log_path = tmp_path / "trial.mcap"
    sim = small_sim(tmp_path)
    with Trial(sim, seed=3, log_path=log_path) as trial:
        into_the_approach(trial)
        _estimator(trial, blind=True)
        fault_t = trial.world.clock.now() - trial.loop.t0
        step(trial, 3.0)
        assert trial.loop.sequencer.phase == "abort"
    ticks = list(TrialLog.open(log_path).ticks())
    after = [t for t in ticks if t.t >= fault_t]
    assert "coasting" in [t.estimate.health for t in after]
    first_stop = next(t for t in after if t.command.stop)
    # Coasting lasts at most the fusion's coast time-out past the last accepted capture (the
    # newest results in flight still land first), then the arm stops.
    assert first_stop.t - fault_t <= sim.fusion.coast_timeout_s + VISION_DELAY_S + 0.02
    assert all(not np.any(t.command.V_BE) for t in after if t.t > first_stop.t)


CHILD = textwrap.dedent(
    """
    import sys, time
    from pathlib import Path
    from configuration.simulation import SimulationConfig
    from hil.runtime.compose import run_trial
    sim = SimulationConfig.model_validate_json(Path(sys.argv[1]).read_text())
    def on_tick(record):
        print(record.tick, time.monotonic(), flush=True)
    run_trial(sim, seed=4, log_path=Path(sys.argv[2]), on_tick=on_tick)
    """
)


def test_log_of_an_approach_killed_with_sigkill_keeps_all_but_the_last_second(tmp_path):
    sim = small_sim(tmp_path, max_duration_s=600)
    config = tmp_path / "sim.json"
    config.write_text(sim.model_dump_json())
    log_path = tmp_path / "killed.mcap"
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[3])}
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(config), str(log_path)],
        stdout=subprocess.PIPE,
        text=True,
        env=env,
    )
    written = []  # (tick, monotonic time it was handed to the log)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            line = child.stdout.readline()
            if not line:
                break
            tick, stamp = line.split()
            written.append((int(tick), float(stamp)))
            if len(written) > 10 and written[-1][1] - written[0][1] > 3.0:
                break
        kill_time = time.monotonic()
        child.send_signal(signal.SIGKILL)
    finally:
        child.wait(timeout=30)
    assert child.returncode == -signal.SIGKILL
    assert written and written[-1][1] - written[0][1] > 3.0, "the approach did not run long enough"
    log = TrialLog.open(log_path)
    assert log.recovered
    ticks = {t.tick for t in log.ticks()}
    must_have = [tick for tick, stamp in written if stamp <= kill_time - 1.0]
    assert must_have and set(must_have) <= ticks
    assert log.header["seed"] == 4


def test_approach_drives_track_and_gripper_over_a_loopback_modbus_server(tmp_path):
    """links: tcp — the track and gripper drivers talk to a real pymodbus server on 127.0.0.1,
    which the trial stops when it ends."""
    log_path = tmp_path / "trial.mcap"
    with Trial(small_sim(tmp_path, links="tcp"), seed=2, log_path=log_path) as trial:
        servers = list(trial.world._servers)
        assert [s.host for s in servers] == ["127.0.0.1", "127.0.0.1"]
        start = trial.world.track.state().position
        into_the_approach(trial)
        step(trial, 1.0)
        moved = trial.world.track.state().position - start
        assert trial.world.gripper.state() is not None
    assert moved > 0.05, "the track should close the range over Modbus"
    for server in servers:
        assert not server.running
        with pytest.raises(OSError):
            socket.create_connection(("127.0.0.1", server.port), timeout=0.5).close()
    assert len(list(TrialLog.open(log_path).ticks())) > 100


def rig_file(tmp_path: Path, **track) -> str:
    """The built-in rig with some track settings changed, as a YAML file."""
    rig = load_rig().model_dump(mode="json")
    rig["track"].update(track)
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(rig))
    return str(path)


def true_distance_m(tick) -> float:
    """The camera's true distance from the ring's centre."""
    return float(np.linalg.norm(tick.truth.X_CT.p))


@pytest.mark.parametrize("onset", ["from the start", "mid-approach"])
def test_tumbling_mockup_is_held_then_aborted_never_chased(tmp_path, onset):
    """The mock-up turns at 3°/s about its vertical axis: the loop holds still and aborts
    naming the rate; the camera never comes inside the stand-off distance."""
    # Holding is acquiring: the acquisition's own time-out must outlast the hold.
    changes = {"approach": {"supervisor": {"acquire_timeout_s": 6.0}}, "max_duration_s": 10.0}
    if onset == "from the start":
        rig = rig_file(tmp_path, drift_rate_deg_s=[0.0, 3.0, 0.0])
        sim = small_sim(tmp_path, rig=rig, **changes)
    else:
        fault = {"kind": "tumbling_target", "phase": "approach", "after_s": 1.0}
        sim = small_sim(tmp_path, faults=[fault], **changes)
    log_path = tmp_path / "trial.mcap"
    with Trial(sim, seed=2, log_path=log_path) as trial:
        result = trial.run()
    reason = result.outcome.abort_reason
    assert result.outcome.phase == "abort"
    assert re.search(r"target rotating at [23]\.\d°/s, limit 1\.0°/s", reason), reason
    ticks = list(TrialLog.open(log_path).ticks())
    standoff = sim.approach.standoff.distance_m
    assert min(true_distance_m(t) for t in ticks if t.phase != "grasp") > standoff
    # Held: from the first stop on, nothing moves until the abort.
    first_stop = next(t for t in ticks if t.command.stop)
    assert all(
        not np.any(t.command.V_BE) and t.command.track_velocity == 0
        for t in ticks
        if t.t >= first_stop.t
    )
    held = ticks[-1].t - first_stop.t
    assert held >= sim.approach.supervisor.target_rate_abort_s - 0.05
    # The flange never turned after it: max rotation from its start stays small.
    R0 = ticks[0].arm.X_BE.R
    turned = max(np.degrees(Rotation.from_matrix(R0.T @ t.arm.X_BE.R).magnitude()) for t in ticks)
    assert turned < 5.0


def test_soft_limit_approached_at_speed_stops_before_it(tmp_path):
    """travel_max 1.0 m lies across the approach: the carriage reaches it at ≈ 0.2 m/s; the
    supervisor stops it while it can still brake (v²/2a ≈ 4 cm before), so it never crosses."""
    sim = small_sim(tmp_path, rig=rig_file(tmp_path, travel_max=1.0))
    log_path = tmp_path / "trial.mcap"
    with Trial(sim, seed=2, log_path=log_path) as trial:
        result = trial.run()
        step(trial, 1.5)  # the carriage brakes to rest
        final = trial.world.track.state()
    assert result.outcome.phase == "abort"
    assert "track_travel" in result.outcome.abort_reason
    ticks = list(TrialLog.open(log_path).ticks())
    first_stop = next(t for t in ticks if t.command.stop)
    assert first_stop.track.velocity > 0.15  # stopped at speed, not crawling up to it
    assert max(t.track.position for t in ticks) < 1.0
    assert final.position < 1.0 and final.velocity == 0.0 and final.fault is None


def test_guarded_advance_into_the_face_stops_on_the_contact_force(tmp_path):
    """The fingertips reach 3 cm past the grasp pose's: the guarded advance pushes them into
    the ring's face and the arm's TCP force stops it (the camera stays out of min_range)."""
    rig = rig_file(tmp_path, start_position=track_position_at_distance(load_rig(), 0.6))
    sim = small_sim(
        tmp_path,
        rig=rig,
        start={"distance_m": 0.6, "max_offset_m": 0.01, "max_rotation_deg": 0.5},
        tool_reach_m=0.38,
        approach={
            "supervisor": {"acquire_timeout_s": 1.5},
            "standoff": {"dwell_s": 0.2},
            "servo": {"slow_speed": 0.06},
            "grasp": {"speed": 0.06},
        },
        max_duration_s=20.0,
    )
    log_path = tmp_path / "trial.mcap"
    with Trial(sim, seed=2, log_path=log_path) as trial:
        result = trial.run()
    reason = result.outcome.abort_reason
    assert result.outcome.phase == "abort" and "contact: force" in reason, reason
    ticks = list(TrialLog.open(log_path).ticks())
    stop = next(t for t in ticks if t.command.stop and t.phase == "abort")
    force = np.linalg.norm(stop.arm.wrench_B[:3])
    limit = sim.approach.supervisor.max_contact_force
    assert limit < force < limit + 2.0  # caught the first tick over the limit
    before = [t for t in ticks if t.t < stop.t]
    assert all(np.linalg.norm(t.arm.wrench_B[:3]) <= limit for t in before)
    assert "grasp" in {t.phase for t in before}
