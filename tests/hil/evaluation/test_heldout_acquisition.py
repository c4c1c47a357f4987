"""Held-out mock-up views with a faint panel that the corner and line systems once failed to
acquire, run exactly as the held-out matrix runs them (docs/any_mockup_heldout.md): each
acquired without a prior, and none a wrong lock."""

from dataclasses import replace

import pytest

from hil.evaluation.matrix import run_case_group
from tests.hil.evaluation.test_heldout_wrong_locks import HELD_OUT, wrong_locks


@pytest.mark.parametrize(
    "system, mockup, distance, at_least",
    [
        # Refused for its weakest edge's z 2.6 while every edge had to reach 3 on its own
        # (3 of 4 frames acquired).
        ("corners", "random:112", 0.5, 4),
        # A dark panel refused for a weakest edge at z 2.4 (2 of 4 frames acquired).
        ("lines", "random:110", 2.0, 3),
    ],
)
def test_a_faint_panel_is_acquired_on_its_four_edges_together(system, mockup, distance, at_least):
    _assert_acquired(system, mockup, distance, "none", at_least)


@pytest.mark.parametrize(
    "mockup, distance, at_least",
    [
        # Close up a faint panel's corners are all there is, and a 12 px window saw them at
        # contrast SNR 3.4-3.9 (1 and 2 of 4 frames acquired).
        ("random:110", 0.5, 3),
        ("random:114", 1.2, 3),
    ],
)
def test_a_faint_panel_corner_is_looked_for_again_in_a_wider_window(mockup, distance, at_least):
    _assert_acquired("corners", mockup, distance, "turn_y_10deg", at_least)


@pytest.mark.parametrize("maneuver", ["none", "turn_y_10deg"])
def test_a_small_panels_faint_corner_is_looked_for_again_without_a_prior(maneuver):
    # random:117 at 3 m, exposed: a panel 31 px across, its fasteners too faint to label, so
    # its four corners are all there is; in a window of a fifth of its side (6 px) a corner
    # under high noise fell short of contrast SNR 4 (3 of 4 frames acquired in either case).
    _assert_acquired("corners", "random:117", 3.0, maneuver, 4, auto_exposure=True)


@pytest.mark.parametrize("distance", [1.2, 0.5])
def test_a_bore_as_dark_as_the_ring_is_acquired_on_its_foot(distance):
    # random:101, square on: ring and bore wall near black, the face seen through the bore
    # bright. The bore shows no rim, only its foot — 9 px inside the rim at 1.2 m, 46 px at
    # 0.5 m, where it is the only ellipse extracted, and was taken for the rim or the outer
    # edge only — and no ring verified (0 of 4 frames at either distance). Frames exposed by
    # the camera's auto-exposure.
    _assert_acquired("ellipses", "random:101", distance, "none", 4, auto_exposure=True)


@pytest.mark.parametrize("system, at_least", [("corners", 3), ("lines", 2)])
def test_a_quad_keeps_its_corners_when_the_narrowest_pass_loses_a_side(system, at_least):
    # random:111 at 3 m, square on, exposed: a faint dark panel 35 px across, three strips a
    # side. Its quad was refined to all four edges, then the last, 1 px search lost a point on
    # two of them and the quad gave no hypothesis (1 of 4 frames acquired by either system).
    _assert_acquired(system, "random:111", 3.0, "none", at_least, auto_exposure=True)


def test_a_short_panel_edge_is_found_with_two_of_its_strips_lost():
    # random:107 at 3 m, square on, exposed: a faint panel about 35 px across, three strips
    # an edge; one lost to noise left too few for a line (2 of 4 frames acquired).
    _assert_acquired("lines", "random:107", 3.0, "none", 4, auto_exposure=True)


def test_a_face_that_is_not_square_overturns_a_wrong_quarter_turn():
    # Nothing asymmetric but a 1.50 × 1.41 m face: a pose a quarter turn off, judged against
    # the right turn's half-turned twin (tied with it), was "undecided", and the tilt search
    # bent it to lay the outline on an edge (2 of 4 frames acquired).
    _assert_acquired("corners", "random:102", 1.2, "none", 4, auto_exposure=True)


def _assert_acquired(
    system: str,
    mockup: str,
    distance: float,
    maneuver: str,
    at_least: int,
    *,
    auto_exposure: bool = False,
    frames: int = HELD_OUT.frames,
):
    """At least ``at_least`` frames of the case acquired without a prior, none a wrong lock."""
    spec = replace(HELD_OUT, systems=(system,), auto_exposure=auto_exposure, frames=frames)
    rows = run_case_group(spec, distance, maneuver, mockup)
    acquired = [r for r in rows if r.mode == "acquisition" and r.status != "lost"]
    assert len(acquired) >= at_least, [r.reason for r in rows if r.status == "lost"]
    assert wrong_locks(acquired, distance) == []


def test_a_quarter_turn_is_retried_after_a_flip():
    # A face 1.41 × 1.73 m, the held-out matrix's second frame of the turn at 1.2 m, low
    # noise: at the wrong quarter turn the outline fits neither flip, so the flip was judged
    # wrong and retried, and that retry used up the one the quarter turn then needed — the
    # pose was reported with its flip undecided, or lost.
    second = _matrix_frame_acquired("random:117", 1.2, index=1)
    assert not second.ambiguous


