"""The approach through the real drivers — URArm on ur-rtde, ModbusTrack and RobotiqGripper on
pymodbus — against the emulated world on the wall clock (the short trial of
hil.analysis.bench_rig): it succeeds and logs what a simulated trial logs; faults injected through the
emulators stop the arm and are named in the log; however the trial ends, the emulators stop and
their addresses are free again."""

from __future__ import annotations

import multiprocessing as mp
import time
from types import SimpleNamespace

import numpy as np
import pytest

from configuration.camera import load_camera
from configuration.mockup import load_mockup
from configuration.rig import load_rig
from hil.analysis.bench_rig import SHARED_MACHINE_STALL_S, short_trial
from hil.analysis.report import report_json
from hil.analysis.trial_analysis import analyse
from hil.logs.triallog import TrialLog
from hil.runtime.compose import Trial, run_trial
from hil.runtime.processes import ProcessStartError, stop_process
from hil.runtime.wall import await_ready, start_world
from sim_backends.loopback import bindable
from sim_backends.start import sample_start
from sim_backends.ur_emulator import UREmulator

# Wall-clock trials run alone (`make test` runs them after the rest, one at a time): beside
# another test on two cores they starve their own emulators and vision processes.
pytestmark = [pytest.mark.slow, pytest.mark.wall_clock]


def _addresses(sim) -> list[tuple[str, int]]:
    devices = sim.devices
    return [
        (devices.arm.host, 30004),
        (devices.arm.host, 29999),
        (devices.track.host, devices.track.port),
        (devices.gripper.host, devices.gripper.port),
    ]


def _speeds(trial: Trial, over_s: float = 0.1) -> tuple[float, float]:
    """How fast the camera and the mock-up truly move now (m/s), from the world's truth."""
    first = trial.world_link.newest()
    time.sleep(over_s)
    last = trial.world_link.newest()
    return tuple(
        float(np.linalg.norm(b.p - a.p)) / over_s
        for a, b in ((first.X_WC, last.X_WC), (first.X_WT, last.X_WT))
    )


def test_emulated_approach_succeeds_and_logs_what_a_simulated_trial_logs(tmp_path):
    sim = short_trial(tmp_path)
    result = run_trial(sim, seed=1, log_path=tmp_path / "emulated.mcap")
    log = TrialLog.open(result.log_path)
    events = [(round(e["t"], 2), e["kind"], e["message"]) for e in log.events()]
    assert result.success, (result.outcome, events)
    assert result.standoff_error_m < sim.approach.standoff.success_position_m
    assert all(bindable(*address) for address in _addresses(sim))

    # The same trial simulated (--clock sim), for a second: the same records, fields and
    # analysis come out of both logs.
    simulated = short_trial(
        tmp_path, devices={}, clock="sim", max_duration_s=1.0, name="simulated-short"
    )
    reference = TrialLog.open(
        run_trial(simulated, seed=1, log_path=tmp_path / "simulated.mcap").log_path
    )
    assert log.header.keys() == reference.header.keys()
    assert (log.header["clock"], reference.header["clock"]) == ("wall", "sim")
    assert log.header["config"]["simulation"]["devices"]["arm"]["backend"] == "ur_rtde"
    ticks, sim_ticks = list(log.ticks()), list(reference.ticks())
    for field in ("arm", "track", "gripper", "truth", "estimate", "command", "timing"):
        assert all(getattr(t, field) is not None for t in ticks), field
        assert all(getattr(t, field) is not None for t in sim_ticks), field
    assert {t.phase for t in ticks} >= {"acquire", "approach", "standoff", "grasp", "done"}
    assert any(t.gripper.object_detected for t in ticks)  # the emulated gripper closed on it
    assert {r.outcome for r in log.vision()} >= {"accepted"}
    emulated_report, sim_report = (report_json(analyse(x)) for x in (log, reference))
    assert emulated_report.keys() == sim_report.keys()


FAULTS = {
    # injected: (device, fault, arguments), then what the log must name
    "link dropped": (("ur", "drop_link"), "RTDE connection lost"),
    "protective stop": (("ur", "protective_stop"), "protective stop"),
    "track silent": (("track", "silence", True), f"no reply within {SHARED_MACHINE_STALL_S} s"),
}


