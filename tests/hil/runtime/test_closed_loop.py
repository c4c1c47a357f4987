"""The closed loop with the real estimators on the simulated rig (the default configuration,
configs/sim.yaml): a full approach, and each estimator blinded in turn in the middle of one. The
20-seed campaign is a command (`satgrasp campaign`, docs/realtime.md), not a test."""

from __future__ import annotations

import math

import numpy as np
import pytest

from configuration.simulation import load_simulation
from estimators.frame import Frame
from estimators.geometry import rotation_error_geodesic, translation_error
from estimators.measurement import Measurement
from hil.analysis.campaign import summarize_log
from hil.runtime.compose import Trial, run_trial


# About 150 s on two cores beside the rest of the suite; more on a loaded machine.
@pytest.mark.timeout(900)
@pytest.mark.parametrize("seed", [1])
def test_closed_loop_approach_succeeds(tmp_path, seed):
    sim = load_simulation("sim")
    log_path = tmp_path / f"seed{seed}.mcap"
    result = run_trial(sim, seed=seed, log_path=log_path)
    assert result.success, result.outcome
    assert result.standoff_error_m <= 0.005
    assert result.standoff_error_rad <= math.radians(0.5)
    summary = summarize_log(log_path, seed, sim.noise.preset)
    assert summary.success
    # Fusion against the best single estimator over the trial. The loop acts on the estimate
    # of the tick's instant, predicted from frames 150–230 ms old, while each system is judged
    # at its own capture instant; since the corner system's range bias is gone (0.1 mm median
    # at low noise) the fused position is on par with it, not below (seed 1, low noise:
    # 128.3 vs 127.7 µm), and the fused attitude is clearly better (0.034° vs 0.049°).
    assert summary.fused_attitude_median_deg < 0.9 * summary.best_single_attitude_median_deg
    assert summary.fused_position_median_m < 1.1 * summary.best_single_position_median_m


class Blinded:
    """An estimator that sees nothing (a covered lens, a saturated sensor)."""

    def __init__(self, system: str):
        self.system = system

    def estimate(self, frame: Frame, prior_X_CT=None) -> Measurement:
        return Measurement.lost(self.system, frame, "blinded by the test")


def test_fusion_keeps_the_lock_when_each_system_drops_out_in_turn(tmp_path):
    sim = load_simulation("sim")
    with Trial(sim, seed=3, log_path=tmp_path / "trial.mcap") as trial:
        loop = trial.loop
        ticks = []
        loop.observers = [*loop.observers, ticks.append]
        loop.start()

        def run_for(seconds: float) -> list:
            first = len(ticks)
            for _ in range(round(seconds / loop.period_s)):
                loop.tick()
                loop.clock.sleep_until(loop.clock.now() + loop.period_s)
            return ticks[first:]

        run_for(4.0)
        assert loop.sequencer.phase == "approach"
        estimators = trial.vision.workers.estimators
        for blind in ("corners", "lines", "ellipses"):
            seeing = estimators[blind]
            estimators[blind] = Blinded(blind)
            during = run_for(3.0)
            estimators[blind] = seeing
            run_for(1.0)  # it re-acquires before the next one is blinded
            assert loop.sequencer.phase in ("approach", "standoff"), loop.sequencer.abort_reason
            health = [t.estimate.health for t in during]
            assert health.count("ok") == len(health), f"lost the lock without {blind}"
            errors = np.array(
                [
                    (
                        translation_error(t.truth.X_CT, t.estimate.X_CT),
                        rotation_error_geodesic(t.truth.X_CT, t.estimate.X_CT),
                    )
                    for t in during
                ]
            )
            # Still a good pose from the other two: millimetres and tenths of a degree.
            assert np.median(errors[:, 0]) < 0.005, blind
            assert np.median(errors[:, 1]) < math.radians(0.5), blind
            assert all(np.linalg.norm(t.arm.V_BE[:3]) <= 0.3 for t in during)