def test_a_tilt_is_not_credited_for_moving_an_outline_edge_into_the_dark():
    # A 1.30 × 1.84 m face against black space, exposed, the matrix's third frame of the turn
    # at 2 m, low noise: the pose was right (0.2°), and a tilt 4° off that moved the outline's
    # side edges 2–4 px off their edges, into the sensor's clipped black where the noise a
    # contour is measured in is lowest, scored 41 z units more; the pose was rejected.
    _matrix_frame_acquired("random:119", 2.0, index=2)


def test_a_tilt_is_not_credited_for_a_contour_only_it_brings_into_view():
    # The face's side lies at the image's left border, just outside the support's margin at
    # the pose (0.2° off, the matrix's second frame of the turn at 1.2 m, low noise); a tilt
    # 2.7° off brought it 3 px in, onto the smoothed edge, and scored 44 z units that the pose
    # had no term to answer: the right pose was refused for a tilt.
    _matrix_frame_acquired("random:110", 1.2, index=1)


def _matrix_frame_acquired(mockup: str, distance: float, *, index: int):
    """One frame of the held-out matrix's corner acquisitions (``--frames 3``, the turn, low
    noise, exposed), asserted acquired and not a wrong lock; returned."""
    spec = replace(HELD_OUT, systems=("corners",), frames=3, noises=("low",), auto_exposure=True)
    rows = run_case_group(spec, distance, "turn_y_10deg", mockup)
    frame = next(r for r in rows if r.mode == "acquisition" and r.index == index)
    assert frame.status == "acquired", frame.reason
    assert wrong_locks([frame], distance) == []
    return frame


def test_a_square_on_panel_corner_settles_under_clipped_noise():
    # A 0.39 m panel at the stand-off under a low side light, the matrix's first frame of the
    # turn at 0.5 m (square on), low noise: one corner's wedge fit, 0.3 px from the truth at
    # contrast SNR 65, swung about its optimum with a growing step and was never declared
    # converged, and the three corners and one fastener left gave no consistent pose.
    frame = _matrix_frame_acquired("random:118", 0.5, index=0)
    assert frame.error.position_m < 0.003


@pytest.mark.parametrize("maneuver", ["none", "turn_y_10deg"])
def test_a_ring_running_out_of_the_frame_is_acquired_from_what_is_in_view(maneuver):
    # random:109 at 0.5 m, exposed: a ring 0.83 m across whose outer edge shows only as arcs
    # at the image's corners, its bore's foot as the largest ellipse. Under high noise one
    # frame of each lost its ring (3 of 4 acquired): square on, 10 of the outer edge's 17
    # samples in view were found where a stage wanted 12; turned, the foot was tried only on
    # the extracted ellipse with the most points, the worse fit of the two.
    _assert_acquired("ellipses", "random:109", 0.5, maneuver, 4, auto_exposure=True)


@pytest.mark.parametrize("system", ["lines", "corners"])
def test_a_wrong_quarter_turn_is_judged_before_the_ring_refuses_it(system):
    # random:101 at 0.5 m, turned, exposed, high noise, the third frame: a panel off the
    # ring's axis, and the one hypothesis a half turn off, where the ring falls off its edges
    # (z -1.3) — refused for that before its turn was checked (5 of 6 frames acquired). Run
    # with the held-out matrix's three frames per case.
    _assert_acquired(system, "random:101", 0.5, "turn_y_10deg", 6, auto_exposure=True, frames=3)


def test_a_wrong_quarter_turn_is_judged_before_its_features_refuse_it():
    # random:108 at 2 m, turned, exposed, low noise, the third frame: a hypothesis a quarter
    # turn off (35 mm / 91°), its fasteners labeled on the wrong ones, was refused for their
    # disagreement (χ²/dof 7.4) before its turn was checked (5 of 6 frames acquired).
    _assert_acquired("corners", "random:108", 2.0, "turn_y_10deg", 6, auto_exposure=True, frames=3)


def test_a_hypothesis_on_the_wrong_side_of_the_line_of_sight_is_flipped_before_it_is_refused():
    # random:110 at 1.2 m, square on, exposed, high noise, the first frame: the one hypothesis
    # 6.2° off, mirrored about the line of sight, its fasteners labeled where that tilt puts
    # them, was refused for their disagreement (χ²/dof 5.0); measured from its planar flip,
    # which the whole model prefers, 1.0° off (5 of 6 frames acquired).
    _assert_acquired("corners", "random:110", 1.2, "none", 6, auto_exposure=True, frames=3)


def test_a_faint_fourth_side_is_found_where_the_other_three_bound_it():
    # random:112 at 3 m, square on, exposed, high noise: a 49 px panel, one side under the
    # contrast an edge must show (3.5 σ, taken at each strip's best position: noise passes it
    # where there is no edge 1 time in 20, so it stays). Scanned along the two sides beside
    # it, its contrast with nothing searched reaches the scan's 4 σ (5 of 6 frames acquired).
    _assert_acquired("lines", "random:112", 3.0, "none", 6, auto_exposure=True, frames=3)
