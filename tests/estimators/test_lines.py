import math

import cv2
import numpy as np
import pytest

from estimators.acquisition import quarter_turns
from estimators.frame import Frame
from estimators.geometry import Pose, rotation_error_rpy_norm, translation_error
from estimators.imaging import image_stack
from estimators.lines import LineOptions, build
from estimators.measurement import Tracker
from estimators.planar_pose import retract
from tests.estimators import rendered

TARGET = rendered.target()
#: Single-frame limits at low noise: 1.5× the issue's targets for a mean. With the face
#: outline the system reaches 0.2–0.3° / 0.1° / 0.05–0.2° means at 3 / 2 / 1.2 m
#: (docs/corners_lines.md); the panel's edges alone could not get below ≈ 6° / 3° / 1°.
LIMITS = {
    3.0: (0.0225, math.radians(3.0)),
    2.0: (0.012, math.radians(1.5)),
    1.2: (0.0045, math.radians(0.6)),
}


def _errors(m, X_true):
    return translation_error(X_true, m.X_CT), rotation_error_rpy_norm(X_true, m.X_CT)


def test_line_estimator_returns_lost_with_a_reason_for_bad_images():
    good = rendered.frame(2.0)
    estimator = build(TARGET, good.info)
    shape = good.info.shape
    bad = [
        (np.zeros(shape, np.uint8), "no contrast"),
        (np.full(shape, 255, np.uint8), "no contrast"),
        (np.zeros((3, 3), np.uint8), "does not match"),
        (np.full(shape, np.nan, np.float32), "NaN"),
        (np.zeros((shape[0] - 1, shape[1]), np.uint8), "does not match"),
    ]
    for image, reason in bad:
        for prior in (None, good.truth.X_CT):
            m = estimator.estimate(Frame(image, 0.0, good.info, 0), prior)
            assert m.status == "lost" and reason in m.reason and m.X_CT is None


@pytest.mark.parametrize("distance", [3.0, 2.0, 1.2])
def test_line_estimator_acquires_and_tracks(distance):
    f = rendered.frame(distance, seed=int(10 * distance))
    X_true = f.truth.X_CT
    estimator = build(TARGET, f.info)
    acquired = estimator.estimate(f)
    assert acquired.status == "acquired", acquired.reason
    position, attitude = _errors(acquired, X_true)
    assert position <= LIMITS[distance][0] and attitude <= LIMITS[distance][1]
    prior = retract(X_true, np.array([0.01, -0.01, 0.01, 0.02, -0.01, 0.01]))
    tracked = estimator.estimate(f, prior)
    assert tracked.status == "tracking", tracked.reason
    position, attitude = _errors(tracked, X_true)
    assert position <= LIMITS[distance][0] and attitude <= LIMITS[distance][1]
    assert np.all(np.linalg.eigvalsh(tracked.covariance) > 0)
    # Edge points on all four edges, Hough segments, and the four corners for overlays.
    assert len(tracked.features["labeled"]) >= 12
    assert len(tracked.features["extracted"]) >= 8
    assert tracked.features["corners"].shape == (4, 2)
    corners_true = f.info.project(X_true.apply(TARGET.panel_corners_T))
    assert np.abs(tracked.features["corners"] - corners_true).max() < 1.5


def test_line_estimator_rejects_a_quarter_turned_prior_and_reacquires():
    f = rendered.frame(1.2, seed=3)
    X_true = f.truth.X_CT
    m = build(TARGET, f.info).estimate(f, X_true @ quarter_turns(TARGET)[2])
    assert m.status == "acquired"
    position, attitude = _errors(m, X_true)
    assert position <= LIMITS[1.2][0] and attitude <= LIMITS[1.2][1]


def test_tracker_recovers_from_a_forced_loss():
    frames = [rendered.frame(1.2, seed=s, seq=s) for s in range(3)]
    saturated = Frame(np.full(frames[0].info.shape, 255, np.uint8), 1 / 30, frames[0].info, 1)
    tracker = Tracker(build(TARGET, frames[0].info))
    statuses = [tracker.update(f).status for f in (frames[0], saturated, frames[2], frames[1])]
    assert statuses == ["acquired", "lost", "acquired", "tracking"]


@pytest.mark.parametrize(("camera", "mockup"), [("oak_d_rgb", "default"), ("reference", "other")])
def test_line_estimator_on_a_camera_and_mockup_it_was_not_tuned_on(camera, mockup):
    f = rendered.frame(1.2, camera=camera, mockup=mockup, seed=5)
    estimator = build(rendered.target(mockup), f.info)
    m = estimator.estimate(f)
    assert m.status == "acquired", m.reason
    position, attitude = _errors(m, f.truth.X_CT)
    assert position <= LIMITS[1.2][0] and attitude <= LIMITS[1.2][1]
    corners_true = f.info.project(f.truth.X_CT.apply(rendered.target(mockup).panel_corners_T))
    assert np.abs(m.features["corners"] - corners_true).max() < 1.5


