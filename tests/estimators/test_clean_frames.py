"""Clean frames: a camera's own shot and read noise (the sensor model, σ ≈ 0.0065 of full scale)
is a thirty-fifth of the reference study's low noise, and a noise-free rendering has none. The
estimators weigh image evidence in z units against margins set under the study's noise; on
clean frames the corner system refused its own right poses on nearly every frame (a tilt 7°
off "fitting the ring better" by hundreds of z units) and the line system locked onto
quarter-turned panels. Every system must acquire a clean frame, right, and say nothing wrong."""

import math

import numpy as np
import pytest

from estimators.geometry import rotation_error_geodesic
from estimators.registry import build_estimator
from hil.evaluation.targets import accuracy_target
from tests.estimators import rendered

#: Poses no edge of which lies on the pixel grid: the generic one, and two turned about the
#: optical axis (the panel's quarter turn must still be told).
OFFSETS = (
    rendered.GENERIC,
    (-0.014, -0.012, 0.019, -0.082, 0.020, 0.046),
    (0.020, 0.020, 0.0, math.radians(-3.0), math.radians(-6.0), math.radians(70.0)),
)


@pytest.mark.parametrize("system", ["corners", "lines"])
@pytest.mark.parametrize("distance", [3.0, 2.0, 1.2])
def test_the_panel_systems_acquire_clean_frames_right(system, distance):
    target = rendered.target()
    for offset in OFFSETS:
        f = rendered.frame(distance, offset, noise="sensor", supersample=4)
        m = build_estimator(system, target, f.info).estimate(f)
        assert m.status == "acquired", f"{offset}: {m.reason}"
        position = float(np.linalg.norm(m.X_CT.p - f.truth.X_CT.p))
        attitude = rotation_error_geodesic(m.X_CT, f.truth.X_CT)
        limit_position, limit_attitude = accuracy_target(system, distance, "low")
        assert position <= limit_position and attitude <= limit_attitude, (
            f"{offset}: {1000 * position:.1f} mm, {math.degrees(attitude):.2f}°"
        )


@pytest.mark.parametrize("system", ["corners", "lines"])
def test_the_simulators_clean_frames_are_tracked_off_the_optical_axis(system):
    """The simulated approach's frames (``configs/sim.yaml``) under the sensor's noise, with the
    panel off the optical axis as the wrist camera sees it: a point-sampled rendering put each
    edge up to half a pixel off per image row, and both panel systems refused such frames along
    most of the approach (χ²/dof 6–25); a camera's pixels integrate light over their area."""
    from configuration.render import NoiseConfig
    from configuration.simulation import load_simulation, with_overrides

    sim = with_overrides(load_simulation("sim"), noise={"preset": "sensor"})
    supersample = sim.render.for_noise(sim.noise).supersample
    target = rendered.target()
    assert sim.noise == NoiseConfig(preset="sensor")
    for distance, offset in [
        (2.0, (0.2, 0.07, 0.0, 0.01, 0.05, 0.01)),
        (1.2, (0.13, 0.05, 0.0, 0.01, 0.035, 0.01)),
        (0.9, (0.07, 0.03, 0.0, 0.006, 0.022, 0.006)),
    ]:
        f = rendered.frame(distance, offset, noise="sensor", supersample=supersample)
        m = build_estimator(system, target, f.info).estimate(f, f.truth.X_CT)
        assert m.status == "tracking", f"{distance} m: {m.reason}"


@pytest.mark.parametrize(("system", "bound_m"), [("corners", 0.0006), ("lines", 0.0005)])
def test_a_cameras_own_noise_leaves_no_range_bias(system, bound_m):
    """At 3 m under the sensor's noise, tracked from the truth: the mean range error over three
    poses stays within a fraction of a millimetre. Fitted as clipped noise of one σ, the black
    background's pixels drew the face's outline outward (lines −3 mm) and the bolt heads' walls
    drew the discs inward (corners +1.2 mm), where noise-free frames gave −0.03…+0.06 and
    −0.4…−0.3 mm."""
    target = rendered.target()
    errors = []
    for offset in OFFSETS:
        f = rendered.frame(3.0, offset, noise="sensor", supersample=4)
        m = build_estimator(system, target, f.info).estimate(f, f.truth.X_CT)
        assert m.status == "tracking", f"{offset}: {m.reason}"
        errors.append(float(m.X_CT.p[2] - f.truth.X_CT.p[2]))
    assert abs(float(np.mean(errors))) <= bound_m, (
        f"range errors {np.round(np.array(errors) * 1000, 2)} mm"
    )


def _near_truth(distance: float, count: int):
    """``count`` generic poses about the nominal one at ``distance`` (a few cm, a few degrees)
    with priors a few millimetres and a fraction of a degree off, as tracking gives them."""
    from estimators.geometry import Pose

    rng = np.random.default_rng(int(distance * 10))
    scale = np.array([0.01 * distance] * 3 + [0.06, 0.06, 0.1])
    for _ in range(count):
        offset = tuple(rng.uniform(-1, 1, 6) * scale)
        wobble = Pose.from_rotvec(rng.normal(0, 0.003, 3), rng.normal(0, 0.003, 3))
        yield offset, wobble


@pytest.mark.parametrize("distance", [1.2, 0.5])
def test_the_corner_systems_covariance_owns_its_model_error_close_up(distance):
    """Close up the disc fits' own σ falls to a few thousandths of a pixel while the disc and
    wedge models stay a few hundredths off a real head's image: without a floor for that, the
    pose's NEES under the sensor's noise was 44–46 (six degrees of freedom: 6 is honest) and a
    noise-free frame at 0.5 m was refused for "features disagree with the model". With it
    every frame is tracked and the NEES is 12–18: still above honest (model errors common to
    all features, such as the corner system's range bias, are no floor's to absorb; issue
    13), but no longer seven times it."""
    from hil.evaluation.errors import measurement_error

    target = rendered.target()
    estimator = None
    nees = []
    for k, (offset, wobble) in enumerate(_near_truth(distance, 8)):
        for noise in ("none", "sensor"):
            f = rendered.frame(distance, offset, noise=noise, seed=k, supersample=4)
            estimator = estimator or build_estimator("corners", target, f.info)
            m = estimator.estimate(f, wobble @ f.truth.X_CT)
            assert m.status == "tracking", f"{noise} {offset}: {m.reason}"
            if noise == "sensor":
                nees.append(measurement_error(m, f.truth.X_CT, target).nees_pose)
    assert np.mean(nees) < 4 * 6, f"NEES {np.round(nees, 1)}"
