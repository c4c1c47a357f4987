import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from estimators.conics import (
    Ellipse,
    circle_image_conic,
    circle_points,
    conic_from_ellipse,
    conic_from_parameters,
    conic_residuals,
    ellipse_from_conic,
    ellipse_sampson_distances,
    fit_ellipse_direct,
    fit_ellipse_leaving_out_an_arc,
    sampson_distances,
)
from estimators.geometry import intrinsics_from_fov, project

K = intrinsics_from_fov(640, 480, 70.0)


@given(
    st.floats(-0.4, 0.4),
    st.floats(-0.3, 0.3),
    st.floats(0.6, 5.0),
    st.floats(-1.2, 1.2),
    st.floats(-1.2, 1.2),
    st.floats(0.05, 0.5),
)
def test_circle_image_conic_passes_through_projected_circle(x, y, z, tilt_x, tilt_y, radius):
    center = np.array([x, y, z])
    normal = np.array([np.sin(tilt_y), np.sin(tilt_x), -1.0])
    normal /= np.linalg.norm(normal)
    points_C = circle_points(center, normal, radius, 90)
    if np.any(points_C[:, 2] < 0.1):
        return
    uv = project(points_C, K)
    Q = circle_image_conic(center, normal, radius, K)
    ellipse = ellipse_from_conic(Q)
    # Geometric check: every projected point lies on the fitted ellipse to 1e-6 px, measured in
    # the ellipse's own frame (distance along the ray to the centre).
    d = uv - ellipse.center
    c, s = np.cos(ellipse.angle), np.sin(ellipse.angle)
    xe = c * d[:, 0] + s * d[:, 1]
    ye = -s * d[:, 0] + c * d[:, 1]
    level = np.sqrt((xe / ellipse.a) ** 2 + (ye / ellipse.b) ** 2)
    assert np.abs(level - 1.0).max() * ellipse.a < 1e-6


def test_circle_image_conic_head_on_is_a_centred_circle():
    Q = circle_image_conic(np.array([0.0, 0.0, 2.0]), np.array([0.0, 0.0, -1.0]), 0.3, K)
    e = ellipse_from_conic(Q)
    assert (e.cx, e.cy) == pytest.approx((K[0, 2], K[1, 2]), abs=1e-9)
    assert e.a == pytest.approx(K[0, 0] * 0.3 / 2.0, rel=1e-12)
    assert e.b == pytest.approx(e.a, rel=1e-12)


@given(
    st.floats(-500, 500),
    st.floats(-500, 500),
    st.floats(1.0, 400.0),
    st.floats(0.05, 1.0),
    st.floats(-1.5, 1.5),
)
def test_ellipse_conic_round_trip(cx, cy, a, ratio, angle):
    e = Ellipse(cx, cy, a, a * ratio, angle)
    back = ellipse_from_conic(conic_from_ellipse(e))
    assert (back.cx, back.cy, back.a, back.b) == pytest.approx(
        (cx, cy, a, a * ratio), rel=1e-6, abs=1e-6
    )
    if ratio < 0.99:  # the axis angle is undefined for a circle
        diff = (back.angle - angle + np.pi / 2) % np.pi - np.pi / 2
        assert abs(diff) < 1e-6
    assert np.abs(conic_residuals(conic_from_ellipse(e), e.points(16))).max() < 1e-9


def test_ellipse_from_conic_rejects_hyperbola_and_imaginary():
    with pytest.raises(ValueError, match="not an ellipse"):
        ellipse_from_conic(np.diag([1.0, -1.0, -1.0]))
    with pytest.raises(ValueError, match="imaginary"):
        ellipse_from_conic(np.diag([1.0, 1.0, 1.0]))


def test_ellipse_validates_axes():
    with pytest.raises(ValueError, match="a ≥ b"):
        Ellipse(0, 0, 1.0, 2.0, 0.0)
    with pytest.raises(ValueError, match="non-finite"):
        Ellipse(np.nan, 0, 2.0, 1.0, 0.0)


def test_circle_image_conic_rejects_degenerate_view():
    with pytest.raises(ValueError, match="degenerate"):
        circle_image_conic(np.array([0.0, 0.0, 2.0]), np.array([1.0, 0.0, 0.0]), 0.3, K)


@given(st.floats(-np.pi, np.pi), st.floats(0.1, 0.25), st.floats(0.6, 1.0), st.integers(0, 10**6))
def test_an_ellipse_fit_leaves_out_one_wrong_arc(start, share, ratio, seed):
    """Points ordered along an ellipse, a run of ``share`` of them moved 10 px inward (another
    edge beside the one sought): the plain fit is pulled by pixels, the robust one stays on
    the ellipse; without a wrong arc both agree."""
    rng = np.random.default_rng(seed)
    e = Ellipse(320.0, 240.0, 60.0, 60.0 * ratio, 0.3)
    t = start + np.linspace(0.0, 2.0 * np.pi, 160, endpoint=False)
    radial = np.column_stack([np.cos(t), np.sin(t) * ratio])
    R = np.array([[np.cos(0.3), -np.sin(0.3)], [np.sin(0.3), np.cos(0.3)]])
    uv = e.center + (60.0 * radial + rng.normal(0.0, 0.05, (160, 2))) @ R.T
    clean = ellipse_from_conic(fit_ellipse_leaving_out_an_arc(uv))
    assert (clean.a, clean.b) == pytest.approx((e.a, e.b), abs=0.1)
    wrong = uv.copy()
    run = slice(0, int(share * 160))
    wrong[run] = e.center + (wrong[run] - e.center) * (1.0 - 10.0 / 60.0)
    robust = ellipse_from_conic(fit_ellipse_leaving_out_an_arc(wrong))
    assert (robust.cx, robust.cy, robust.a, robust.b) == pytest.approx(
        (e.cx, e.cy, e.a, e.b), abs=0.1
    )
    plain = ellipse_from_conic(fit_ellipse_direct(wrong))
    assert max(abs(plain.cx - e.cx), abs(plain.cy - e.cy), abs(plain.a - e.a)) > 0.5


