"""Matrix runner options shared by all systems: acquisition-only runs, blank frames and the
re-acquisition count, wrong-lock and ambiguity counts."""

import pytest

from hil.evaluation.matrix import (
    MatrixSpec,
    bias_table,
    markdown_table,
    mockup_table,
    run_case_group,
    run_matrix,
    summarize,
)

ORACLE = "tests.hil.fake_estimators:build_oracle"


def test_matrix_blank_frames_force_a_loss_and_count_recovery():
    spec = MatrixSpec(
        systems=(ORACLE,),
        distances_m=(3.0,),
        maneuvers=("none",),
        noises=("low",),
        frames=8,
        blank_frames=(3, 4),
        estimator_options={"lose_every": 0},
    )
    rows = run_matrix(spec)
    assert [r.blank for r in rows] == [False] * 3 + [True] * 2 + [False] * 3
    s = summarize(rows)[0]
    # The oracle reads ground truth, so it "sees" through blank frames: no loss, recovery 0.
    assert (s.frames, s.blank, s.valid, s.recovery_max) == (6, 2, 6, 0)
    table = markdown_table([s])
    assert "re-acquired after blanks" in table and "1 frame(s)" in table


def test_matrix_acquisition_mode_estimates_every_frame_without_a_prior():
    spec = MatrixSpec(
        systems=(ORACLE,),
        distances_m=(2.0,),
        maneuvers=("none",),
        noises=("none",),
        frames=4,
        acquisition=True,
    )
    rows = run_matrix(spec)
    acquisition = [r for r in rows if r.mode == "acquisition"]
    assert len(acquisition) == 4
    assert all(not r.had_prior and r.status == "acquired" for r in acquisition)
    summaries = {s.mode: s for s in summarize(rows)}
    assert (summaries["acquisition"].acquired_ok, summaries["acquisition"].acquired_tries) == (4, 4)
    assert summaries["tracking"].acquired_tries == 1  # only its first frame had no prior


def test_matrix_counts_wrong_locks_beyond_the_gate():
    spec = MatrixSpec(
        systems=(ORACLE,),
        distances_m=(2.0,),
        maneuvers=("none",),
        noises=("none",),
        frames=3,
        estimator_options={"offset_m": 0.08},  # 8 cm off: beyond the 5 cm gate
    )
    s = summarize(run_matrix(spec))[0]
    # The oracle claims a 1 mm covariance: an 8 cm error it does not admit is a wrong lock.
    assert s.wrong_locks == 3
    assert s.position_mean_m == pytest.approx(0.08)


def test_matrix_runs_several_mockups_under_a_light_and_tables_their_bias():
    spec = MatrixSpec(
        systems=(ORACLE,),
        distances_m=(0.5,),
        maneuvers=("none",),
        noises=("none",),
        frames=2,
        mockups=("random:3", "random:4"),
        lighting="harsh",
        estimator_options={"offset_m": 0.0003},  # a 0.3 mm bias along the camera's x
    )
    rows = run_matrix(spec)
    assert sorted({r.mockup for r in rows}) == ["random:3", "random:4"]
    bias = bias_table(rows)
    assert f"| {ORACLE} | none | 0.5 m | 4 | +0.30 / +0.00 / +0.00 |" in bias
    assert bias.rstrip().endswith("| ✗ |")  # 0.3 mm is beyond 0.2 mm (the spread is nil)
    per_mockup = mockup_table(rows)
    assert f"| random:3 | {ORACLE} | 2/2 | – | 0 (0) |" in per_mockup
    with pytest.raises(ValueError, match="light must be one of"):
        run_matrix(MatrixSpec(systems=(ORACLE,), lighting="dusk", frames=2))


def test_matrix_renders_with_the_passes_it_is_given(monkeypatch):
    """``--passes`` reaches the renderer (square-on edges to 1/(supersample·passes) px), and a
    campaign of the matrix carries it as a setting."""
    import hil.evaluation.matrix as matrix
    from hil.analysis.campaigns.matrix_runs import matrix_campaign

    seen = []

    class Stop(Exception):
        pass

    def renderer(scene, camera, config):
        seen.append((config.supersample, config.passes))
        raise Stop

    monkeypatch.setattr(matrix, "make_renderer", renderer)
    spec = MatrixSpec(systems=("lines",), distances_m=(2.0,), supersample=4, passes=3)
    with pytest.raises(Stop):
        run_case_group(spec, 2.0, spec.maneuvers[0])
    assert seen == [(4, 3)]
    assert matrix_campaign(spec).parts[0].settings["passes"] == 3


def test_matrix_exposes_with_the_cameras_auto_exposure_when_asked(monkeypatch):
    """``--auto-exposure`` reaches the sensor of every frame, and a campaign of the matrix
    carries it to its trials' spec."""
    import hil.evaluation.matrix as matrix
    from hil.analysis.campaigns.matrix_runs import matrix_campaign
    from hil.analysis.campaigns.trials import matrix_spec

    seen = []
    expose = matrix.expose

    def recording(image, depth_m, K, noise, rng, *args):
        seen.append(noise.auto_exposure)
        return expose(image, depth_m, K, noise, rng, *args)

    monkeypatch.setattr(matrix, "expose", recording)
    spec = MatrixSpec(
        systems=(ORACLE,), distances_m=(2.0,), noises=("low",), frames=2, auto_exposure=True
    )
    run_case_group(spec, 2.0, spec.maneuvers[0])
    assert seen == [True, True]
    part = matrix_campaign(spec).parts[0]
    trial_params = {**part.settings, "systems": [ORACLE]}
    assert matrix_spec(trial_params, seed=0).auto_exposure is True
    assert "auto_exposure" not in matrix_campaign(MatrixSpec(systems=(ORACLE,))).parts[0].settings
