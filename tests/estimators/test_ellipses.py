"""The ellipse estimator against simulator ground truth: acquisition, tracking, re-acquisition,
bad frames, covariance calibration, other cameras and other mock-up geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from configuration.camera import load_camera
from configuration.mockup import MockupConfig, load_mockup
from configuration.random_mockup import named_lighting, seed_of
from configuration.render import NoiseConfig, RenderConfig
from estimators import ellipses as ellipses_module
from estimators.conics import circle_plane_basis
from estimators.ellipses import EllipseEstimator, build
from estimators.frame import Frame, GroundTruth
from estimators.geometry import Pose
from estimators.measurement import Tracker
from hil.evaluation.approach_path import ApproachPath
from hil.evaluation.errors import measurement_error
from hil.evaluation.matrix import MatrixSpec, case_seed
from hil.evaluation.scenarios import MANEUVERS, camera_pose_for, target_offset
from hil.evaluation.targets import is_wrong_lock
from sim_backends.renderer import PybulletRenderer
from sim_backends.scene import MockupScene
from sim_backends.sensor import expose, frame_rng
from tests.estimators import rendered

REFERENCE = load_camera("reference").camera_info()
DEFAULT = load_mockup("default")


def render_frames(mockup: MockupConfig, camera, poses, noise: str, seed: int) -> list[Frame]:
    """Frames (with ground truth) of the mock-up seen from camera poses ``X_WC``."""
    frames = []
    with MockupScene(mockup) as scene:
        renderer = PybulletRenderer(scene, camera, RenderConfig())
        for i, X_WC in enumerate(poses):
            r = renderer.render(X_WC)
            image = expose(
                r.image, r.depth_m, camera.K, NoiseConfig(preset=noise), frame_rng(seed, i)
            )
            frames.append(Frame(image, i / 30.0, camera, i, GroundTruth(r.X_CT, r.X_WC)))
    return frames


def poses(*cases) -> list[Pose]:
    """Camera poses for (distance, target offset) cases."""
    return [camera_pose_for(d, offset)[0] for d, offset in cases]


@pytest.fixture(scope="module")
def sequence_2m() -> list[Frame]:
    """A 2 m sequence turning the target by up to 8° about y, low noise."""
    cases = [
        (2.0, target_offset(0.02, -0.01, 0.0, 0.0, math.radians(8.0 * math.sin(k / 3)), 0.0))
        for k in range(8)
    ]
    return render_frames(DEFAULT, REFERENCE, poses(*cases), "low", 11)


@pytest.fixture(scope="module")
def estimator() -> EllipseEstimator:
    return build(DEFAULT.target_model(), REFERENCE)


def _errors(m, frame, target=None):
    return measurement_error(m, frame.truth.X_CT, target or DEFAULT.target_model())


def _lit_random_frame(
    name: str, distance: float, offset, seed: int = 0, noise: str = "low"
) -> Frame:
    """A frame of random mock-up ``name`` under its own random light, 4 × 4 samples a pixel,
    the camera's auto-exposure and ``noise``."""
    mockup = load_mockup(name)
    X_WC = camera_pose_for(distance, offset)[0]
    with MockupScene(mockup) as scene:
        config = RenderConfig(supersample=4, lighting=named_lighting("random", seed_of(name)))
        r = PybulletRenderer(scene, REFERENCE, config).render(X_WC)
    exposure = NoiseConfig(preset=noise, auto_exposure=True)
    image = expose(r.image, r.depth_m, REFERENCE.K, exposure, frame_rng(seed, 0))
    return Frame(image, 0.0, REFERENCE, 0, GroundTruth(r.X_CT, X_WC))


def _prior_behind(X_CT: Pose, metres: float) -> Pose:
    """``X_CT`` moved ``metres`` farther along its line of sight (a track one frame behind
    on an approach)."""
    return Pose(X_CT.R, X_CT.p * (1.0 + metres / np.linalg.norm(X_CT.p)))


@pytest.mark.parametrize(
    ("distance", "normal_bound_deg"),
    [(3.0, 6.0), (1.2, 1.0)],
)
def test_ellipses_acquire_ring_and_thruster_without_prior(estimator, distance, normal_bound_deg):
    cases = [(distance, target_offset(0.03, 0.02, 0.0, 0.02, -0.03, 0.1))]
    (frame,) = render_frames(DEFAULT, REFERENCE, poses(*cases), "low", 3)
    m = estimator.estimate(frame, None)
    assert m.status == "acquired", m.reason
    assert m.X_CT is not None and m.covariance is not None  # the thruster was found: 6-DOF
    e = _errors(m, frame)
    assert e.center_m < 0.01
    assert math.degrees(e.normal_rad) < normal_bound_deg
    assert math.degrees(e.roll_rad) < 3.0
    assert m.circle == "ring_outer" and abs(np.linalg.norm(m.normal_C) - 1) < 1e-9
    assert m.normal_C @ m.center_C < 0  # the face's normal points toward the camera
    assert len(m.features["labeled"]) > 50 and m.residual_px < 1.5


