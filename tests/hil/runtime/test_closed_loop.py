"""The closed loop with the real estimators on the simulated rig (the default configuration,
configs/sim.yaml): two seeds of the full approach, and each estimator blinded in turn in the
middle of the approach. The 20-seed campaign is a command (`satgrasp campaign`), not a test."""

from __future__ import annotations

import math

import numpy as np
import pytest

from configuration.simulation import load_simulation
from estimators.frame import Frame
from estimators.geometry import rotation_error_geodesic, translation_error
from estimators.measurement import Measurement
from hil.analysis.campaign import summarize_log
from hil.runtime.trial import SimTrial, run_sim_trial


@pytest.mark.parametrize("seed", [1, 2])
def test_closed_loop_approach_succeeds(tmp_path, seed):
    sim = load_simulation("sim")
    log_path = tmp_path / f"seed{seed}.mcap"
    result = run_sim_trial(sim, seed=seed, log_path=log_path)
    outcome = result.outcome
    assert outcome.success, outcome
    assert outcome.standoff_error_m <= 0.005 and outcome.standoff_error_rad <= math.radians(0.5)
    summary = summarize_log(log_path, seed, sim.noise.preset)
    assert summary.success
    # Fusion beats every single estimator: on 1 s medians in nearly every window (the first
    # second or two, while the filter starts from its first measurements, may not).
    assert summary.fused_below_all_1s_position >= 0.85
    assert summary.fused_below_all_1s_attitude >= 0.85
    assert summary.fused_position_median_m < summary.best_single_position_median_m


class Blinded:
    """An estimator that sees nothing (a covered lens, a saturated sensor)."""

    def __init__(self, system: str):
        self.system = system

    def estimate(self, frame: Frame, prior_X_CT=None) -> Measurement:
        return Measurement.lost(self.system, frame, "blinded by the test")


@pytest.mark.parametrize("blind", ["corners", "lines", "ellipses"])
def test_fusion_keeps_the_lock_when_one_system_drops_out(tmp_path, blind):
    sim = load_simulation("sim")
    dt = 1.0 / sim.approach.servo.control_rate_hz
    with SimTrial(sim, seed=3, log_path=tmp_path / "trial.mcap") as trial:
        loop, world = trial.loop, trial.world
        loop.sequencer.start(world.clock.now())
        original = dict(loop.estimators)

        def run_for(seconds: float, record: list) -> None:
            for _ in range(round(seconds / dt)):
                loop.tick()
                world.advance(dt)
                estimate = loop.fusion.estimate(world.clock.now())
                truth = world.truth()
                if estimate.health == "ok" and estimate.X_MT is not None:
                    X_CM = loop.geometry.X_CM(world.arm.state().X_BE, world.track.state().position)
                    X_CT_true = truth["X_WC"].inverse() @ truth["X_WT"]
                    X_CT = estimate.X_CT(X_CM)
                    record.append(
                        (
                            estimate.health,
                            translation_error(X_CT_true, X_CT),
                            rotation_error_geodesic(X_CT_true, X_CT),
                        )
                    )
                else:
                    record.append((estimate.health, math.inf, math.inf))

        before, during = [], []
        run_for(4.0, before)
        assert loop.sequencer.phase == "approach"
        loop.estimators = {**original, blind: Blinded(blind)}
        run_for(6.0, during)
        assert loop.sequencer.phase in ("approach", "standoff"), loop.sequencer.abort_reason
        health = [h for h, _, _ in during]
        assert health.count("ok") == len(health), f"lost the lock without {blind}"
        errors = np.array([(p, r) for _, p, r in during])
        # Still a good pose from the other two: millimetres and tenths of a degree.
        assert np.median(errors[:, 0]) < 0.005 and np.median(errors[:, 1]) < math.radians(0.5)
        assert not np.any(np.linalg.norm(world.arm.state().V_BE[:3]) > 0.3)