@pytest.mark.parametrize("fault", list(FAULTS))
def test_emulated_fault_mid_approach_stops_the_arm_and_the_log_names_it(tmp_path, fault):
    (device, name, *args), reason = FAULTS[fault]
    sim = short_trial(tmp_path, distance_m=0.9)  # a longer approach to break into
    injected: list[float] = []

    def inject_while_moving(record) -> None:
        # The approach closes mostly with the track; the arm aligns the camera meanwhile.
        moving = record.track is not None and abs(record.track.velocity) > 0.02
        if not injected and record.phase == "approach" and moving:
            trial.world_link.inject(device, name, *args)
            injected.append(record.t)

    log_path = tmp_path / "fault.mcap"
    with Trial(sim, seed=2, log_path=log_path, on_tick=inject_while_moving) as trial:
        result = trial.run()
        # Any stop is done by now — the arm's: 2 m/s² from ≤ 0.25 m/s takes 0.125 s; the
        # track's: 0.5 m/s² from 0.25 m/s, after its own 0.5 s watchdog when its link is silent.
        time.sleep(1.0)
        camera_speed, mockup_speed = _speeds(trial)
    assert injected, "nothing moved in the approach"
    assert result.outcome.phase == "abort", result.outcome
    log = TrialLog.open(log_path)
    messages = [e["message"] for e in log.events() if e["kind"] in ("fault", "abort")]
    assert any(reason in m for m in messages), messages
    # The loop commanded a stop within a few ticks of the fault (a silent track costs its
    # reply time-out, a dropped link the receive thread's noticing it).
    first_stop = next(t for t in log.ticks() if t.t >= injected[0] and t.command.stop)
    delay = first_stop.t - injected[0]
    assert delay < SHARED_MACHINE_STALL_S + 0.2, delay
    assert camera_speed < 1e-3, f"{fault}: the camera still moves at {camera_speed:.4f} m/s"
    assert mockup_speed < 1e-3, f"{fault}: the mock-up still moves at {mockup_speed:.4f} m/s"
    assert not any(p.is_alive() for p in trial.processes.values())
    assert all(bindable(*address) for address in _addresses(sim))


def test_emulated_trial_interrupted_stops_every_emulator_and_frees_its_addresses(tmp_path):
    sim = short_trial(tmp_path)

    def interrupt(record) -> None:
        if record.tick == 30:
            raise KeyboardInterrupt

    log_path = tmp_path / "interrupted.mcap"
    with (
        pytest.raises(KeyboardInterrupt),
        Trial(sim, seed=3, log_path=log_path, on_tick=interrupt) as trial,
    ):
        trial.run()
    assert not any(p.is_alive() for p in trial.processes.values())
    assert all(bindable(*address) for address in _addresses(sim))
    messages = [e["message"] for e in TrialLog.open(log_path).events()]
    assert any("KeyboardInterrupt" in m for m in messages), messages


def test_emulated_devices_refuse_the_simulated_clock_in_one_line(tmp_path):
    sim = short_trial(tmp_path, clock="sim")
    with pytest.raises(ValueError, match="--clock sim steps a simulated world") as refused:
        Trial(sim, seed=1, log_path=tmp_path / "never.mcap")
    assert "\n" not in str(refused.value)
    assert not (tmp_path / "never.mcap").exists()


def test_emulated_world_on_a_taken_address_fails_its_start_in_one_line(tmp_path):
    sim = short_trial(tmp_path)
    setup = SimpleNamespace(
        config=sim,
        mockup=load_mockup(sim.mockup),
        camera=load_camera(sim.camera),
        start=sample_start(sim.start, load_rig(sim.rig), np.random.default_rng(0)),
        seed=0,
    )
    context = mp.get_context("spawn")
    processes: dict = {}
    with UREmulator(sim.devices.arm.host):  # someone else's emulator holds the address
        world = start_world(setup, context, processes, None)
        try:
            with pytest.raises(ProcessStartError) as refused:
                await_ready(world, "world", processes["world"])
        finally:
            stop_process(processes["world"], timeout_s=5.0)
    message = str(refused.value)
    assert f"cannot listen on {sim.devices.arm.host}:29999 (dashboard)" in message, message
    assert "\n" not in message and not processes["world"].is_alive()