def test_ellipses_without_prior_do_not_trust_a_thruster_found_on_the_mirror_pose(estimator):
    """A 3 m high-noise frame (the reference matrix's turn_y case, frame 21) where the thruster
    search succeeded on the mirror pose of the ring (19° off) and the refit from the other pose
    with that roll failed: the other pose's own thruster must be looked for before the first
    is trusted. The answer is the right pose, or says it is ambiguous."""
    maneuver = next(m for m in MANEUVERS if m.name == "turn_y_10deg")
    spec = MatrixSpec(systems=("ellipses",), noises=("low", "high"))
    seed = case_seed(spec, 0, spec.maneuvers.index(maneuver.name), 1)
    X_WC = camera_pose_for(3.0, maneuver.offset(21 / 30))[0]
    with MockupScene(DEFAULT) as scene:
        r = PybulletRenderer(scene, REFERENCE, RenderConfig()).render(X_WC)
    image = expose(r.image, r.depth_m, REFERENCE.K, NoiseConfig(preset="high"), frame_rng(seed, 21))
    frame = Frame(image, 0.0, REFERENCE, 21, GroundTruth(r.X_CT, r.X_WC))
    m = estimator.estimate(frame)
    assert m.status == "acquired", m.reason
    error = _errors(m, frame)
    assert not is_wrong_lock(error, 3.0, ambiguous=m.ambiguous)
    assert m.ambiguous or error.normal_rad < math.radians(10.0)


def test_ellipses_ring_holes_fix_the_weak_tilt_at_3m():
    """At 3 m near head-on the ring's edges and the thruster leave one tilt axis weak; the
    ring's holes, fitted as discs and added to the 6-DOF fit, bring the normal's error under
    the issue's 2° — and well under the edges-only estimate on the same frames."""
    target = DEFAULT.target_model()
    cases = [
        (3.0, target_offset(0.02 * k - 0.04, 0.01, 0.0, 0.01 * k, -0.015 * k, 0.1 * k))
        for k in range(6)
    ]
    frames = render_frames(DEFAULT, REFERENCE, poses(*cases), "low", 31)
    estimators = {True: build(target, REFERENCE), False: build(target, REFERENCE, ring_holes=False)}
    errors: dict[bool, list[float]] = {True: [], False: []}
    for frame in frames:
        for holes, estimator in estimators.items():
            m = estimator.estimate(frame, frame.truth.X_CT)
            assert m.X_CT is not None, m.reason
            errors[holes].append(math.degrees(_errors(m, frame).normal_rad))
    assert np.mean(errors[True]) < 2.0 and max(errors[True]) < 3.0, errors
    assert np.mean(errors[True]) < 0.6 * np.mean(errors[False]), errors


def test_ellipses_judge_the_rings_two_poses_with_its_walls():
    """A deep, dark ring (``rendered.DEEP_RING_MOCKUP``) turned 8.7° at 3 m: its bore wall
    shifts the inner edge by pixels, more than the ring's mirror pose moves it. Judged with the
    rim alone the mirror (17° off) fitted better and was taken as decided (13.5° and 18° off on
    these frames, unflagged); judged by the model the fit uses (each bore sample against the
    nearer of the bore's rim and foot) the right pose is chosen, and from no prior the answer
    is right or says it is ambiguous."""
    target = rendered.target("deep_ring")
    estimator = build(target, REFERENCE)
    for seq, turn_deg in enumerate((8.66, -8.66)):
        offset = (0.0, 0.0, 0.0, 0.0, math.radians(turn_deg), 0.0)
        frame = rendered.frame(3.0, offset, noise="low", seed=5, seq=seq, mockup="deep_ring")
        m = estimator.estimate(frame, frame.truth.X_CT)
        assert m.valid, m.reason
        assert math.degrees(_errors(m, frame, target).normal_rad) < 2.0
        m = estimator.estimate(frame, None)
        assert m.valid, m.reason
        assert m.ambiguous or math.degrees(_errors(m, frame, target).normal_rad) < 2.0


