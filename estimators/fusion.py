"""Kalman fusion of the estimators' measurements into one target pose and twist.

An error-state (multiplicative) extended Kalman filter on the pose ``X_MT`` of the target T in
the track carriage frame M, with a constant-velocity process model (see docs/fusion.md).

* Nominal state: ``X_MT`` (R_MT, p_MT), the angular velocity ω (of T, expressed in M, rad/s)
  and the linear velocity v = ṗ_MT (in M, m/s).
* Error state (12): δx = [δθ, δp, δω, δv] with the rotation error on the left, in M:
  R_MT = Exp(δθ)·R̂_MT, p_MT = p̂_MT + δp, ω = ω̂ + δω, v = v̂ + δv. Rotations are never
  filtered as Euler angles; after each update the error is injected into the nominal state and
  reset to zero (Solà 2017, "Quaternion kinematics for the error-state Kalman filter", §7).
* Process: R(t+Δt) = Exp(ω·Δt)·R(t), p(t+Δt) = p(t) + v·Δt, driven by white angular and linear
  acceleration with spectral densities q_ω, q_v (the continuous white-noise acceleration model,
  Bar-Shalom, Li & Kirubarajan 2001, "Estimation with Applications to Tracking and
  Navigation", §6.2.2).
* Measurements are given with ``X_CM``, the carriage in the camera at the frame's time
  (computed by the caller from arm state, hand-eye and track position), so arm and track motion
  never look like target motion: X_CT = X_CM · X_MT. A 6-DOF measurement observes X_CT, a 5-DOF
  one a circle's centre and normal. Each is gated by its Mahalanobis distance against the χ²
  quantile of its degrees of freedom and applied sequentially: poses with filterpy's
  Joseph-form update, circles with a Schmidt ("consider") update that cannot touch the turn
  about the circle's axis, which a circle does not observe (``schmidt_update``).
* Ambiguity (issue 13; ``estimators.measurement``): only what a frame decided starts or
  confirms a track — not an ``ambiguous`` answer, nor one that chose between look-alike poses
  by its prior (``from_prior``). A circle that comes with its other pose is used only when the
  track rules that pose out and keeps the measured one (both gated), so other systems and the
  camera's known motion separate the two over frames; a quarter turn kept from a prior is used
  only while the track's own roll is measured (``max_roll_sigma_rad``), else as its circle.
* Latency: each batch is applied at its frame's capture stamp with the X_CM of that instant,
  whenever it arrives. A batch that arrives after later ones (the estimators run in parallel
  and take different times) is re-filtered in: the filter keeps the state before every update
  of the last ``history_s`` and replays the later updates (``PoseFusion``; the "reprocessing"
  solution to out-of-sequence measurements, Bar-Shalom 2002). ``state()`` is a small snapshot
  that ``estimate_from_state`` brings forward to "now" anywhere, e.g. in the control process.

Residuals follow the covariance conventions of ``estimators.measurement``: the measurement's
error is e(truth, estimate) (``pose_error_C`` / ``circle_error_C``), which its covariance
describes; the filter linearises e(h(x̂ ⊞ δx), z) = ε about δx = 0, so the innovation is
y = −e(h(x̂), z) and H = ∂e/∂δx (Jacobians from "A micro Lie theory", Solà, Deray & Atchuthan
2018, and verified by finite differences in the tests).
"""

from __future__ import annotations

import math
import numbers
from bisect import bisect_left, bisect_right
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from functools import partial
from types import MappingProxyType
from typing import Literal

import numpy as np
from filterpy.kalman import predict as kf_predict
from filterpy.kalman import update as kf_update
from scipy.stats import chi2

from estimators.conics import circle_plane_basis
from estimators.frame import readonly_array
from estimators.geometry import Pose, skew
from estimators.measurement import Measurement, without_roll
from estimators.so3 import (
    exp_so3,
    pose_error_C,
    so3_left_jacobian,
    so3_left_jacobian_inverse,
)
from estimators.target import Circle3D, TargetModel

Health = Literal["uninitialized", "ok", "coasting", "lost"]
STATE_DIM = 12
_SMALL_ANGLE = 1e-8


# --- S² helpers ----------------------------------------------------------------------------


