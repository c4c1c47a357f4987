"""The loop's logic and fault paths, on fast fake devices (no rendering)."""

from dataclasses import dataclass

import numpy as np
import pytest

from configuration.approach import ApproachConfig
from drivers.clock import SimClock
from hil.runtime.loop import ApproachLoop
from tests.hil.runtime.loop_fakes import (
    FakeArm,
    FakeCamera,
    FakeFusion,
    FakeGripper,
    FakeTrack,
    FakeWorld,
    TruthEstimator,
    rig_geometry,
    start_X_BE,
)


class RecordingLog:
    def __init__(self):
        self.ticks, self.events = [], []

    def write_tick(self, record):
        self.ticks.append(record)

    def write_event(self, t, kind, message, **data):
        self.events.append((t, kind, message))


@dataclass
class Bench:
    loop: ApproachLoop
    arm: FakeArm
    track: FakeTrack
    world: FakeWorld
    camera: FakeCamera
    estimators: dict
    log: RecordingLog


def make_loop(config=None, systems=("a", "b"), fusion=None) -> Bench:
    clock = SimClock()
    geometry = rig_geometry()
    arm = FakeArm(clock, start_X_BE(geometry))
    track = FakeTrack(clock)
    world = FakeWorld(clock, arm, track, geometry)
    camera = FakeCamera(world)
    estimators = {s: TruthEstimator(s, i) for i, s in enumerate(systems)}
    log = RecordingLog()
    loop = ApproachLoop(
        arm=arm,
        track=track,
        gripper=FakeGripper(clock),
        camera=camera,
        estimators=estimators,
        fusion=FakeFusion(),
        geometry=geometry,
        config=config or ApproachConfig(),
        clock=clock,
        log=log,
        world=world,
        camera_fps=15.0,
    )
    return Bench(loop, arm, track, world, camera, estimators, log)


def test_loop_runs_a_full_approach_on_fakes():
    bench = make_loop()
    log = bench.log
    outcome = bench.loop.run(max_duration_s=120)
    assert outcome.phase == "done", log.events
    assert outcome.success, outcome
    assert outcome.standoff_error_m < 0.005
    phases = list(dict.fromkeys(t["phase"] for t in log.ticks))
    assert phases == ["acquire", "approach", "standoff", "grasp", "retreat", "done"]
    assert bench.track.position < -1.5  # the track carried the mock-up most of the way
    last = log.ticks[-1]
    assert last["command"]["stop"] and not np.any(last["command"]["V_BE"])
    assert all(t["truth"] is not None for t in log.ticks)


def _stopped_within_one_tick(log, arm, fault_t, detect_by_t):
    """The arm got stop() by ``detect_by_t`` and then only zero commands while stopped (in
    acquire after a recoverable fault, until the estimate re-locks; or for good in abort)."""
    assert arm.stops and fault_t <= arm.stops[0] <= detect_by_t + 1e-9, (arm.stops[:3], fault_t)
    after = [t for t in log.ticks if t["t"] >= arm.stops[0]]
    stopped = []
    for tick in after:
        if tick["phase"] not in ("acquire", "abort"):
            break
        stopped.append(tick)
    assert stopped and all(not np.any(t["command"]["V_BE"]) for t in stopped)


@pytest.mark.parametrize(
    ("name", "inject", "expect_kind", "final_phase"),
    [
        ("frames stop", lambda p: setattr(p["camera"], "stopped", True), "frames", "abort"),
        ("corrupt frame", lambda p: setattr(p["camera"], "corrupt_next", True), "frames", None),
        (
            "estimator raises",
            lambda p: setattr(p["estimators"]["a"], "raise_error", True),
            "estimator",
            "abort",
        ),
        ("NaN pose", lambda p: setattr(p["estimators"]["b"], "nan", True), "estimator", "abort"),
        (
            "protective stop",
            lambda p: setattr(p["arm"], "protective_stop", True),
            "arm_fault",
            "abort",
        ),
        ("arm link down", lambda p: setattr(p["arm"], "link_down", True), "arm_link", "abort"),
        (
            "track fault",
            lambda p: setattr(p["track"], "fault", "soft limit"),
            "track_fault",
            "abort",
        ),
    ],
)
def test_loop_stops_the_arm_on_each_fault(name, inject, expect_kind, final_phase):
    config = ApproachConfig.model_validate({"supervisor": {"acquire_timeout_s": 2.0}})
    bench = make_loop(config)
    loop, arm, world, log = bench.loop, bench.arm, bench.world, bench.log
    parts = {
        "arm": arm,
        "track": bench.track,
        "camera": bench.camera,
        "estimators": bench.estimators,
    }
    dt = 1.0 / config.servo.control_rate_hz
    # Run into the approach, then inject.
    loop.sequencer.start(0.0)
    loop._start_t = 0.0
    while loop.sequencer.phase != "approach" or world.clock.now() < 3.0:
        loop.tick()
        world.advance(dt)
    assert np.any(arm.V_BE), "the arm should be moving before the fault"
    fault_t = world.clock.now()
    inject(parts)
    for _ in range(int(4.0 / dt)):
        if loop.sequencer.phase in ("done", "abort"):
            break
        loop.tick()
        world.advance(dt)
    kinds = [message for _, kind, message in log.events if kind in ("fault", "abort")]
    assert any(expect_kind in message for message in kinds), (name, log.events[-5:])
    # Detected at the first tick that sees it; stopped in that same tick (≤ one camera period
    # for vision faults, which are only seen when a frame is due).
    detect_window = 1.0 / 15.0 + dt
    _stopped_within_one_tick(log, arm, fault_t, fault_t + detect_window)
    if final_phase is not None:
        assert loop.sequencer.phase == final_phase


def test_loop_runs_with_the_real_fusion_filter():
    from configuration.mockup import load_mockup
    from estimators.fusion import PoseFusion

    bench = make_loop(fusion=PoseFusion(load_mockup("default").target_model()))
    outcome = bench.loop.run(max_duration_s=120)
    assert outcome.success, (outcome, bench.log.events[-4:])
    accepted = [t["estimate"]["accepted"] for t in bench.log.ticks if t["measurements"]]
    assert sum(len(a) == 2 for a in accepted) > 0.9 * len(accepted)


def test_loop_keeps_going_when_one_system_is_blinded():
    bench = make_loop(systems=("a", "b", "c"))
    bench.estimators["b"].blind = True
    outcome = bench.loop.run(max_duration_s=120)
    assert outcome.phase == "done", bench.log.events[-3:]
    statuses = {
        m["status"] for t in bench.log.ticks for m in t["measurements"] if m["system"] == "b"
    }
    assert statuses == {"lost"}


def test_loop_times_out_a_trial():
    outcome = make_loop().loop.run(max_duration_s=5.0)
    assert outcome.phase == "abort" and "exceeded" in outcome.abort_reason
    assert not outcome.success