@pytest.mark.parametrize(
    ("name", "distance", "normal_bound_deg"), [("random:112", 2.0, 2.0), ("random:107", 0.5, 1.0)]
)
def test_ellipses_track_a_turn_across_the_line_of_sight_right_or_ambiguous(
    name, distance, normal_bound_deg
):
    """The held-out matrix's turn: the target at −8.66° about y, tracked from a prior at +8.66°
    — on the side of the line of sight where the ring's other pose lies. The true pose failed
    its support checks (random:112 at 2 m: a faint thruster found at 0.36 of its length a pixel
    or two from where the wrong pose puts it; random:107 at 0.5 m: the bore's rim at 0.14), and
    "not verified" was read as "wrong": the other pose, 13–18° off, was answered as decided or
    kept because of the prior (NEES 2000–12 000). The answer is now right or says it is
    ambiguous, with the right pose as its alternative."""
    target = load_mockup(name).target_model()
    turn = math.radians(8.66)
    frame = _lit_random_frame(name, distance, target_offset(0.0, 0.0, 0.0, 0.0, -turn, 0.0))
    prior = camera_pose_for(distance, target_offset(0.0, 0.0, 0.0, 0.0, turn, 0.0))[1]
    m = build(target, REFERENCE).estimate(frame, prior)
    assert m.valid, m.reason
    error = _errors(m, frame, target)
    if math.degrees(error.normal_rad) < normal_bound_deg:
        return
    assert m.ambiguous, (error, m.from_prior)
    true_normal = frame.truth.X_CT.R @ target.circle("ring_outer").normal_T
    alternative_deg = math.degrees(math.acos(min(1.0, m.alternative_normal_C @ true_normal)))
    assert alternative_deg < normal_bound_deg, alternative_deg


@pytest.mark.parametrize("seed", [0, 3])
def test_ellipses_do_not_take_a_thruster_found_on_a_pose_the_rings_edges_refute(seed):
    """random:116 at 1.2 m turned 8.66°, no prior: its thruster is out of view, and the roll
    search round the ring's other pose (16° off) took a bolt 96° round for it; "the thruster
    found on the other pose decides" answered that pose, though its ring edges cost ten times
    the true pose's (NEES 5·10⁴–1.6·10⁵ on half of the noise draws). The ring's own edges now
    outweigh such a find."""
    name = "random:116"
    target = load_mockup(name).target_model()
    offset = target_offset(0.0, 0.0, 0.0, 0.0, math.radians(8.66), 0.0)
    frame = _lit_random_frame(name, 1.2, offset, seed)
    m = build(target, REFERENCE).estimate(frame, None)
    assert m.valid, m.reason
    error = _errors(m, frame, target)
    assert math.degrees(error.normal_rad) < 1.0 and error.center_m < 0.005, error


def test_ellipses_do_not_read_a_ring_from_two_straight_edges():
    """random:117 square on at 3 m, high noise, no prior (one noise draw in 40): the ring not
    extracted, an "ellipse" 1968 × 106 px fitted across the image from two nearly straight
    arcs gave a ring 0.28 m away, seen edge-on, that verified at half its edges' length — a
    wrong lock 2.7 m off. Its length was not measured (28 %); dropped, the ring is found."""
    name = "random:117"
    target = load_mockup(name).target_model()
    frame = _lit_random_frame(name, 3.0, target_offset(0.0, 0.0, 0.0, 0.0, 0.0, 0.0), 20, "high")
    m = build(target, REFERENCE).estimate(frame, None)
    assert m.valid, m.reason
    assert not is_wrong_lock(_errors(m, frame, target), 3.0, ambiguous=m.ambiguous)
    assert _errors(m, frame, target).center_m < 0.1


@pytest.mark.parametrize("seed", [0, 1])
def test_ellipses_covariance_holds_what_an_unresolved_outer_wall_may_do(seed):
    """The deep, dark ring (``rendered.DEEP_RING_MOCKUP``, 8.5 cm proud) at 3 m turned 12°:
    its outer wall shows as a band of 1–3 px outside the ring's front on one side, blurred
    into the edge, which then lies somewhere between rim and foot. The fit takes the rim and
    was 2.7° off claiming a fraction of that (NEES 37 and 40, 5 degrees of freedom); with
    what the band may do in the covariance (``_outer_wall_covariance``) the error lies within
    its own 3σ region (χ²₅ 99.73 %: 18.2; NEES 15 and 10)."""
    target = rendered.target("deep_ring")
    offset = (0.0, 0.0, 0.0, math.radians(3.0), math.radians(12.0), 0.0)
    frame = rendered.frame(3.0, offset, noise="low", seed=seed, mockup="deep_ring", supersample=4)
    m = build(target, REFERENCE).estimate(frame, frame.truth.X_CT)
    assert m.valid, m.reason
    error = _errors(m, frame, target)
    assert math.degrees(error.normal_rad) < 4.0 and error.nees_circle < 18.2, error