@given(
    st.floats(20.0, 620.0),
    st.floats(20.0, 460.0),
    st.floats(np.log(8.0), np.log(400.0)),
    st.floats(0.2, 1.0),
    st.floats(-np.pi, np.pi),
    st.floats(0.3, 1.0),
    st.integers(0, 10**6),
)
def test_each_arc_left_out_is_fitted_as_a_direct_fit_of_the_rest(
    cx, cy, log_a, ratio, angle, span, seed
):
    """The subsets' fits come from the whole curve's scatter less the runs left out, normalised
    once for all points: each equals the direct fit of its own points (the fit is invariant
    under similarities). Checked against those fits, the winner chosen as before, on arcs of
    a third of the ellipse to all of it, a run moved off the curve by up to a fifth of it."""
    rng = np.random.default_rng(seed)
    a = float(np.exp(log_a))
    t = rng.uniform(-np.pi, np.pi) + np.linspace(0.0, 2.0 * np.pi * span, 120, endpoint=False)
    c, s = np.cos(angle), np.sin(angle)
    local = np.column_stack([a * np.cos(t), a * ratio * np.sin(t)])
    uv = np.array([cx, cy]) + local @ np.array([[c, -s], [s, c]]).T
    uv += rng.normal(0.0, 0.3, uv.shape)
    run = slice(int(rng.integers(0, 90)), None)
    uv[run][:20] += rng.uniform(-0.2, 0.2) * a * np.array([c, s])

    def reference(points, blocks=8):  # every subset fitted afresh
        best = fit_ellipse_direct(points)
        best_score = 0.8 * float(np.median(np.abs(sampson_distances(best, points))))
        runs = np.array_split(np.arange(len(points)), blocks)
        for i in range(blocks):
            keep = np.ones(len(points), bool)
            keep[runs[i]] = keep[runs[(i + 1) % blocks]] = False
            try:
                Q = fit_ellipse_direct(points[keep])
            except ValueError:
                continue
            score = float(np.median(np.abs(sampson_distances(Q, points))))
            if score < best_score:
                best, best_score = Q, score
        return best

    try:
        expected = reference(uv)
    except ValueError:
        with pytest.raises(ValueError):
            fit_ellipse_leaving_out_an_arc(uv)
        return
    got = fit_ellipse_leaving_out_an_arc(uv)
    expected_ellipse, got_ellipse = ellipse_from_conic(expected), ellipse_from_conic(got)
    assert (got_ellipse.cx, got_ellipse.cy, got_ellipse.a, got_ellipse.b) == pytest.approx(
        (expected_ellipse.cx, expected_ellipse.cy, expected_ellipse.a, expected_ellipse.b),
        rel=1e-7,
        abs=1e-7,
    )


@given(
    st.floats(50.0, 600.0),
    st.floats(50.0, 400.0),
    st.floats(np.log(5.0), np.log(400.0)),
    st.floats(0.3, 3.0),
    st.floats(-np.pi, np.pi),
    st.integers(0, 10**6),
)
def test_the_ellipse_refinements_jacobian_is_the_derivative_of_its_sampson_distances(
    cx, cy, log_a, ratio, angle, seed
):
    """Analytic (``ellipse_sampson_distances``) against central differences, on points within
    a third of its size of the curve (either axis the longer, circles' images seen up to 73°
    off their axis); the distances are ``sampson_distances`` of the state's conic."""
    rng = np.random.default_rng(seed)
    state = np.array([cx, cy, log_a, log_a + np.log(ratio), angle])
    a, b = np.exp(state[2]), np.exp(state[3])
    t = rng.uniform(0.0, 2.0 * np.pi, 40)
    c, s = np.cos(angle), np.sin(angle)
    local = np.column_stack([a * np.cos(t), b * np.sin(t)]) * rng.uniform(0.67, 1.33, (40, 1))
    uv = np.array([cx, cy]) + local @ np.array([[c, s], [-s, c]])
    d, J = ellipse_sampson_distances(state, uv, jacobian=True)
    assert J is not None
    np.testing.assert_allclose(
        d, sampson_distances(conic_from_parameters(cx, cy, a, b, angle), uv), atol=1e-9
    )
    numeric = np.empty_like(J)
    for j in range(5):
        step = np.zeros(5)
        step[j] = 1e-6
        plus, minus = (ellipse_sampson_distances(state + k * step, uv)[0] for k in (1, -1))
        numeric[:, j] = (plus - minus) / 2e-6
    np.testing.assert_allclose(J, numeric, rtol=1e-5, atol=1e-6 * max(1.0, np.abs(numeric).max()))


def test_an_axis_held_at_its_bound_does_not_move_the_distances():
    uv = np.array([[320.0, 200.0], [380.0, 260.0], [300.0, 300.0]])
    state = np.array([320.0, 240.0, np.log(1e7), np.log(40.0), 0.2])  # a beyond 10⁶ px
    _, J = ellipse_sampson_distances(state, uv, jacobian=True)
    assert J is not None
    assert np.all(J[:, 2] == 0.0) and np.any(J[:, 3] != 0.0)
