"""The approach path 2.5 m → 0.5 m (re-centring an off-centre, rotated start) with the
ellipse estimator: tracked throughout, and partial rings at close range still give a pose."""

import itertools
import math

import numpy as np

from configuration.camera import load_camera
from configuration.mockup import load_mockup
from configuration.random_mockup import named_lighting, seed_of
from estimators.measurement import Tracker
from estimators.registry import build_estimator
from hil.evaluation.approach_path import (
    THREE_SIGMA_NEES,
    ApproachPath,
    markdown_approach,
    markdown_visible,
    render_approach,
    run_approach,
)
from hil.evaluation.errors import measurement_error


def test_approach_path_closes_and_recentres():
    path = ApproachPath()
    d0, start = path.offset(0.0)
    d1, end = path.offset(1.0)
    assert (d0, d1) == (2.5, 0.5)
    assert np.linalg.norm(start.p) > 0.3 and np.linalg.norm(end.p) < 1e-12
    assert np.allclose(end.R, np.eye(3))


def test_ellipses_track_the_approach_to_partial_rings():
    results = run_approach("ellipses", frames=30, noise="low", seed=2)
    assert [r.status for r in results] == ["acquired"] + ["tracking"] * 29
    far = [r for r in results if r.distance_m > 1.5]
    near = [r for r in results if r.ring_visible < 0.9]  # the ring cut by the image border
    assert far and near and min(r.ring_visible for r in near) > 0.5
    assert all(r.six_dof for r in far)  # the thruster is in view far out
    for r in results:
        assert r.error.center_m < 0.01
        assert math.degrees(r.error.normal_rad) < (4.0 if r.distance_m > 1.5 else 1.0)
    for r in near:
        assert r.error.center_m < 0.002 and math.degrees(r.error.normal_rad) < 0.5
    table = markdown_approach(results, (2.5, 1.5, 0.8, 0.4))
    assert table.count("\n") == 5 and "| 2.50–1.50 m |" in table
    partial = markdown_visible(results, (1.01, 0.9, 0.5))
    assert f"| 50–90 % | {sum(r.ring_visible < 0.9 for r in results)} |" in partial


#: Issue 13's mock-up: a dark panel on a mid-grey face, a bright ring with bright bolts and no
#: thruster; one dark disc on the face is the only part that breaks the ring's symmetry.
ISSUE_13_MOCKUP = """
name: issue13
bus_face: {width: 1.6, height: 1.6, depth: 0.4, color: [0.40, 0.40, 0.40]}
marman_ring: {outer_diameter: 0.60, radial_width: 0.05, protrusion: 0.06,
              color: [0.78, 0.78, 0.78], segments: 512}
centre_panel: {side: 0.30, thickness: 0.008, color: [0.12, 0.12, 0.12]}
fasteners:
  - {name: ring_bolt, surface: ring, diameter: 0.022, color: [0.95, 0.95, 0.95],
     circle_pattern: {radius: 0.275, count: 8, phase_deg: 22.5}}
  - {name: marker, surface: bus, diameter: 0.06, color: [0.05, 0.05, 0.05],
     positions: [[0.42, 0.30]]}
thruster: null
"""


def test_ellipses_never_take_the_rings_mirror_pose_as_decided(tmp_path):
    """The ring alone, tracked from 2.5 m to 0.5 m: its mirror pose (14–15° off here) fits
    the edges nearly as well out to ~1.3 m. It was taken as decided on 2 of 60 frames when a
    15 % cost ratio judged fits on the edge points each had found; judged on the same points
    against their noise, the frame decides only when it can."""
    mockup = tmp_path / "issue13.yaml"
    mockup.write_text(ISSUE_13_MOCKUP)
    results = run_approach("ellipses", frames=60, noise="low", seed=0, mockup=str(mockup))
    assert all(r.status != "lost" for r in results)
    confident = [r for r in results if not r.ambiguous]
    worst = max(math.degrees(r.error.normal_rad) for r in confident)
    assert worst < 5.0, f"an unflagged ring normal {worst:.1f}° off (the mirror pose)"
    assert sum(r.overconfident for r in results) <= 2


def test_the_approach_path_under_a_dim_light_is_exposed_by_the_cameras_auto_exposure():
    """Under a light at a fifth of the default the frames are dim as rendered; with the
    camera's auto-exposure the mock-up's brightest pixels come back near full scale."""
    from configuration.camera import load_camera
    from configuration.mockup import load_mockup
    from configuration.render import Lighting
    from hil.evaluation.approach_path import render_approach

    info = load_camera("reference").camera_info()
    dim = Lighting(ambient=0.09, diffuse=0.11)

    def brightest(auto_exposure: bool) -> float:
        frames = render_approach(
            info,
            load_mockup("default"),
            frames=2,
            noise="none",
            light=dim,
            auto_exposure=auto_exposure,
        )
        return max(float(np.percentile(f.frame.image, 99.9)) for f in frames) / 255.0

    assert brightest(False) < 0.3
    assert brightest(True) > 0.8


def test_the_approach_path_renders_anti_aliased_when_asked(monkeypatch):
    """One sample a pixel leaves every edge a staircase; close up the panel systems' fits
    read it as the panel's edge to a fraction of the noise they claim (the lines' over-confident
    frames at 0.5 m, docs/any_mockup.md). ``supersample`` reaches the renderer, and changes
    the frames."""
    import hil.evaluation.approach_path as approach_path
    from configuration.camera import load_camera
    from configuration.mockup import load_mockup

    info = load_camera("reference").camera_info()
    configs = []
    make_renderer = approach_path.make_renderer

    def recording(scene, camera, render):
        configs.append(render)
        return make_renderer(scene, camera, render)

    monkeypatch.setattr(approach_path, "make_renderer", recording)

    def first_frame(supersample: int) -> np.ndarray:
        frames = approach_path.render_approach(
            info, load_mockup("default"), frames=2, noise="none", supersample=supersample
        )
        return next(iter(frames)).frame.image

    aliased, smooth = first_frame(1), first_frame(4)
    assert [c.supersample for c in configs] == [1, 4]
    assert np.abs(smooth.astype(int) - aliased.astype(int)).max() > 50


def test_ellipses_do_not_track_a_bores_rim_and_foot_as_the_ring():
    """Random mock-up 107 on the open-loop path (3 m start, auto-exposure, 4 × 4 samples), frames
    107–108 at 0.57–0.56 m. Frame 108 was tracked 17.9 mm / 9.7° off claiming 0.2° (NEES 3356):
    its fit took every sample of the bore (a dark wall between rim and foot) for the rim and,
    scaling each edge set's noise by its own residuals, discounted the ring's outer edge, which
    it left pixels off the fitted ellipse. Such a fit is no longer the ring's
    (``ellipses._outer_misfit_px``)."""
    mockup = "random:107"
    info = load_camera("reference").camera_info()
    config = load_mockup(mockup)
    frames = itertools.islice(
        render_approach(
            info,
            config,
            frames=120,
            path=ApproachPath(start_distance_m=3.0),
            light=named_lighting("random", seed_of(mockup)),
            auto_exposure=True,
            supersample=4,
            start=107,
        ),
        2,
    )
    target = config.target_model()
    tracker = Tracker(build_estimator("ellipses", target, info))
    for rendered in frames:
        m = tracker.update(rendered.frame)
        error = measurement_error(m, rendered.frame.truth.X_CT, target)
        assert m.valid, m.reason
        if not m.ambiguous:
            assert error.nees_circle < THREE_SIGMA_NEES[5], (rendered.index, error)
    assert rendered.index == 108 and m.status == "tracking"
    assert error.center_m < 0.002