def test_line_estimator_lhm_pose_method_and_bad_options():
    f = rendered.frame(1.2, seed=9)
    m = build(TARGET, f.info, pose_method="lhm").estimate(f, f.truth.X_CT)
    assert m.status == "tracking"
    position, attitude = _errors(m, f.truth.X_CT)
    assert position <= LIMITS[1.2][0] and attitude <= LIMITS[1.2][1]
    with pytest.raises(ValueError, match="pose_method"):
        LineOptions(pose_method="dlt")
    with pytest.raises(ValueError, match="angle_gate_deg"):
        LineOptions(angle_gate_deg=60.0)


def test_without_a_prior_the_outline_is_searched_at_the_tilt_its_edges_support():
    """A face taller than wide (random:117) at 1.2 m shows only its two sides. A hypothesis 10°
    off in tilt predicts them beyond the outline's edge search; the tilt search finds the tilt
    at which they are edges (on the coarse gradients: to a couple of degrees, well inside the
    joint fit's search, which then finds the tilt to a fraction of a degree)."""
    mockup = "random:117"
    f = rendered.frame(1.2, seed=3, mockup=mockup)
    target = rendered.target(mockup)
    estimator = build(target, f.info)
    image = image_stack(f)
    X_true = f.truth.X_CT
    edges = estimator._panel_edges_at(image, X_true)
    assert edges is not None
    centre = X_true.apply(target.panel_corners_T.mean(axis=0)[None])[0]
    for axis in ([0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.6, -0.8, 0.0]):
        R = Pose.from_rotvec(math.radians(10.0) * np.array(axis), np.zeros(3)).R
        X_off = Pose(R @ X_true.R, centre + R @ (X_true.p - centre))
        found = estimator._outline_tilt(image, X_off, edges)
        assert found is not None
        normal_error = math.acos(min(1.0, float(found.R[:, 2] @ X_true.R[:, 2])))
        assert math.degrees(normal_error) < 3.0, axis


def test_the_integer_median_of_gradient_magnitudes_is_numpys_median():
    """The Canny thresholds rest on the crop's median Sobel magnitude, taken from a histogram
    (``lines._integer_median``): it must be the median, for odd and even counts and for
    values piled on a few levels."""
    from estimators.lines import _integer_median

    rng = np.random.default_rng(3)
    for size in (1, 2, 7, 10, 999, 1000):
        for high in (3, 2041):
            values = rng.integers(0, high, size=size).astype(np.float32)
            assert _integer_median(values) == float(np.median(values))


def test_a_faint_band_beside_a_panel_edge_does_not_take_the_edges_label():
    """A shadow or side band beside the panel has an edge of the panel's polarity too. Here
    one 6 px wide, a fifth of the panel's contrast, its outer edge a fifth longer than the
    panel's: as the longer image segment it was labeled the panel's edge, the track failed
    and fell back to acquisition (held-out random:117 at 3 m, noise-free: a pose 33° off)."""
    image, X_true, info = rendered.render(3.0, rendered.GENERIC, supersample=2)
    corners = info.project(X_true.apply(TARGET.panel_corners_T))
    a, b = corners[1], corners[2]
    along = (b - a) / np.linalg.norm(b - a)
    outward = np.array([-along[1], along[0]])
    if outward @ (corners.mean(axis=0) - a) > 0:
        outward = -outward
    inside = a + 8.0 * -outward + 0.5 * (b - a)
    outside = a + 10.0 * outward + 0.5 * (b - a)
    panel, face = (float(image[round(p[1]), round(p[0])]) for p in (inside, outside))
    # The band as a trapezoid on the edge, its coverage of each pixel from an 8× raster.
    extend = 0.1 * (b - a)
    band = np.array([a, b, b + extend + 6.0 * outward, a - extend + 6.0 * outward])
    scale = 8
    mask = np.zeros((image.shape[0] * scale, image.shape[1] * scale), np.uint8)
    cv2.fillConvexPoly(mask, np.round((band + 0.5) * scale - 0.5).astype(np.int32), 255)
    cover = cv2.resize(
        mask.astype(np.float32) / 255.0, image.shape[::-1], interpolation=cv2.INTER_AREA
    )
    banded = (image * (1.0 - cover) + (face + 0.2 * (panel - face)) * cover).astype(np.float32)
    estimator = build(TARGET, info)
    tracked = estimator.estimate(Frame(banded, 0.0, info, 0), X_true)
    assert tracked.status == "tracking", tracked.reason
    position, attitude = _errors(tracked, X_true)
    assert position < 0.001 and attitude < math.radians(0.1)
