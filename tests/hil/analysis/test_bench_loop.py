"""``hil.analysis.bench_loop``: the vision pipeline's bench feeds the systems as a rig would."""

from __future__ import annotations

import numpy as np

import hil.analysis.bench_loop as bench_loop
from estimators.geometry import translation_error
from estimators.registry import build_estimator


def test_the_pipeline_bench_predicts_each_frame_from_the_arms_motion(monkeypatch):
    """On a rig the arm's motion is measured and fusion predicts each frame's pose from it: the
    priors the systems get are good to a millimetre. A bench that held the arm still while its
    frames moved (forward and back along the approach) handed them priors up to 8 cm off."""
    priors = []

    class Spy:
        def __init__(self, estimator):
            self.estimator, self.system = estimator, estimator.system

        def estimate(self, frame, prior):
            priors.append((frame, prior))
            return self.estimator.estimate(frame, prior)

    monkeypatch.setattr(
        bench_loop, "build_estimator", lambda *a, **k: Spy(build_estimator(*a, **k))
    )
    forward = bench_loop.approach_frames("reference", "default", frames=12, start_m=2.0, end_m=1.9)
    timing = bench_loop.pipeline_timing(
        "serial", forward + forward[-2:0:-1], ("lines",), seconds=2.0
    )
    errors_mm = [
        1000.0 * translation_error(prior, frame.truth.X_CT)
        for frame, prior in priors
        if prior is not None
    ]
    assert timing.frames_per_s > 0
    assert len(errors_mm) >= 10
    assert np.max(errors_mm) < 3.0