def test_ellipses_measure_the_outer_wall_where_the_fit_would_be_without_it():
    """random:109 (a ring 7.2 cm proud, a thruster) at the open-loop path's start, 3 m, 2.3°
    off axis, rendered without noise: the fit leans 3.2° toward the outer wall's band and so
    narrows the band it sees at its own pose (0.25 px; 0.9 px at the truth). Measured there,
    the wall's term held a quarter of the error (6-DOF NEES 49 claiming the roll to 0.15°);
    measured where the fit would land without the wall (a fixed point), the error lies within
    its own 3σ region (χ²₆ 99.73 %: 20.1; NEES 18). Neighbouring frames of the path, at 21–26,
    are still just beyond it: the fit moves further than the band's linear response."""
    name = "random:109"
    distance, offset = ApproachPath(start_distance_m=3.0).offset(2 / 119)
    frame = _lit_random_frame(name, distance, offset, noise="none")
    target = load_mockup(name).target_model()
    m = build(target, REFERENCE).estimate(frame, None)
    assert m.valid and m.X_CT is not None, m.reason
    error = _errors(m, frame, target)
    assert math.degrees(error.rotation_geodesic_rad) > 2.0  # the wall's pull is there
    assert error.nees_pose < 20.1, error


@pytest.mark.parametrize("turn_deg", [8.66, -8.66])
def test_ellipses_acquire_a_deep_ring_whose_lit_bore_wall_mimics_its_edge(turn_deg):
    """The deep, dark ring at 3 m without noise: the lit bore wall shows an edge of the outer
    edge's polarity a ring's width (10 px) inside it, which the extractor's edge search took for
    the outer edge over a sixth of the curve; a least-squares ellipse through both was 9 %
    flat (b/a 0.91 for 0.99), and the ring's fit from it stuck 21–23° off, taken as decided.
    The extractor's fit now leaves such an arc out, and the ring is acquired right."""
    target = rendered.target("deep_ring")
    offset = (0.0, 0.0, 0.0, 0.0, math.radians(turn_deg), 0.0)
    frame = rendered.frame(3.0, offset, noise="none", mockup="deep_ring", supersample=4)
    m = build(target, REFERENCE).estimate(frame, None)
    assert m.valid, m.reason
    error = _errors(m, frame, target)
    assert math.degrees(error.normal_rad) < 1.0 and error.center_m < 0.01


def test_ellipses_acquire_the_best_supported_ring_not_the_first_that_verifies():
    """Random mock-up 206 (a dark ring 7.7 cm tall, its bore wall in shade) under its own
    random light, head-on at 0.5 m, where the ring runs out of the frame. At the first
    smoothing the bore's rim is too faint; at the second, arcs of the ring and of the bore's
    wall join into stray ellipses, off centre, whose reading as the ring's inner edge implies a
    larger ring and so came first. One verified (outer edge 36 % found, inner 61 %) and was
    taken, 6 cm and 17° off. The true ring verifies too, its outer edge found all round: the
    best supported ring wins."""
    name = "random:206"
    mockup = load_mockup(name)
    target = mockup.target_model()
    lighting = named_lighting("random", seed_of(name))
    X_WC = camera_pose_for(0.5, target_offset(0.0, 0.0, 0.0, 0.0, 0.0, 0.0))[0]
    with MockupScene(mockup) as scene:
        config = RenderConfig(supersample=4, lighting=lighting)
        r = PybulletRenderer(scene, REFERENCE, config).render(X_WC)
    image = expose(r.image, r.depth_m, REFERENCE.K, NoiseConfig(preset="low"), frame_rng(0, 0))
    frame = Frame(image, 0.0, REFERENCE, 0, GroundTruth(r.X_CT, X_WC))
    m = build(target, REFERENCE).estimate(frame, None)
    assert m.valid, m.reason
    error = _errors(m, frame, target)
    assert error.center_m < 0.005 and math.degrees(error.normal_rad) < 1.0, error


def test_ellipses_track_a_deep_bore_from_a_prior_off_in_depth():
    """Random mock-up 100 (its bore 8 cm deep) under its own light at 1.6 m, turned 4°, tracked
    from a prior 3 cm too far (a track one frame behind on the approach path). Its inner edge
    is the bore's rim over three quarters of its length and the foot over the rest; split
    between the two at the prior, the foot's samples all fell nearer the rim and the fit
    tilted the ring to hold them: 4.9° off, unflagged (the open-loop path drifted 4° over nine
    frames, claiming 0.3°). Split again at the fitted pose, the ring is right."""
    name = "random:100"
    target = load_mockup(name).target_model()
    offset = target_offset(0.02, -0.01, 0.0, math.radians(4.0), math.radians(2.0), 0.3)
    frame = _lit_random_frame(name, 1.6, offset)
    m = build(target, REFERENCE).estimate(frame, _prior_behind(frame.truth.X_CT, 0.03))
    assert m.valid, m.reason
    error = _errors(m, frame, target)
    assert math.degrees(error.normal_rad) < 1.0 and error.center_m < 0.005, error