def tangent_log(base: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Log map of the unit sphere at ``base``: the tangent vector (3,) at ``base`` pointing
    along the great circle to ``n``, whose length is the angle between them (rad).

    For antipodal vectors the direction is arbitrary (the first ``circle_plane_basis`` vector);
    the length π still tells a flipped normal from a good one.
    """
    a = np.asarray(base, dtype=float)
    b = np.asarray(n, dtype=float)
    w = b - (a @ b) * a
    sin_angle = float(np.linalg.norm(w))
    angle = math.atan2(sin_angle, float(a @ b))
    if sin_angle < _SMALL_ANGLE:
        if angle < 1.0:
            return w  # ≈ 0, and exact to first order
        return angle * circle_plane_basis(a)[0]
    return angle * w / sin_angle


def _tangent_log_jacobian(base: np.ndarray, n: np.ndarray) -> np.ndarray:
    """∂(Bᵀ·Log_base(n))/∂n (2×3), B = circle_plane_basis(base), for unit ``n``.

    With s = Bᵀn, c = baseᵀn, r = |s|, θ = atan2(r, c): Bᵀ·Log = θ·s/r, so
    d(θ s/r) = [θ/r (I − ŝŝᵀ) + c/(r² + c²) ŝŝᵀ] ds − r/(r² + c²) ŝ dc.
    """
    u, v = circle_plane_basis(base)
    B = np.column_stack([u, v])
    s = B.T @ n
    c = float(base @ n)
    r = float(np.linalg.norm(s))
    if r < _SMALL_ANGLE:
        return B.T / max(c, _SMALL_ANGLE) if c > 0 else B.T
    s_hat = s / r
    theta = math.atan2(r, c)
    rho2 = r * r + c * c
    ds = theta / r * (np.eye(2) - np.outer(s_hat, s_hat)) + c / rho2 * np.outer(s_hat, s_hat)
    return ds @ B.T - (r / rho2) * np.outer(s_hat, base)


# --- measurement errors (the conventions of estimators.measurement) -------------------------


def circle_error_C(
    center_true: np.ndarray, normal_true: np.ndarray, center_est: np.ndarray, normal_est: np.ndarray
) -> np.ndarray:
    """Error [δc, α, β] (5,) of a circle estimate in the Measurement convention:
    c_true = c_est + δc, n_true ≈ n_est + α·u + β·v with (u, v) = circle_plane_basis(n_est);
    (α, β) are the components of the sphere's Log map, so a flipped normal has |(α, β)| = π."""
    u, v = circle_plane_basis(normal_est)
    log = tangent_log(np.asarray(normal_est, dtype=float), np.asarray(normal_true, dtype=float))
    return np.concatenate([np.asarray(center_true) - np.asarray(center_est), [u @ log, v @ log]])


def uses_pose(m: Measurement) -> bool:
    """Whether fusion uses ``m`` as a 6-DOF pose (True) or as a 5-DOF circle (False).

    A measurement carrying both (ellipses with the thruster) is used as a pose only: both come
    from the same fit, so applying both would count the same information twice.
    """
    return m.X_CT is not None


def measurement_error(m: Measurement, X_CT_true: Pose, target: TargetModel) -> np.ndarray:
    """The error vector (6,) or (5,) of a valid measurement against the true ``X_CT``, in the
    model fusion uses for it (see ``uses_pose``) — what its covariance should describe."""
    if uses_pose(m):
        return pose_error_C(X_CT_true, m.X_CT)
    circle = target.circle(m.circle)
    return circle_error_C(
        X_CT_true.apply(circle.center_T), X_CT_true.R @ circle.normal_T, m.center_C, m.normal_C
    )


def measurement_covariance(m: Measurement) -> np.ndarray:
    """The covariance matching ``measurement_error`` (6×6 or 5×5)."""
    return np.asarray(m.covariance if uses_pose(m) else m.covariance_5dof)


def calibrated_covariance(
    m: Measurement, scale: float = 1.0, floor: tuple[float, float] = (0.0, 0.0)
) -> np.ndarray:
    """``scale`` × the stated covariance + a model-error floor (σ_rotation rad, σ_position m).

    Why an additive floor besides the scale: a planar model of a mock-up with relief (an 8 mm
    panel, 1.5 mm fastener heads seen off-axis) leaves a systematic error of about a millimetre
    that does not shrink with range the way the fit's noise does; close in, the fit claims a
    tenth of it. In the measurement's own order: 6-DOF [δθ, δp], 5-DOF [δc, α, β].
    """
    covariance = scale * measurement_covariance(m)
    sigma_rad, sigma_m = floor
    if uses_pose(m):
        diagonal = [sigma_rad**2] * 3 + [sigma_m**2] * 3
    else:
        diagonal = [sigma_m**2] * 3 + [sigma_rad**2] * 2
    return covariance + np.diag(diagonal)


# --- process and measurement models (pure) --------------------------------------------------


def _integration_time(dt: float, tau: float) -> tuple[float, float]:
    """(h, a) of the damped velocity model: the velocity decays as a = exp(−Δt/τ) and the pose
    moves by the velocity times h = ∫₀^Δt exp(−s/τ) ds = τ(1 − a); τ = ∞ is constant velocity."""
    if math.isinf(tau):
        return dt, 1.0
    a = math.exp(-dt / tau)
    return tau * (1.0 - a), a


def predict_nominal(X_MT: Pose, V_MT: np.ndarray, dt: float, tau: float = math.inf) -> Pose:
    """Velocity-model prediction: R ← Exp(ω·h)·R, p ← p + v·h (V_MT = [ω, v] in M), with
    h = Δt for constant velocity (τ = ∞) or τ(1 − e^(−Δt/τ)) for a damped velocity."""
    h, _ = _integration_time(dt, tau)
    omega, v = V_MT[:3], V_MT[3:]
    return Pose(exp_so3(omega * h) @ X_MT.R, X_MT.p + v * h)


def predict_velocity(V_MT: np.ndarray, dt: float, tau: float = math.inf) -> np.ndarray:
    """The velocity after Δt: unchanged (τ = ∞) or decayed by e^(−Δt/τ)."""
    return np.asarray(V_MT, dtype=float) * _integration_time(dt, tau)[1]


def process_jacobian(V_MT: np.ndarray, dt: float, tau: float = math.inf) -> np.ndarray:
    """F = ∂δx(t+Δt)/∂δx(t) (12×12) of the (damped) velocity model with left rotation error.

    Exp(δθ') = Exp((ω̂+δω)h)·Exp(δθ)·Exp(−ω̂h) ≈ Exp(J_l(ω̂h)·δω·h)·Exp(Exp(ω̂h)·δθ), so
    δθ' = Exp(ω̂h)·δθ + J_l(ω̂h)·h·δω; δp' = δp + h·δv; δω' = a·δω, δv' = a·δv (a = e^(−Δt/τ)).

    Why damped: the target sits on its mount and drifts slowly if at all. A rate the filter
    once believed in (from slightly biased measurements) would otherwise be integrated for
    ever along directions no current measurement observes — a circle cannot see roll, and
    with the ring alone the fused roll drifted by 30° in two minutes of a simulated approach.
    """
    h, a = _integration_time(dt, tau)
    phi = np.asarray(V_MT[:3], dtype=float) * h
    F = np.eye(STATE_DIM)
    F[0:3, 0:3] = exp_so3(phi)
    F[0:3, 6:9] = so3_left_jacobian(phi) * h
    F[3:6, 9:12] = np.eye(3) * h
    F[6:12, 6:12] *= a
    return F


def process_noise(dt: float, angular_accel_psd: float, linear_accel_psd: float) -> np.ndarray:
    """Discrete Q (12×12) of white acceleration with spectral densities q_ω (rad²/s³) and q_v
    (m²/s³): per axis q·[[Δt³/3, Δt²/2], [Δt²/2, Δt]] over (angle, rate) and (position, speed)."""
    block = np.array([[dt**3 / 3.0, dt**2 / 2.0], [dt**2 / 2.0, dt]])
    Q = np.zeros((STATE_DIM, STATE_DIM))
    for q, (i_pos, i_vel) in ((angular_accel_psd, (0, 6)), (linear_accel_psd, (3, 9))):
        for (a, b), value in np.ndenumerate(block):
            rows = (i_pos, i_vel)[a]
            cols = (i_pos, i_vel)[b]
            Q[rows : rows + 3, cols : cols + 3] = q * value * np.eye(3)
    return Q


def pose_model(X_MT: Pose, X_CM: Pose, X_CT_measured: Pose) -> tuple[np.ndarray, np.ndarray]:
    """Innovation y (6,) and Jacobian H (6×12) of a 6-DOF measurement of X_CT = X_CM·X_MT.

    e(δx) = [Log(Exp(R_CM δθ)·R̂_CT·R_zᵀ), R_CM(p̂ + δp) + p_CM − p_z]; with φ₀ = Log(R̂_CT R_zᵀ),
    Log(Exp(a)·Exp(φ₀)) ≈ φ₀ + J_l(φ₀)⁻¹·a gives H = [[J_l(φ₀)⁻¹ R_CM, 0, 0, 0], [0, R_CM, 0, 0]].
    """
    X_CT = X_CM @ X_MT
    error = pose_error_C(X_CT, X_CT_measured)
    H = np.zeros((6, STATE_DIM))
    H[0:3, 0:3] = so3_left_jacobian_inverse(error[:3]) @ X_CM.R
    H[3:6, 3:6] = X_CM.R
    return -error, H


def circle_model(
    X_MT: Pose, X_CM: Pose, circle: Circle3D, center_C: np.ndarray, normal_C: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Innovation y (5,) and Jacobian H (5×12) of a 5-DOF measurement of ``circle``.

    Centre c = R_CM(Exp(δθ)·q + p̂ + δp) + p_CM with q = R̂_MT·c_T: ∂c/∂δθ = −R_CM[q]×,
    ∂c/∂δp = R_CM. Normal n = R_CM·Exp(δθ)·R̂_MT·n_T: ∂n/∂δθ = −[n̂]×R_CM, then through the
    derivative of Bᵀ·Log_{n_z}(n) (``_tangent_log_jacobian``).
    """
    q_M = X_MT.R @ circle.center_T
    center = X_CM.R @ q_M + X_CM.apply(X_MT.p)
    normal = X_CM.R @ (X_MT.R @ circle.normal_T)
    error = circle_error_C(center, normal, center_C, normal_C)
    H = np.zeros((5, STATE_DIM))
    H[0:3, 0:3] = -X_CM.R @ skew(q_M)
    H[0:3, 3:6] = X_CM.R
    H[3:5, 0:3] = _tangent_log_jacobian(np.asarray(normal_C), normal) @ (-skew(normal) @ X_CM.R)
    return -error, H


def roll_directions(X_MT: Pose, circle: Circle3D) -> np.ndarray:
    """Orthonormal columns (12×2) of the error-state directions a circle cannot observe: a turn
    of the target about the circle's own axis, and the rate of that turn.

    Turning by γ about the axis m = R̂_MT·n_T through the centre (q = R̂_MT·c_T from T's origin)
    is δθ = γ·m, δp = −γ·m × q; ``circle_model``'s H maps both columns to zero.
    """
    m = X_MT.R @ circle.normal_T
    q = X_MT.R @ circle.center_T
    direction = np.concatenate([m, -np.cross(m, q)])
    direction /= np.linalg.norm(direction)
    U = np.zeros((STATE_DIM, 2))
    U[0:6, 0] = direction
    U[6:12, 1] = direction
    return U


def roll_sigma_rad(X_MT: Pose, covariance: np.ndarray, axis_T: np.ndarray | None = None) -> float:
    """1σ (rad) of the target's turn about its own axis ``axis_T`` (unit, in T; default z, the
    ring's axis): the part of the pose a circle does not observe and a square panel observes
    only up to a quarter turn. ``covariance``: the error-state covariance (rotation first)."""
    axis_M = X_MT.R @ (np.array([0.0, 0.0, 1.0]) if axis_T is None else np.asarray(axis_T))
    variance = float(axis_M @ np.asarray(covariance)[0:3, 0:3] @ axis_M)
    return math.sqrt(max(variance, 0.0))


def schmidt_update(
    P: np.ndarray, y: np.ndarray, R: np.ndarray, H: np.ndarray, consider: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """A Kalman update that leaves the state along the columns of ``consider`` (orthonormal,
    unobservable by this measurement) uncorrected: the Schmidt–Kalman "consider" update
    (Schmidt 1966; Simon 2006, "Optimal State Estimation", §7.5).

    K = Π·P Hᵀ S⁻¹ with Π = I − U Uᵀ; δx = K y; P ← (I − KH) P (I − KH)ᵀ + K R Kᵀ — the Joseph
    form is exact for any gain, so P stays honest. Why: the linearised H does not see a turn
    about the circle's axis, but the multiplicative reset re-couples it with tilt every step, and
    an ordinary update then "learns" roll from a circle — the filter claimed σ_roll = 0.5 rad
    while its roll drifted by 2 rad in a 13 s ring-only test. With this update the variance
    along U is exactly preserved by every circle measurement.
    """
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    K = K - consider @ (consider.T @ K)
    I_KH = np.eye(len(P)) - K @ H
    return K @ y, _sym(I_KH @ P @ I_KH.T + K @ R @ K.T)


def camera_pose_noise(
    dof: int, point_C: np.ndarray, normal_C: np.ndarray | None, sigma_rad: float, sigma_m: float
) -> np.ndarray:
    """Covariance (6×6 or 5×5) a camera-pose error adds to a measurement.

    With X_CM known only to a rotation ε_θ about the camera and a shift ε_p (X_CM,true =
    (Exp(ε_θ)·R_CM, Exp(ε_θ)·p_CM + ε_p)), a point at ``point_C`` moves by −[p]ₓ ε_θ + ε_p and a
    rotation by ε_θ, so the arm's, track's and hand-eye's jitter grow with the target distance.
    """
    if sigma_rad == 0.0 and sigma_m == 0.0:
        return np.zeros((dof, dof))
    A = np.zeros((dof, 6))
    if dof == 6:
        A[0:3, 0:3] = np.eye(3)
        A[3:6, 0:3] = -skew(point_C)
        A[3:6, 3:6] = np.eye(3)
    else:
        u, v = circle_plane_basis(normal_C)
        A[0:3, 0:3] = -skew(point_C)
        A[0:3, 3:6] = np.eye(3)
        A[3:5, 0:3] = -np.vstack([u, v]) @ skew(normal_C)
    E = np.diag([sigma_rad**2] * 3 + [sigma_m**2] * 3)
    return A @ E @ A.T


# --- parameters and the estimate ------------------------------------------------------------


def _check_positive(name: str, value: float, *, allow_zero: bool = False) -> None:
    ok = math.isfinite(value) and (value >= 0 if allow_zero else value > 0)
    if not ok:
        bound = "≥ 0" if allow_zero else "> 0"
        raise ValueError(f"FusionParams.{name} must be finite and {bound}; got {value!r}")


@dataclass(frozen=True, slots=True)
class FusionParams:
    """Tuning of ``PoseFusion`` (SI units; see docs/fusion.md for how to choose them).

    ``angular_accel_psd`` (rad²/s³) and ``linear_accel_psd`` (m²/s³): spectral densities of the
    target's white acceleration in M — how fast its drift/tumble rates may change.
    ``initial_*_sigma``: 1σ of the velocities at initialisation (the pose's comes from the
    measurement); ``initial_roll_sigma_rad``: roll about the circle's normal when a track starts
    from a 5-DOF measurement. ``gate_probability``: χ² quantile of the Mahalanobis gate.
    ``coast_timeout_s`` / ``lost_timeout_s``: health time-outs since the last accepted
    measurement. ``confirm_measurements``: accepted measurements that decided their pose (not
    ambiguous, not from the prior; the first included, from any systems and frames) before a new
    track is declared. ``max_stamp_skew_s``:
    largest |measurement.stamp − update stamp|. ``max_roll_sigma_rad``: the track's roll about the
    ring's axis counts as measured while its 1σ is below this (a quarter turn taken from such a
    prior is then right with near certainty). ``camera_pointing_sigma_rad`` /
    ``camera_position_sigma_m``: 1σ jitter of X_CM (arm, track, hand-eye). ``covariance_scale``:
    per-system factor on the stated covariances (from ``hil.analysis.calibration``; default 1).
    """

    angular_accel_psd: float = 1e-3
    linear_accel_psd: float = 1e-4
    initial_angular_velocity_sigma: float = 0.05
    initial_linear_velocity_sigma: float = 0.05
    initial_roll_sigma_rad: float = 1.0
    gate_probability: float = 0.999
    coast_timeout_s: float = 0.3
    lost_timeout_s: float = 2.0
    #: The target's velocity decays with this time constant (s) between measurements (∞:
    #: constant velocity). Keeps unobserved rates (roll under circle-only measurements) from
    #: being integrated for ever; see ``process_jacobian``.
    velocity_time_constant_s: float = 3.0
    confirm_measurements: int = 2
    max_stamp_skew_s: float = 0.1
    #: 10°: a quarter turn (90°) is then 9σ away, so a measurement that kept its turn from the
    #: track's prediction kept the right one; a track whose roll no measurement decided (its
    #: start's 1 rad, or grown while only circles were seen) is above it.
    max_roll_sigma_rad: float = math.radians(10.0)
    camera_pointing_sigma_rad: float = 0.0
    camera_position_sigma_m: float = 0.0
    covariance_scale: Mapping[str, float] = field(default_factory=dict)
    #: Per-system model-error floor (σ rotation rad, σ position m) added to the stated
    #: covariance after scaling (``calibrated_covariance``; from ``hil.analysis.calibration``).
    covariance_floor: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    #: How far (s) behind the newest update a late batch may still land at its own stamp
    #: (out-of-sequence updates by re-filtering; 0: late batches are refused).
    history_s: float = 1.0

    def __post_init__(self) -> None:
        for name in (
            "angular_accel_psd",
            "linear_accel_psd",
            "camera_pointing_sigma_rad",
            "camera_position_sigma_m",
            "history_s",
        ):
            _check_positive(name, getattr(self, name), allow_zero=True)
        for name in (
            "initial_angular_velocity_sigma",
            "initial_linear_velocity_sigma",
            "initial_roll_sigma_rad",
            "coast_timeout_s",
            "lost_timeout_s",
            "max_stamp_skew_s",
            "max_roll_sigma_rad",
        ):
            _check_positive(name, getattr(self, name))
        if not self.velocity_time_constant_s > 0:  # math.inf: constant velocity
            raise ValueError(
                "FusionParams.velocity_time_constant_s must be > 0 (inf for constant velocity); "
                f"got {self.velocity_time_constant_s!r}"
            )
        if not 0.0 < self.gate_probability < 1.0:
            raise ValueError(
                f"FusionParams.gate_probability must be in (0, 1); got {self.gate_probability}"
            )
        if self.lost_timeout_s <= self.coast_timeout_s:
            raise ValueError(
                f"FusionParams.lost_timeout_s ({self.lost_timeout_s}) must exceed "
                f"coast_timeout_s ({self.coast_timeout_s})"
            )
        if int(self.confirm_measurements) != self.confirm_measurements or not (
            1 <= self.confirm_measurements <= 100
        ):
            raise ValueError(
                f"FusionParams.confirm_measurements must be an integer in [1, 100]; "
                f"got {self.confirm_measurements!r}"
            )
        scales = dict(self.covariance_scale)
        for system, scale in scales.items():
            if not isinstance(scale, int | float) or not math.isfinite(scale) or scale <= 0:
                raise ValueError(
                    f"FusionParams.covariance_scale[{system!r}] must be a positive number; "
                    f"got {scale!r}"
                )
        object.__setattr__(self, "covariance_scale", MappingProxyType(scales))
        floors = {}
        for system, floor in dict(self.covariance_floor).items():
            values = tuple(float(v) for v in floor)
            if len(values) != 2 or not all(math.isfinite(v) and v >= 0 for v in values):
                raise ValueError(
                    f"FusionParams.covariance_floor[{system!r}] must be (σ rotation rad, σ position m) "
                    f"≥ 0; got {floor!r}"
                )
            floors[system] = values
        object.__setattr__(self, "covariance_floor", MappingProxyType(floors))

    def __reduce__(self):
        # The read-only mappings do not pickle; campaigns hand configurations to processes.
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        values["covariance_scale"] = dict(self.covariance_scale)
        values["covariance_floor"] = dict(self.covariance_floor)
        return (partial(FusionParams, **values), ())

    def scale_for(self, system: str) -> float:
        return float(self.covariance_scale.get(system, 1.0))

    def floor_for(self, system: str) -> tuple[float, float]:
        return tuple(self.covariance_floor.get(system, (0.0, 0.0)))  # type: ignore[return-value]


def _frozen(array: np.ndarray) -> np.ndarray:
    out = np.array(array, dtype=float)
    out.flags.writeable = False
    return out


@dataclass(frozen=True, slots=True, eq=False)
class TargetEstimate:
    """The fused target state at ``stamp``.

    ``X_MT``: target in the carriage frame (None when there is no track: none started yet, or
    dropped when it was lost). ``V_MT`` (6,):
    [ω (rad/s), v (m/s)], both in M. ``covariance`` (12×12) over the error state [δθ, δp, δω, δv]
    (rotation error on the left, in M). ``health``: ``uninitialized`` (no track, or a tentative
    one not yet confirmed — then ``X_MT`` is set but must not be acted on), ``ok``, ``coasting``
    or ``lost``. ``accepted``: systems whose measurements were applied in this update;
    ``rejected``: (system, reason) for those refused (gate, malformed, ambiguous, …);
    ``not_measured``: (system, reason) of the estimators that reported ``lost``;
    ``innovations``: (system, d², dof) of every gated measurement (normalised innovation
    squared, for tuning). ``age_s``: time since the last accepted measurement (inf if none).
    """

    stamp: float
    X_MT: Pose | None
    V_MT: np.ndarray | None
    covariance: np.ndarray | None
    health: Health
    accepted: tuple[str, ...] = ()
    rejected: tuple[tuple[str, str], ...] = ()
    age_s: float = math.inf
    not_measured: tuple[tuple[str, str], ...] = ()
    innovations: tuple[tuple[str, float, int], ...] = ()

    def X_CT(self, X_CM: Pose) -> Pose:
        """The target in frame C given the carriage in C (works for any frame A: X_AT = X_AM·X_MT)."""
        if self.X_MT is None:
            raise ValueError("TargetEstimate has no pose (health uninitialized)")
        return X_CM @ self.X_MT

    def pose_covariance_C(self, X_CM: Pose) -> np.ndarray:
        """6×6 covariance of ``X_CT(X_CM)`` in the Measurement convention (left rotation error in
        C, rotation first), ignoring any uncertainty of X_CM."""
        if self.covariance is None:
            raise ValueError("TargetEstimate has no covariance (health uninitialized)")
        J = np.zeros((6, 6))
        J[0:3, 0:3] = X_CM.R
        J[3:6, 3:6] = X_CM.R
        return J @ self.covariance[:6, :6] @ J.T

    def roll_sigma_rad(self) -> float:
        """1σ (rad) of the target's roll about the ring's axis (``roll_sigma_rad``); inf without
        a track. A track that only circles measured keeps the roll it started with, unknown."""
        if self.X_MT is None or self.covariance is None:
            return math.inf
        return roll_sigma_rad(self.X_MT, self.covariance)

    def to_dict(self) -> dict:
        """JSON-ready view for trial logs (poses as 4×4 nested lists, inf as None)."""
        return {
            "stamp": self.stamp if math.isfinite(self.stamp) else None,
            "health": self.health,
            "X_MT": None if self.X_MT is None else self.X_MT.to_list(),
            "V_MT": None if self.V_MT is None else self.V_MT.tolist(),
            "covariance": None if self.covariance is None else self.covariance.tolist(),
            "accepted": list(self.accepted),
            "rejected": [list(r) for r in self.rejected],
            "not_measured": [list(r) for r in self.not_measured],
            "innovations": [list(i) for i in self.innovations],
            "age_s": self.age_s if math.isfinite(self.age_s) else None,
        }


# --- the filter's state and the estimate from it (pure) -------------------------------------


@dataclass(frozen=True, slots=True, eq=False)
class FusionState:
    """A snapshot of ``PoseFusion`` after its newest update, at ``stamp``: all that
    ``estimate_from_state`` needs to answer "the estimate at t" for any t ≥ ``stamp``, in this
    process or another (it pickles to about 2.2 kB and holds no history).

    ``stamp`` is −inf before the first update. ``X_MT``, ``V_MT`` (6,) and ``covariance``
    (12×12) are as in ``TargetEstimate`` (all None when there is no track). The bookkeeping
    behind ``health``: ``last_accepted``, the stamp of the last accepted measurement (−inf if
    none); ``support_systems``, the systems of the accepted, unambiguous measurements since the
    track started, until they reached ``params.confirm_measurements`` and made it
    ``confirmed``.
    """

    params: FusionParams
    stamp: float = -math.inf
    X_MT: Pose | None = None
    V_MT: np.ndarray | None = None
    covariance: np.ndarray | None = None
    last_accepted: float = -math.inf
    support_systems: tuple[str, ...] = ()
    confirmed: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.params, FusionParams):
            raise TypeError(f"FusionState.params must be FusionParams; got {type(self.params)}")
        object.__setattr__(self, "support_systems", tuple(self.support_systems))
        track = (self.X_MT, self.V_MT, self.covariance)
        if any(v is None for v in track):
            if any(v is not None for v in track):
                raise ValueError("FusionState: X_MT, V_MT and covariance are all set or all None")
            return
        if not isinstance(self.X_MT, Pose):
            raise TypeError(f"FusionState.X_MT must be a Pose; got {type(self.X_MT).__name__}")
        for name, shape in (("V_MT", (6,)), ("covariance", (STATE_DIM, STATE_DIM))):
            value = readonly_array(getattr(self, name), shape, f"FusionState.{name}")
            object.__setattr__(self, name, value)

    def __reduce__(self):
        # Through the constructor, so that an unpickled state is checked and read-only too.
        return (FusionState, tuple(getattr(self, f.name) for f in fields(self)))


def estimate_from_state(state: FusionState, stamp: float) -> TargetEstimate:
    """The estimate at ``stamp`` from ``state``: its track predicted by the process model, with
    health and age at ``stamp``. Pure, so the control loop can run it on the newest state the
    vision side sent; ``PoseFusion.estimate`` answers with it too. The prediction never runs
    backwards: for ``stamp`` < ``state.stamp`` the track is returned as it is."""
    return _estimate(state, stamp, _Outcome())


@dataclass(frozen=True, slots=True, eq=False)
class _Track:
    """Nominal state and error covariance at ``stamp``."""

    stamp: float
    X_MT: Pose
    V_MT: np.ndarray
    P: np.ndarray


@dataclass
class _Outcome:
    accepted: list[str] = field(default_factory=list)
    rejected: list[tuple[str, str]] = field(default_factory=list)
    not_measured: list[tuple[str, str]] = field(default_factory=list)
    innovations: list[tuple[str, float, int]] = field(default_factory=list)

    def reject(self, system: str, reason: str) -> None:
        self.rejected.append((system, reason))


def _system_of(m: object) -> str:
    return str(getattr(m, "system", type(m).__name__))


def _track_of(state: FusionState) -> _Track | None:
    if state.X_MT is None:
        return None
    return _Track(state.stamp, state.X_MT, state.V_MT, state.covariance)


def _predict(track: _Track | None, stamp: float, params: FusionParams) -> _Track | None:
    """``track`` brought forward to ``stamp`` by the process model (never backwards)."""
    if track is None:
        return None
    dt = stamp - track.stamp
    if not dt > 0.0:  # no prediction backwards in time (or to a NaN stamp)
        return track
    tau = params.velocity_time_constant_s
    F = process_jacobian(track.V_MT, dt, tau)
    Q = process_noise(dt, params.angular_accel_psd, params.linear_accel_psd)
    _, P = kf_predict(np.zeros(STATE_DIM), track.P, F, Q)  # P = F P Fᵀ + Q
    X_MT = predict_nominal(track.X_MT, track.V_MT, dt, tau)
    return _Track(stamp, X_MT, predict_velocity(track.V_MT, dt, tau), _sym(P))


def _health(
    has_track: bool, confirmed: bool, last_accepted: float, stamp: float, params: FusionParams
) -> Health:
    if not has_track:
        return "uninitialized"
    age = stamp - last_accepted
    if not confirmed:
        # A tentative track that found no support in time is dropped, reported as such.
        return "uninitialized" if age <= params.lost_timeout_s else "lost"
    if age <= params.coast_timeout_s:
        return "ok"
    if age <= params.lost_timeout_s:
        return "coasting"
    return "lost"


def _estimate(state: FusionState, stamp: float, outcome: _Outcome) -> TargetEstimate:
    """The estimate at ``stamp`` from ``state``, listing ``outcome`` (one update's verdicts)."""
    params = state.params
    track = _predict(_track_of(state), stamp, params)
    age = stamp - state.last_accepted
    verdicts = (
        tuple(outcome.accepted),
        tuple(outcome.rejected),
        age if math.isfinite(state.last_accepted) else math.inf,
        tuple(outcome.not_measured),
        tuple(outcome.innovations),
    )
    if track is None:
        # After a lost track is dropped and nothing re-initialised it, keep saying "lost".
        lost = math.isfinite(state.last_accepted) and age > params.lost_timeout_s
        return TargetEstimate(
            stamp, None, None, None, "lost" if lost else "uninitialized", *verdicts
        )
    health = _health(True, state.confirmed, state.last_accepted, stamp, params)
    return TargetEstimate(
        stamp, track.X_MT, _frozen(track.V_MT), _frozen(track.P), health, *verdicts
    )


@dataclass(frozen=True, slots=True, eq=False)
class _Batch:
    """One applied update, kept for re-filtering: its inputs and the filter just before it."""

    stamp: float
    measurements: tuple[object, ...]
    X_CM: Pose
    before: FusionState


# --- the filter -----------------------------------------------------------------------------


class PoseFusion:
    """The fusion filter: feed it each frame's measurements with X_CM at the frame's capture
    stamp, in any order within ``params.history_s``; ask it for priors and estimates.

    ``update`` never raises for bad input: a malformed measurement, an outlier or an unusable
    frame is listed in ``TargetEstimate.rejected`` with the reason. See the module docstring and
    docs/fusion.md for the models.

    Out-of-sequence updates by re-filtering (the "reprocessing" solution): for every update of
    the last ``history_s`` seconds the filter keeps its inputs and the filter state just before
    it. A batch stamped earlier than the newest restores the state before the first later
    batch, is applied there, and every later batch is applied again in stamp order, prediction
    included. This runs the very operations an in-order arrival would have run, so the result
    equals that of receiving everything in stamp order bit for bit — the exact reference that
    Bar-Shalom's one-step solutions reproduce for a linear filter with less memory (Bar-Shalom
    2002, "Update with out-of-sequence measurements in tracking: exact solution", IEEE TAES
    38(3); Challa, Evans & Wang 2003, "A Bayesian solution and its approximations to
    out-of-sequence measurement problems", Information Fusion 4(3)). Here it also replays the
    track's start, confirmation and drop, which the one-step solutions do not model.
    """

    def __init__(self, target: TargetModel, params: FusionParams | None = None):
        self.target = target
        self.params = params if params is not None else FusionParams()
        self._gate = {dof: float(chi2.ppf(self.params.gate_probability, dof)) for dof in (5, 6)}
        self.reset()

    def reset(self) -> None:
        """Forget the track and the history: the next valid measurement starts a new track."""
        self._restore(FusionState(self.params))
        # applied batches of the last history_s seconds, in the order they were applied
        self._history: list[_Batch] = []

    # --- queries ------------------------------------------------------------------------
    def state(self) -> FusionState:
        """A snapshot after the newest update (for ``estimate_from_state``, e.g. in another
        process)."""
        track = self._track
        return FusionState(
            self.params,
            self._stamp,
            None if track is None else track.X_MT,
            None if track is None else track.V_MT,
            None if track is None else track.P,
            self._last_accepted,
            tuple(self._support_systems),
            self._confirmed,
        )

    def estimate(self, stamp: float) -> TargetEstimate:
        """The belief at ``stamp`` from the updates stamped up to it (the filter is not changed):
        for ``stamp`` ≥ the newest update, the current state predicted to ``stamp``; inside the
        history, the state saved before the first later update, predicted to ``stamp``. Before
        the history it is the oldest state kept, never predicted backwards."""
        return estimate_from_state(self._state_before(stamp), stamp)

    def prior_X_CT(self, X_CM: Pose, stamp: float) -> Pose | None:
        """Predicted X_CT at ``stamp`` (the frame's capture stamp; ``X_CM`` at that stamp) for
        the estimators; None unless the track is confirmed and not lost (a lost or tentative
        track must not steer the estimators' searches)."""
        estimate = self.estimate(stamp)
        if estimate.health not in ("ok", "coasting"):
            return None
        return estimate.X_CT(X_CM)

    def roll_measured(self, stamp: float) -> bool:
        """Whether the track's roll about the ring's axis is measured at ``stamp`` (1σ ≤
        ``params.max_roll_sigma_rad``): a track that only circles started holds a guessed one."""
        return self.estimate(stamp).roll_sigma_rad() <= self.params.max_roll_sigma_rad

    # --- the update ---------------------------------------------------------------------
    def update(
        self, measurements: Sequence[Measurement], X_CM: Pose, stamp: float
    ) -> TargetEstimate:
        """Apply one batch at ``stamp`` (the frame's capture stamp): predict to it, apply each
        measurement through the gate; a batch earlier than the newest update is re-filtered in
        (class docstring). ``X_CM``: the carriage in the camera at ``stamp``.

        Returns the estimate at the filter's newest stamp, with this batch's accepted, rejected
        and innovations. A batch more than ``params.history_s`` behind the newest update is
        refused whole, and the filter is left unchanged.
        """
        outcome = _Outcome()
        try:
            items = tuple(measurements)
        except TypeError:
            items = ()
            outcome.reject("?", f"measurements is not a sequence ({type(measurements).__name__})")
        problem = self._frame_problem(X_CM, stamp)
        if problem:
            for m in items:
                outcome.reject(_system_of(m), problem)
            when = self._stamp if math.isfinite(self._stamp) else math.nan
            if isinstance(stamp, numbers.Real) and math.isfinite(float(stamp)):
                when = float(stamp) if math.isnan(when) else max(when, float(stamp))
            return _estimate(self.state(), when, outcome)
        stamp = float(stamp)
        if stamp >= self._stamp:  # in order (a tie goes after the batches of its stamp)
            self._history.append(_Batch(stamp, items, X_CM, self.state()))
            self._apply_batch(items, X_CM, stamp, outcome)
            self._prune()
            return _estimate(self.state(), stamp, outcome)
        age = self._stamp - stamp
        if age > self.params.history_s:
            reason = (
                f"update stamp {stamp:.6f} s is earlier than the filter's history: {age:.3f} s "
                f"behind its newest update {self._stamp:.6f} s (history_s {self.params.history_s})"
            )
            for m in items:
                outcome.reject(_system_of(m), reason)
            return _estimate(self.state(), self._stamp, outcome)
        self._refilter(_Batch(stamp, items, X_CM, self.state()), outcome)
        return _estimate(self.state(), self._stamp, outcome)

    # --- internals ------------------------------------------------------------------------
    def _restore(self, state: FusionState) -> None:
        self._stamp = state.stamp
        self._track = _track_of(state)
        self._last_accepted = state.last_accepted
        # systems of the accepted, unambiguous measurements since the track started
        self._support_systems = list(state.support_systems)
        self._confirmed = state.confirmed

    def _state_before(self, stamp: float) -> FusionState:
        """The state before the first kept update later than ``stamp`` (the current state if
        there is none, or if ``stamp`` is not a number)."""
        i = bisect_right(self._history, stamp, key=_stamp_of)
        return self._history[i].before if i < len(self._history) else self.state()

    def _refilter(self, late: _Batch, outcome: _Outcome) -> None:
        """Insert ``late`` at its stamp: restore the state before the first later batch, apply
        ``late`` there (its verdicts go to ``outcome``), then every later batch again."""
        i = bisect_right(self._history, late.stamp, key=_stamp_of)
        later = self._history[i:]
        self._restore(later[0].before)
        self._history[i:] = [_Batch(late.stamp, late.measurements, late.X_CM, self.state())]
        self._apply_batch(late.measurements, late.X_CM, late.stamp, outcome)
        for batch in later:
            self._history.append(_Batch(batch.stamp, batch.measurements, batch.X_CM, self.state()))
            self._apply_batch(batch.measurements, batch.X_CM, batch.stamp, _Outcome())

    def _prune(self) -> None:
        # A late batch may land at newest − history_s: it needs the state before the first
        # batch after it, so batches at or after that instant stay.
        oldest = self._stamp - self.params.history_s
        keep = bisect_left(self._history, oldest, key=_stamp_of)
        del self._history[:keep]

    def _apply_batch(
        self, items: Sequence[object], X_CM: Pose, stamp: float, outcome: _Outcome
    ) -> None:
        """Predict to ``stamp`` and apply each measurement through the gate (the in-order
        update; the caller keeps the history)."""
        self._stamp = stamp
        self._track = _predict(self._track, stamp, self.params)
        if self._track is not None and self._health_at(stamp) == "lost":
            self._drop_track()
        # 6-DOF first, unambiguous first: a new track then starts from the best evidence.
        ordered = sorted(items, key=_application_order)
        for m in ordered:
            try:
                self._apply(m, X_CM, stamp, outcome)
            except Exception as exc:  # a bug or a corrupted input must not take the loop down
                outcome.reject(_system_of(m), f"internal error ({type(exc).__name__}: {exc})")
        if outcome.accepted:
            self._last_accepted = stamp

    def _frame_problem(self, X_CM: Pose, stamp: float) -> str:
        if not isinstance(X_CM, Pose):
            return f"X_CM is not a Pose (got {type(X_CM).__name__})"
        if not isinstance(stamp, numbers.Real) or not math.isfinite(float(stamp)):
            return f"update stamp is not a finite number (got {stamp!r})"
        return ""

    def _health_at(self, stamp: float) -> Health:
        return _health(
            self._track is not None, self._confirmed, self._last_accepted, stamp, self.params
        )

    def _drop_track(self) -> None:
        self._track = None
        self._support_systems = []
        self._confirmed = False

    def _problem(self, m: Measurement, stamp: float) -> str:
        """Why ``m`` cannot be used ('' if it can). Measurement validates itself on creation;
        these checks also catch objects corrupted after it and what only fusion can judge."""
        if abs(m.stamp - stamp) > self.params.max_stamp_skew_s:
            return (
                f"stamp {m.stamp:.3f} s is {abs(m.stamp - stamp):.3f} s from the update's "
                f"(max_stamp_skew_s {self.params.max_stamp_skew_s})"
            )
        if uses_pose(m):
            values = (m.X_CT.R, m.X_CT.p, m.covariance)
        else:
            if m.center_C is None or m.normal_C is None or m.circle is None:
                return "no pose and no circle"
            if not self.target.has_circle(m.circle):
                names = [c.name for c in self.target.circles]
                return f"unknown circle {m.circle!r} (target {self.target.name!r} has {names})"
            values = (m.center_C, m.normal_C, m.covariance_5dof)
        covariance = values[-1]
        if covariance is None:
            return "no covariance"
        if not all(np.all(np.isfinite(np.asarray(v, dtype=float))) for v in values):
            return "non-finite pose or covariance"
        if not uses_pose(m) and abs(np.linalg.norm(m.normal_C) - 1.0) > 1e-6:
            return "normal_C is not a unit vector"
        cov = np.asarray(covariance, dtype=float)
        if np.abs(cov - cov.T).max() > 1e-9 * max(1.0, np.abs(cov).max()):
            return "covariance is not symmetric"
        if np.linalg.eigvalsh(cov).min() <= 0.0:
            return "covariance is not positive definite"
        return ""

    def _noise(
        self, m: Measurement, point_C: np.ndarray, normal_C: np.ndarray | None
    ) -> np.ndarray:
        R = calibrated_covariance(
            m, self.params.scale_for(m.system), self.params.floor_for(m.system)
        )
        dof = len(R)
        return R + camera_pose_noise(
            dof,
            point_C,
            normal_C,
            self.params.camera_pointing_sigma_rad,
            self.params.camera_position_sigma_m,
        )

    def _apply(self, m: object, X_CM: Pose, stamp: float, outcome: _Outcome) -> None:
        if not isinstance(m, Measurement):
            outcome.reject(_system_of(m), f"not a Measurement ({type(m).__name__})")
            return
        if not m.valid:
            outcome.not_measured.append((m.system, m.reason or "lost"))
            return
        try:
            problem = self._problem(m, stamp)
        except Exception as exc:  # a corrupted object must not take the loop down
            problem = f"malformed ({type(exc).__name__}: {exc})"
        if problem:
            outcome.reject(m.system, problem)
            return
        if self._track is None:
            self._start_track(m, X_CM, stamp, outcome)
            return
        if m.from_prior and uses_pose(m) and not self._roll_measured(m):
            # The quarter turn came from a prior that had not measured it: only the circle
            # about the turn axis is this frame's evidence.
            if m.center_C is None:
                outcome.reject(m.system, "roll kept from a prior whose roll is not measured")
                return
            m = without_roll(m)
        if m.alternative_center_C is not None:
            problem = self._unresolved_circle(m, X_CM)
            if problem:
                outcome.reject(m.system, problem)
                return
        try:
            y, H, R = self._linearised(m, X_CM)
            d2 = self._distance(y, H, R)
        except (np.linalg.LinAlgError, ValueError) as exc:
            outcome.reject(m.system, f"innovation not computable ({exc})")
            return
        dof = len(y)
        outcome.innovations.append((m.system, d2, dof))
        if not math.isfinite(d2) or d2 > self._gate[dof]:
            reason = f"gate: d²={d2:.1f} > {self._gate[dof]:.1f} ({dof} dof)"
            if not self._confirmed and _can_start(m):
                # Two disagreeing measurements and no confirmed track: the older one may be the
                # bad one, so restart from the newer; agreement later confirms whichever is right.
                for system in dict.fromkeys(self._support_systems):
                    outcome.reject(
                        system, f"tentative track dropped: {m.system} disagreed ({reason})"
                    )
                outcome.accepted.clear()  # all of this frame's accepted supported that track
                self._drop_track()
                self._start_track(m, X_CM, stamp, outcome)
                return
            outcome.reject(m.system, reason)
            return
        if uses_pose(m):
            # δx = K y, P = (I − KH) P (I − KH)ᵀ + K R Kᵀ (Joseph form)
            dx, P = kf_update(np.zeros(STATE_DIM), self._track.P, y, R, H)
        else:
            circle = self.target.circle(m.circle)
            dx, P = schmidt_update(
                self._track.P, y, R, H, roll_directions(self._track.X_MT, circle)
            )
        self._track = _inject(self._track, dx, P)
        outcome.accepted.append(m.system)
        if _is_evidence(m) and not self._confirmed:
            # Only a tentative track needs its witnesses; a confirmed one stops counting, so
            # that the state stays small over a long track. An answer that the prior or the
            # track chose between poses is no witness of that choice.
            self._support_systems.append(m.system)
            if len(self._support_systems) >= self.params.confirm_measurements:
                self._confirmed = True

    def _distance(self, y: np.ndarray, H: np.ndarray, R: np.ndarray) -> float:
        """Squared Mahalanobis distance d² of innovation ``y`` against the track."""
        S = H @ self._track.P @ H.T + R
        return float(y @ np.linalg.solve(S, y))

    def _roll_measured(self, m: Measurement) -> bool:
        axis_T = self.target.circle(m.circle).normal_T if m.circle is not None else None
        sigma = roll_sigma_rad(self._track.X_MT, self._track.P, axis_T)
        return sigma <= self.params.max_roll_sigma_rad

    def _unresolved_circle(self, m: Measurement, X_CM: Pose) -> str:
        """Why a circle that came with its other pose (its mirror, issue 13) is not used: ''
        when the track keeps the measured pose and rules the other out, so the track — built
        from other frames, other systems and the camera's known motion between them — decides
        what the frame could not. Both poses are judged as circles, whatever else ``m`` holds.
        """
        circle_m = without_roll(m) if m.X_CT is not None else m
        other = replace(
            circle_m,
            center_C=m.alternative_center_C,
            normal_C=m.alternative_normal_C,
            alternative_center_C=m.center_C,
            alternative_normal_C=m.normal_C,
        )
        try:
            measured, mirrored = (
                self._distance(*self._linearised(c, X_CM)) for c in (circle_m, other)
            )
        except (np.linalg.LinAlgError, ValueError) as exc:
            return f"innovation not computable ({exc})"
        gate = self._gate[5]
        if mirrored > gate:
            return ""
        if measured <= gate:
            return (
                f"ambiguous: both of the circle's poses fit the track "
                f"(d² {measured:.1f} and {mirrored:.1f} ≤ {gate:.1f})"
            )
        return (
            f"the circle's other pose fits the track, not the one measured "
            f"(d² {mirrored:.1f} ≤ {gate:.1f} < {measured:.1f})"
        )

    def _linearised(self, m: Measurement, X_CM: Pose) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if uses_pose(m):
            y, H = pose_model(self._track.X_MT, X_CM, m.X_CT)
            return y, H, self._noise(m, m.X_CT.p, None)
        circle = self.target.circle(m.circle)
        y, H = circle_model(self._track.X_MT, X_CM, circle, m.center_C, m.normal_C)
        return y, H, self._noise(m, m.center_C, m.normal_C)

    def _start_track(self, m: Measurement, X_CM: Pose, stamp: float, outcome: _Outcome) -> None:
        if not _can_start(m):
            if m.ambiguous:
                reason = "ambiguous: cannot start a track"
            elif m.from_prior:
                reason = "chose between poses by its prior: cannot start a track"
            else:
                reason = "a 5-DOF measurement without X_CT_hint cannot start a track"
            outcome.reject(m.system, reason)
            return
        if uses_pose(m):
            X_CT = m.X_CT
            P_C = self._noise(m, X_CT.p, None)
        else:
            circle = self.target.circle(m.circle)
            X_CT, A = _pose_from_circle(m.X_CT_hint, circle, m.center_C, m.normal_C)
            cov_in = np.zeros((6, 6))
            cov_in[:5, :5] = self._noise(m, m.center_C, m.normal_C)
            cov_in[5, 5] = self.params.initial_roll_sigma_rad**2
            P_C = A @ cov_in @ A.T
        # δ_M = R_MC·δ_C for both rotation and position (H = blockdiag(R_CM, R_CM) at δ = 0).
        J = np.zeros((6, 6))
        J[0:3, 0:3] = X_CM.R.T
        J[3:6, 3:6] = X_CM.R.T
        P = np.zeros((STATE_DIM, STATE_DIM))
        P[:6, :6] = J @ P_C @ J.T
        P[6:9, 6:9] = np.eye(3) * self.params.initial_angular_velocity_sigma**2
        P[9:12, 9:12] = np.eye(3) * self.params.initial_linear_velocity_sigma**2
        self._track = _Track(stamp, X_CM.inverse() @ X_CT, np.zeros(6), _sym(P))
        self._support_systems = [m.system]
        self._confirmed = self.params.confirm_measurements <= 1
        outcome.accepted.append(m.system)


def _is_evidence(m: Measurement) -> bool:
    """Whether the frame itself decided ``m``'s pose among those that look alike (a circle's
    mirror, a panel's flip or quarter turn): not ambiguous, and not chosen by its prior."""
    return not m.ambiguous and not m.from_prior


def _can_start(m: Measurement) -> bool:
    """A track starts only from a pose the frame decided, or such a circle with a hint for its
    roll (the roll then starts unknown: ``initial_roll_sigma_rad``)."""
    return _is_evidence(m) and (uses_pose(m) or m.X_CT_hint is not None)


def _application_order(m: object) -> tuple[int, bool]:
    if not isinstance(m, Measurement) or not m.valid:
        return (2, False)
    return (0 if uses_pose(m) else 1, not _is_evidence(m))


def _stamp_of(batch: _Batch) -> float:
    return batch.stamp


def _sym(P: np.ndarray) -> np.ndarray:
    return 0.5 * (P + P.T)


def _inject(track: _Track, dx: np.ndarray, P: np.ndarray) -> _Track:
    """Fold the error estimate into the nominal state and reset it to zero.

    The reset maps the error as δθ⁺ ≈ δθ − δθ̂ + ½ δθ̂ × δθ (BCH), so P ← G P Gᵀ with
    G = I + ½[δθ̂]ₓ on the rotation block (Solà 2017, §7.2, for a global/left error).
    """
    dx = np.asarray(dx, dtype=float).reshape(-1)
    X_MT = Pose(exp_so3(dx[0:3]) @ track.X_MT.R, track.X_MT.p + dx[3:6])
    G = np.eye(STATE_DIM)
    G[0:3, 0:3] += 0.5 * skew(dx[0:3])
    return _Track(track.stamp, X_MT, track.V_MT + dx[6:12], _sym(G @ P @ G.T))


def _pose_from_circle(
    hint: Pose, circle: Circle3D, center_C: np.ndarray, normal_C: np.ndarray
) -> tuple[Pose, np.ndarray]:
    """A full X_CT from a circle (centre, normal) and a hint for roll, and the map A (6×6) from
    [δc, α, β, γ] (γ: roll about the normal) to the pose error [δθ, δp] in C.

    The hint is turned by the smallest rotation that carries its normal onto the measured one;
    then p = c − R·c_T. Errors: δθ = −β·u + α·v + γ·n (so that δθ × n = α·u + β·v) and
    δp = δc + [R c_T]ₓ δθ.
    """
    n = np.asarray(normal_C, dtype=float)
    n_hint = hint.R @ circle.normal_T
    axis = np.cross(n_hint, n)
    angle = math.atan2(float(np.linalg.norm(axis)), float(n_hint @ n))
    if np.linalg.norm(axis) > _SMALL_ANGLE:
        R_align = exp_so3(axis / np.linalg.norm(axis) * angle)
    elif n_hint @ n > 0:
        R_align = np.eye(3)
    else:  # hint flipped: turn half-way round any axis in the plane
        R_align = exp_so3(circle_plane_basis(n)[0] * math.pi)
    R_CT = R_align @ hint.R
    q_C = R_CT @ circle.center_T
    X_CT = Pose(R_CT, np.asarray(center_C, dtype=float) - q_C)
    u, v = circle_plane_basis(n)
    A = np.zeros((6, 6))
    A[0:3, 3] = v
    A[0:3, 4] = -u
    A[0:3, 5] = n
    A[3:6, 0:3] = np.eye(3)
    A[3:6, :] += skew(q_C) @ A[0:3, :]
    return X_CT, A
