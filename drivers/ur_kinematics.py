"""Kinematics of Universal Robots e-Series arms from UR's published Denavit–Hartenberg table.

Pure numpy, no device and no pybullet: forward kinematics, the geometric Jacobian, damped
least-squares resolved-rate control and a numerical inverse kinematics for set-up and checks.
The simulated arm, the supervisor (singularity margin) and the UR emulator share it; the URDF
written from the same parameters is ``sim_backends.ur_urdf``.

Frames follow UR's convention: B is the controller's ``base`` frame (DH frame 0; the frame
``getActualTCPPose`` reports in), E is ``tool0``, the flange (DH frame 6, z out of the flange).
Each link transform is standard DH, ``A_i = Rz(θ_i)·Tz(d_i)·Tx(a_i)·Rx(α_i)`` (UR's "a" is
Wikipedia's "r"). Twists are ``[v, ω]``: v the velocity of E's origin, ω the angular velocity,
both expressed in B (UR's TCP speed convention).

Sources: UR support article "Parameters for calculations of kinematics and dynamics" (DH table
and link masses, e-Series 5.1); UR e-Series user manuals (joint ranges and speeds, as collected
in ros-industrial's ``ur_description`` joint_limits.yaml). The elbow is limited to ±π because
the upper arm physically blocks it beyond that.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from estimators.geometry import Pose

_HALF_PI = math.pi / 2
_ALPHA = (_HALF_PI, 0.0, 0.0, _HALF_PI, -_HALF_PI, 0.0)
_TWO_PI = 2 * math.pi
_LIMITS = ((-_TWO_PI, _TWO_PI),) * 2 + ((-math.pi, math.pi),) + ((-_TWO_PI, _TWO_PI),) * 3


@dataclass(frozen=True, slots=True, eq=False)
class URModel:
    """One arm: DH parameters (m, rad), joint ranges (rad), maximum joint speeds (rad/s),
    link masses (kg, for the URDF only), a nominal reach (m, UR's datasheet) and a radius for
    the cylinder visuals (m)."""

    name: str
    d: tuple[float, ...]
    a: tuple[float, ...]
    alpha: tuple[float, ...]
    joint_limits: tuple[tuple[float, float], ...]
    max_joint_speed: tuple[float, ...]
    link_mass: tuple[float, ...]
    reach: float
    visual_radius: float

    def __post_init__(self) -> None:
        for field_name in ("d", "a", "alpha", "max_joint_speed", "link_mass"):
            if len(getattr(self, field_name)) != 6:
                raise ValueError(f"URModel.{field_name} needs 6 values")
        if len(self.joint_limits) != 6:
            raise ValueError("URModel.joint_limits needs 6 (lower, upper) pairs")

    @property
    def lower(self) -> np.ndarray:
        return np.array([lo for lo, _ in self.joint_limits])

    @property
    def upper(self) -> np.ndarray:
        return np.array([hi for _, hi in self.joint_limits])


def _deg(values: tuple[float, ...]) -> tuple[float, ...]:
    return tuple(math.radians(v) for v in values)


#: UR e-Series arms (DH table of UR's support article; speeds from the user manuals).
UR_MODELS: dict[str, URModel] = {
    "ur3e": URModel(
        "ur3e",
        d=(0.15185, 0.0, 0.0, 0.13105, 0.08535, 0.0921),
        a=(0.0, -0.24355, -0.2132, 0.0, 0.0, 0.0),
        alpha=_ALPHA,
        joint_limits=_LIMITS,
        max_joint_speed=_deg((180, 180, 180, 360, 360, 360)),
        link_mass=(1.98, 3.4445, 1.437, 0.871, 0.805, 0.261),
        reach=0.50,
        visual_radius=0.045,
    ),
    "ur5e": URModel(
        "ur5e",
        d=(0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996),
        a=(0.0, -0.425, -0.3922, 0.0, 0.0, 0.0),
        alpha=_ALPHA,
        joint_limits=_LIMITS,
        max_joint_speed=_deg((180,) * 6),
        link_mass=(3.761, 8.058, 2.846, 1.37, 1.3, 0.365),
        reach=0.85,
        visual_radius=0.06,
    ),
    "ur10e": URModel(
        "ur10e",
        d=(0.1807, 0.0, 0.0, 0.17415, 0.11985, 0.11655),
        a=(0.0, -0.6127, -0.57155, 0.0, 0.0, 0.0),
        alpha=_ALPHA,
        joint_limits=_LIMITS,
        max_joint_speed=_deg((120, 120, 180, 180, 180, 180)),
        link_mass=(7.369, 13.051, 3.989, 2.1, 1.98, 0.615),
        reach=1.30,
        visual_radius=0.075,
    ),
    "ur16e": URModel(
        "ur16e",
        d=(0.1807, 0.0, 0.0, 0.17415, 0.11985, 0.11655),
        a=(0.0, -0.4784, -0.36, 0.0, 0.0, 0.0),
        alpha=_ALPHA,
        joint_limits=_LIMITS,
        max_joint_speed=_deg((120, 120, 180, 180, 180, 180)),
        link_mass=(7.369, 10.45, 4.321, 2.18, 2.033, 0.907),
        reach=0.90,
        visual_radius=0.075,
    ),
}


def ur_model(name: str) -> URModel:
    """The model called ``name`` (``ur3e``, ``ur5e``, ``ur10e``, ``ur16e``)."""
    try:
        return UR_MODELS[name]
    except KeyError:
        known = ", ".join(sorted(UR_MODELS))
        raise ValueError(f"unknown arm model {name!r}; known: {known}") from None


def _check_q(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    if q.shape != (6,):
        raise ValueError(f"joint vector q must have shape (6,); got {q.shape}")
    if not np.all(np.isfinite(q)):
        raise ValueError("joint vector q contains NaN or infinite values")
    return q


def dh_transform(a: float, alpha: float, d: float, theta: float) -> np.ndarray:
    """Standard DH link transform ``Rz(θ)·Tz(d)·Tx(a)·Rx(α)`` as a 4×4 matrix."""
    ct, st = math.cos(theta), math.sin(theta)
    ca, sa = math.cos(alpha), math.sin(alpha)
    return np.array(
        [
            [ct, -st * ca, st * sa, a * ct],
            [st, ct * ca, -ct * sa, a * st],
            [0.0, sa, ca, d],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


def joint_frames(model: URModel, q: np.ndarray) -> np.ndarray:
    """``X_B{i}`` for DH frames i = 0…6 as a (7, 4, 4) array; frame 0 is B, frame 6 is E."""
    q = _check_q(q)
    frames = np.empty((7, 4, 4))
    frames[0] = np.eye(4)
    for i in range(6):
        frames[i + 1] = frames[i] @ dh_transform(model.a[i], model.alpha[i], model.d[i], q[i])
    return frames


def forward_kinematics(model: URModel, q: np.ndarray) -> Pose:
    """``X_BE``: the flange (tool0) in the base frame."""
    return Pose.from_matrix(joint_frames(model, q)[6])


def jacobian_from_frames(frames: np.ndarray) -> np.ndarray:
    """Geometric Jacobian (6×6) from the DH frames: ``V_BE = J q̇`` with V = [v, ω] in B.

    Column i of a revolute joint about z_{i} (axis of frame i, through its origin o_i):
    ``[z_i × (o_E − o_i); z_i]`` (Siciliano et al., Robotics, §3.1).
    """
    z = frames[:6, :3, 2]  # joint axes (6, 3)
    lever = frames[6, :3, 3] - frames[:6, :3, 3]  # joint origin → flange (6, 3)
    # row-wise z × lever, written out (np.cross costs more than the rest of this function)
    cross = z[:, [1, 2, 0]] * lever[:, [2, 0, 1]] - z[:, [2, 0, 1]] * lever[:, [1, 2, 0]]
    return np.vstack([cross.T, z.T])


def jacobian(model: URModel, q: np.ndarray) -> np.ndarray:
    """Geometric Jacobian of the flange at ``q`` (see ``jacobian_from_frames``)."""
    return jacobian_from_frames(joint_frames(model, q))


def manipulability(J: np.ndarray) -> float:
    """Yoshikawa's measure w = √det(J Jᵀ) (m³/rad³ for this mixed-unit J)."""
    return float(np.sqrt(max(np.linalg.det(J @ J.T), 0.0)))


def damped_least_squares(
    J: np.ndarray, V: np.ndarray, *, sigma_threshold: float, damping_max: float
) -> tuple[np.ndarray, float]:
    """Joint velocities for twist ``V`` by damped least squares, and the smallest singular value.

    ``q̇ = Σ σ_i/(σ_i² + λ²) v_i u_iᵀ V`` with the damping switched on only near a singularity:
    λ² = (1 − (σ_min/ε)²)·λ_max² when σ_min < ε, else 0 — the singular-value-based damping of
    Nakamura & Hanafusa (1986) and Chiaverini, "Singularity-robust task-priority redundancy
    resolution…", IEEE T-RA 13(3), 1997. Away from singularities it is the exact inverse.
    """
    U, sigma, Vt = np.linalg.svd(J)
    sigma_min = float(sigma[-1])
    lam2 = 0.0
    if sigma_min < sigma_threshold:
        lam2 = (1.0 - (sigma_min / sigma_threshold) ** 2) * damping_max**2
    gains = sigma / (sigma**2 + lam2) if lam2 > 0 else 1.0 / sigma
    qd = Vt.T @ (gains * (U.T @ np.asarray(V, dtype=float)))
    return qd, sigma_min


def pose_error(X_current: Pose, X_target: Pose) -> np.ndarray:
    """[Δp, Δθ] in the base frame taking ``X_current`` to ``X_target`` (Δθ a rotation vector)."""
    dtheta = Rotation.from_matrix(X_target.R @ X_current.R.T).as_rotvec()
    return np.concatenate([X_target.p - X_current.p, dtheta])


def solve_ik(
    model: URModel,
    X_BE_target: Pose,
    q_start: np.ndarray,
    *,
    tol_m: float = 1e-6,
    tol_rad: float = 1e-6,
    max_iterations: int = 200,
) -> tuple[np.ndarray, bool]:
    """Joint angles reaching ``X_BE_target`` from ``q_start`` by damped Newton steps on the pose
    error (the resolved-rate law integrated to convergence), respecting joint ranges.

    Returns (q, converged). Used to set up and check rigs, never in the control loop.
    """
    q = _check_q(q_start).copy()
    lower, upper = model.lower, model.upper
    for _ in range(max_iterations):
        frames = joint_frames(model, q)
        error = pose_error(Pose.from_matrix(frames[6]), X_BE_target)
        if np.linalg.norm(error[:3]) < tol_m and np.linalg.norm(error[3:]) < tol_rad:
            return q, True
        step, _ = damped_least_squares(
            jacobian_from_frames(frames), error, sigma_threshold=0.02, damping_max=0.02
        )
        largest = np.max(np.abs(step))
        if largest > 0.3:  # keep Newton steps small enough to stay on one IK branch
            step *= 0.3 / largest
        q = np.clip(q + step, lower, upper)
    return q, False