@pytest.mark.parametrize("seed", [0, 1])
def test_ellipses_track_a_faint_ring_not_its_deep_bore_close_up(seed):
    """Random mock-up 104 (a faint ring, its bore 8.8 cm deep) under its own light at 0.8 m,
    tracked from a prior 2.5 cm too far (one frame behind on the approach path). The search
    from the prior misses the ring's edges; the ellipses extracted around it were labeled by
    their nearness to the predicted edges, and the bore's rim and foot — extracted where the
    ring's faint outer edge was not — were taken for the ring: 12 cm too far, as a confident
    track (the open-loop path held it down to the stand-off, NEES ~10⁵). They are now
    verified as acquisition verifies them, and the ring is found."""
    name = "random:104"
    target = load_mockup(name).target_model()
    offset = target_offset(0.01, -0.01, 0.0, math.radians(2.0), math.radians(-2.0), 0.5)
    frame = _lit_random_frame(name, 0.8, offset, seed)
    m = build(target, REFERENCE).estimate(frame, _prior_behind(frame.truth.X_CT, 0.025))
    assert m.valid, m.reason
    error = _errors(m, frame, target)
    assert error.center_m < 0.005 and math.degrees(error.normal_rad) < 1.0, error


@pytest.mark.parametrize("distance", [0.62, 0.67])
def test_ellipses_acquire_a_faint_ring_not_the_ring_its_deep_bore_implies(distance):
    """Random mock-up 104 under its own light, 0.62–0.67 m, no prior: the ring's hypotheses
    include the bore's rim and foot read as the ring's two edges (a ring 10 cm farther),
    which verified with its foot — a strong edge all round — as the "inner edge" over 0.99
    of its length, against 0.47 / 0.57 for the true ring's faint edges: the wrong ring won,
    9–10 cm off, and so did a track falling back to it. Judged with the bore's foot too
    (only the true ring explains it), the ring is right."""
    name = "random:104"
    target = load_mockup(name).target_model()
    offset = target_offset(0.01, -0.01, 0.0, math.radians(2.0), math.radians(-2.0), 0.5)
    frame = _lit_random_frame(name, distance, offset)
    m = build(target, REFERENCE).estimate(frame, None)
    assert m.valid, m.reason
    error = _errors(m, frame, target)
    assert error.center_m < 0.005 and math.degrees(error.normal_rad) < 1.0, error


@pytest.mark.parametrize(("distance", "turn_deg"), [(0.5, 0.0), (0.6, 8.0), (0.8, 0.0), (0.8, 8.0)])
def test_ellipses_acquire_a_ring_with_a_deep_narrow_bore_close_up(distance, turn_deg):
    """``rendered.DEEP_BORE_MOCKUP`` close up, no prior: the bore's rim and foot (a concentric
    pair of opposite polarity, ratio near the ring's own) were taken for the ring's two edges,
    or the foot alone for its inner edge (the ring 6–8 cm too far), and the rim, whose wall in
    shade gives it the outer edge's polarity, was searched with the other one and never found
    (at 0.8 m a stray ellipse then won, 20° off). Now the bore's reading of a pair is tried,
    and the image chooses the bore's polarity."""
    target = rendered.target("deep_bore")
    offset = (0.01, 0.0, 0.0, 0.0, math.radians(turn_deg), 0.0)
    frame = rendered.frame(distance, offset, noise="low", seed=1, mockup="deep_bore", supersample=2)
    m = build(target, REFERENCE).estimate(frame, None)
    assert m.valid, m.reason
    error = _errors(m, frame, target)
    assert error.center_m < 0.005 and math.degrees(error.normal_rad) < 2.0, error


def test_ellipses_track_a_sequence_with_the_prior(estimator, sequence_2m):
    tracker = Tracker(estimator)
    statuses, normals, rolls = [], [], []
    for frame in sequence_2m:
        m = tracker.update(frame)
        statuses.append(m.status)
        e = _errors(m, frame)
        normals.append(math.degrees(e.normal_rad))
        rolls.append(math.degrees(e.roll_rad))
    assert statuses == ["acquired"] + ["tracking"] * (len(sequence_2m) - 1)
    assert np.mean(normals) < 2.5 and max(normals) < 6.0
    assert max(rolls) < 3.0


def test_ellipses_reacquire_after_blank_frames(estimator, sequence_2m):
    """Three blank frames (uniform grey with the same noise): lost with a reason each, then
    the first real frame is acquired again without help."""
    rng = np.random.default_rng(5)
    blank = [
        Frame(
            np.clip(90 + 56 * rng.standard_normal((480, 640)), 0, 255).astype(np.uint8),
            0.0,
            REFERENCE,
            100 + k,
        )
        for k in range(3)
    ]
    tracker = Tracker(estimator)
    sequence = [*sequence_2m[:2], *blank, *sequence_2m[2:4]]
    statuses = [tracker.update(frame).status for frame in sequence]
    assert statuses == ["acquired", "tracking", "lost", "lost", "lost", "acquired", "tracking"]


def test_ellipses_return_lost_for_bad_frames(estimator):
    shape_wrong = Frame(np.zeros((100, 100), np.uint8), 0.0, REFERENCE, 0)
    empty = Frame(np.zeros((0, 0), np.uint8), 0.0, REFERENCE, 1)
    nan = Frame(np.full((480, 640), np.nan, np.float32), 0.0, REFERENCE, 2)
    black = Frame(np.zeros((480, 640), np.uint8), 0.0, REFERENCE, 3)
    rng = np.random.default_rng(1)
    noise = Frame(rng.integers(0, 256, (480, 640), dtype=np.uint8), 0.0, REFERENCE, 4)
    reasons = {}
    for frame in (shape_wrong, empty, nan, black, noise):
        m = estimator.estimate(frame, Pose.from_rpy(math.pi, 0, 0, np.array([0, 0, 2.0])))
        assert m.status == "lost" and m.X_CT is None and m.center_C is None
        reasons[frame.seq] = m.reason
    assert "shape" in reasons[0] and "empty" in reasons[1] and "NaN" in reasons[2]
    assert "no contrast (black" in reasons[3] and "noise" in reasons[4]
    # Another camera's frame never reaches an ellipse estimator built by estimators.registry
    # (one per CameraInfo): handed one directly, it is a bug, caught by an internal check.
    other_camera = load_camera("oak_d_rgb").camera_info()
    with pytest.raises(AssertionError, match="intrinsics"):
        estimator.estimate(Frame(np.zeros((800, 1280, 3), np.uint8), 0.0, other_camera, 5))


def test_ellipses_covariance_is_calibrated(estimator):
    """Normalised estimation error squared of the 5-DOF circle pose over frames at 2 and
    1.2 m: its mean is near the 5 degrees of freedom (χ²), neither tiny nor huge."""
    cases = [
        (d, target_offset(0.04 * k - 0.08, 0.03, 0.0, 0.03 * k, -0.02, 0.2))
        for d in (2.0, 1.2)
        for k in range(5)
    ]
    frames = render_frames(DEFAULT, REFERENCE, poses(*cases), "low", 21)
    ring = DEFAULT.target_model().circle("ring_outer")
    nees = []
    for frame in frames:
        X = frame.truth.X_CT
        m = estimator.estimate(frame, X)
        n_true = X.R @ ring.normal_T
        u, v = circle_plane_basis(m.normal_C)
        dn = n_true - m.normal_C
        e = np.concatenate([X.apply(ring.center_T) - m.center_C, [dn @ u, dn @ v]])
        nees.append(e @ np.linalg.solve(m.covariance_5dof, e))
        if m.X_CT is not None:  # and the 6-DOF covariance's convention (rotation on the left)
            rotation = Rotation.from_matrix(X.R @ m.X_CT.R.T).as_rotvec()
            e6 = np.concatenate([rotation, X.p - m.X_CT.p])
            assert e6 @ np.linalg.solve(m.covariance, e6) < 60.0
    assert 1.5 < np.mean(nees) < 15.0, nees


def test_ellipses_distorted_oak_d_camera():
    """The OAK-D profile (1280×800, lens distortion): edge points are undistorted before the
    conic fits, so the pose stays accurate — a camera the estimator was not tuned on."""
    camera = load_camera("oak_d_rgb").camera_info()
    cases = [(2.0, target_offset(0.25, -0.12, 0.0, 0.05, 0.08, 0.3))]  # the ring off-centre
    (frame,) = render_frames(DEFAULT, camera, poses(*cases), "low", 4)
    m = build(DEFAULT.target_model(), camera).estimate(frame, None)
    assert m.valid, m.reason
    e = _errors(m, frame)
    assert e.center_m < 0.01 and math.degrees(e.normal_rad) < 1.5
    assert m.X_CT is not None and math.degrees(e.roll_rad) < 1.0


def test_ellipses_other_mockup_geometry():
    """A Ø0.8 m ring with a thruster elsewhere (another place, size and protrusion): the
    geometry comes from the model, nothing is tuned to the default mock-up."""
    mockup = MockupConfig.model_validate(
        {
            "name": "large_ring",
            "bus_face": {"width": 2.0, "height": 2.0},
            "marman_ring": {"outer_diameter": 0.8, "radial_width": 0.07, "protrusion": 0.04},
            "centre_panel": {"side": 0.4},
            "thruster": {"center": [-0.62, 0.5], "exit_diameter": 0.16, "length": 0.14},
            "fasteners": [
                {
                    "name": "bolt",
                    "surface": "ring",
                    "diameter": 0.025,
                    "circle_pattern": {"radius": 0.365, "count": 8},
                }
            ],
        }
    )
    target = mockup.target_model()
    cases = [(2.5, target_offset(-0.05, 0.08, 0.0, -0.1, 0.06, -0.4))]
    (frame,) = render_frames(mockup, REFERENCE, poses(*cases), "low", 8)
    m = build(target, REFERENCE).estimate(frame, None)
    assert m.valid, m.reason
    e = _errors(m, frame, target)
    assert e.center_m < 0.01 and math.degrees(e.normal_rad) < 2.0
    assert m.X_CT is not None and math.degrees(e.roll_rad) < 2.0


def test_ellipses_build_rejects_unknown_options_and_targets():
    with pytest.raises(ValueError, match="unknown ellipse estimator option"):
        build(DEFAULT.target_model(), REFERENCE, sigma=3)
    assert build(DEFAULT.target_model(), REFERENCE, max_range_m=9.0).settings.max_range_m == 9.0
    target = DEFAULT.target_model()
    no_ring = type(target)(target.name, target.panel_corners_T, target.point_features, ())
    with pytest.raises(ValueError, match="ring_outer"):
        build(no_ring, REFERENCE)


def test_each_projected_circle_is_sampled_once_per_pose_and_scale(monkeypatch):
    """Close up the ring's polarity probes and the search after them asked for the same samples
    of the bore's edge up to three times a stage (about 1 ms of the 33 ms a frame at 0.5 m)."""
    import estimators.ellipses as ellipses
    from tests.estimators import rendered

    asked = []
    sample = ellipses.sample_projected_circle

    def counting(center_C, normal_C, radius, camera, **settings):
        asked.append((center_C.tobytes(), normal_C.tobytes(), radius, *sorted(settings.items())))
        return sample(center_C, normal_C, radius, camera, **settings)

    monkeypatch.setattr(ellipses, "sample_projected_circle", counting)
    f = rendered.frame(0.5, noise="low")
    m = build(rendered.target(), f.info).estimate(f, f.truth.X_CT)
    assert m.valid, m.reason
    assert len(asked) >= 4
    assert len(set(asked)) == len(asked)


@pytest.mark.parametrize(("prior_shift_m", "abandoned"), [(0.0, False), (0.015, True)])
def test_ellipses_track_abandons_a_fine_stage_whose_ring_lies_beyond_its_window(
    estimator, monkeypatch, prior_shift_m, abandoned
):
    """At 1.2 m a prior 1.5 cm to the side puts the ring ~7 px from its prediction, beyond the
    fine stage's 3 px window, whose pose the track would discard and search again coarse to
    fine (issue 12: 27 of the bench's 30 frames at 1.2 m). The stage is abandoned once the
    ring's outer edge shows it — the thruster's and bore's searches and the fit skipped — and
    the measurement is the one the whole stage would have led to; from a prior on the truth
    nothing is abandoned."""
    offset = target_offset(0.02, -0.01, 0.0, math.radians(3.0), math.radians(-2.0), 0.2)
    (frame,) = render_frames(DEFAULT, REFERENCE, poses((1.2, offset)), "low", 4)
    X_CT = frame.truth.X_CT
    prior = Pose(X_CT.R, X_CT.p + np.array([prior_shift_m, 0.0, 0.0]))
    searched = []
    circle_edges = EllipseEstimator._circle_edges

    def spy(self, *args, **kwargs):
        searched.append(args[2].name)
        return circle_edges(self, *args, **kwargs)

    monkeypatch.setattr(EllipseEstimator, "_circle_edges", spy)
    m = estimator.estimate(frame, prior)
    searches = len(searched)
    searched.clear()
    monkeypatch.setattr(ellipses_module, "_SHIFT_MARGIN_PX", math.inf)  # never abandoned
    whole = estimator.estimate(frame, prior)
    assert m.status == whole.status == "tracking", m.reason
    assert np.allclose(m.X_CT.p, whole.X_CT.p, atol=1e-9) and np.allclose(
        m.X_CT.R, whole.X_CT.R, atol=1e-9
    )
    assert (searches < len(searched)) == abandoned, (searches, len(searched))
    error = _errors(m, frame)
    assert error.position_m < 0.002 and math.degrees(error.attitude_rad) < 0.3, error


@pytest.mark.parametrize("ring_holes", [True, False])
def test_ellipses_track_lets_the_rings_holes_decide_before_fitting_its_other_pose(
    monkeypatch, ring_holes
):
    """A track whose ring moved beyond the fine window of its prior is weighed against the
    ring's other pose — a 6-DOF fit coarse to fine and a thruster search there, 15–25 ms of the
    bench's 35 ms a frame at 1.2 m. Where the ring's holes decide between its two poses (the
    joint fit started at both, which the answer gets anyway) that fit has nothing left to
    settle and is skipped; without holes it is still made."""
    offset = target_offset(0.02, -0.01, 0.0, math.radians(3.0), math.radians(-2.0), 0.2)
    (frame,) = render_frames(DEFAULT, REFERENCE, poses((1.2, offset)), "low", 4)
    X_CT = frame.truth.X_CT
    prior = Pose(X_CT.R, X_CT.p + np.array([0.015, 0.0, 0.0]))  # ~7 px: beyond the window
    other_fits = []
    other_full = EllipseEstimator._other_full

    def spy(self, *args, **kwargs):
        other_fits.append(args)
        return other_full(self, *args, **kwargs)

    monkeypatch.setattr(EllipseEstimator, "_other_full", spy)
    estimator = build(DEFAULT.target_model(), REFERENCE, ring_holes=ring_holes)
    m = estimator.estimate(frame, prior)
    assert m.status == "tracking" and not m.ambiguous, m.reason
    assert bool(other_fits) != ring_holes, len(other_fits)
    error = _errors(m, frame)
    attitude_deg = 0.3 if ring_holes else 1.0  # (the holes measure the tilt to first order)
    assert error.position_m < 0.002 and math.degrees(error.attitude_rad) < attitude_deg, error


def _outer_misfit(t: np.ndarray, residuals: np.ndarray, *, perimeter_px: float) -> float:
    """``ellipses._outer_misfit_px`` of an outer edge sampled every 2 px at angles ``t``, all
    found, with fit residuals ``residuals`` (px), on a stage smoothed at σ 2.77 px."""
    from types import SimpleNamespace

    samples = SimpleNamespace(t=t, spacing_px=2.0, perimeter_px=perimeter_px)
    outer = SimpleNamespace(samples=samples, hits=SimpleNamespace(found=np.ones(len(t), bool)))
    sets = [SimpleNamespace(circle=SimpleNamespace(name="ring_outer"))]
    result = SimpleNamespace(residuals=[residuals])
    return ellipses_module._outer_misfit_px(result, sets, "ring_outer", outer, 2.77)


def _smoothed_noise(rng, count: int, sigma_px: float) -> np.ndarray:
    """Edge residuals whose neighbours share pixels through the smoothing (σ 2.86 px with the
    Sobel's own, 1.43 samples apart at a 2 px spacing)."""
    kernel = np.exp(-0.5 * (np.arange(-6, 7) / 1.43) ** 2)
    noise = np.convolve(rng.normal(0.0, 1.0, count + 12), kernel, "valid")
    return sigma_px * noise / noise.std()


def test_an_outer_edge_seen_in_short_arcs_is_not_judged_off_by_its_noise():
    # Close up only arcs at the image's corners are in view: 4 arcs of 10 samples, 3.4 % of
    # a perimeter of 2370 px, under 0.7 px of noise correlated through the smoothing
    # (held-out random:109 at 0.5 m, high noise). Their harmonics alone passed 1 px on half of
    # these fits, and a ring so fitted was dropped as "the pose of something else".
    rng = np.random.default_rng(3)
    corners = np.radians([37.0, 143.0, 217.0, 323.0])
    arcs = np.concatenate([c + np.linspace(-0.06, 0.06, 10) for c in corners])
    judged_off = sum(
        _outer_misfit(arcs, _smoothed_noise(rng, len(arcs), 0.7), perimeter_px=2370.0) > 1.0
        for _ in range(300)
    )
    assert judged_off <= 80
    # An edge 1.5 px off its fitted image all round, in a change of scale, is told from its
    # noise in arcs; an edge in view all round keeps the plain limit.
    off = 1.5 + _smoothed_noise(rng, len(arcs), 0.3)
    assert _outer_misfit(arcs, off, perimeter_px=2370.0) > 1.0
    whole = np.linspace(0.0, 2.0 * np.pi, 200, endpoint=False)
    wide = 1.2 + _smoothed_noise(rng, len(whole), 2.0)
    assert _outer_misfit(whole, wide, perimeter_px=400.0) > 1.0
