"""Rigid transforms, the camera model and the pose-error metrics used everywhere.

Notation (Drake's monogram notation, see DESIGN.md): ``X_AB`` is the pose of frame B in frame
A, so a point with coordinates ``p_B`` in B has coordinates ``p_A = X_AB.apply(p_B)`` in A, and
poses compose when the inner letters cancel: ``X_AC = X_AB @ X_BC``. ``R_AB`` is the rotation
part and ``p_AB`` the position of B's origin in A. Units are SI (metres, radians).

Camera frame C is OpenCV's optical frame (x right, y down, z forward); pixel coordinates put
integer values at pixel centres. Lens distortion follows OpenCV's model with 4, 5, 8, 12 or 14
coefficients ``(k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4[, τx, τy]]]])``: radial
(rational), tangential, thin prism and the tilted-sensor terms — depthai reports all 14.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

_ORTHONORMAL_TOL = 1e-6


def as_points(points: np.ndarray, dim: int, name: str) -> np.ndarray:
    array = np.asarray(points, dtype=float)
    if array.ndim == 1 and array.shape[0] == dim:
        array = array[None, :]
    if array.ndim != 2 or array.shape[1] != dim:
        raise ValueError(f"{name} must have shape (N, {dim}); got {np.shape(points)}")
    return array


def _frozen(array: np.ndarray) -> np.ndarray:
    array = np.array(array, dtype=float)  # a private copy
    array.flags.writeable = False
    return array


@dataclass(frozen=True, slots=True, eq=False)
class Pose:
    """A rigid transform ``X_AB``: rotation ``R`` (= R_AB) and translation ``p`` (= p_AB, m).

    Immutable; construct with ``Pose(R, p)``, ``Pose.from_matrix``, ``Pose.from_rotvec`` or
    ``Pose.identity()``. ``R`` must be orthonormal with determinant +1 (within 1e-6).
    """

    R: np.ndarray
    p: np.ndarray

    def __post_init__(self) -> None:
        R = np.asarray(self.R, dtype=float)
        p = np.asarray(self.p, dtype=float).reshape(-1)
        if R.shape != (3, 3):
            raise ValueError(f"Pose.R must be 3x3; got shape {R.shape}")
        if p.shape != (3,):
            raise ValueError(f"Pose.p must have 3 elements; got shape {np.shape(self.p)}")
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(p))):
            raise ValueError("Pose contains NaN or infinite values")
        deviation = np.abs(R @ R.T - np.eye(3)).max()
        if deviation > _ORTHONORMAL_TOL or np.linalg.det(R) < 0:
            raise ValueError(
                f"Pose.R is not a rotation (|R Rᵀ − I| = {deviation:.2e}, det = "
                f"{np.linalg.det(R):.3f}); use Pose.from_matrix(..., orthonormalize=True)"
            )
        object.__setattr__(self, "R", _frozen(R))
        object.__setattr__(self, "p", _frozen(p))

    # --- construction -------------------------------------------------------------------
    @classmethod
    def unchecked(cls, R: np.ndarray, p: np.ndarray) -> Pose:
        """A pose known to be a rigid transform up to rounding — computed from valid poses
        (product, inverse) or read back from a log that wrote one — so the checks of
        ``__post_init__`` are skipped: they dominate the cost of composing poses in the control
        loop and of reading logs."""
        pose = object.__new__(cls)
        R, p = np.array(R, dtype=float), np.array(p, dtype=float)
        R.flags.writeable = False
        p.flags.writeable = False
        object.__setattr__(pose, "R", R)
        object.__setattr__(pose, "p", p)
        return pose

    @staticmethod
    def identity() -> Pose:
        return Pose(np.eye(3), np.zeros(3))

    @staticmethod
    def from_matrix(X: np.ndarray, *, orthonormalize: bool = False) -> Pose:
        """From a 4×4 homogeneous matrix; ``orthonormalize`` projects R onto SO(3) by SVD."""
        X = np.asarray(X, dtype=float)
        if X.shape != (4, 4):
            raise ValueError(f"a pose matrix must be 4x4; got shape {X.shape}")
        if not np.allclose(X[3], [0.0, 0.0, 0.0, 1.0]):
            raise ValueError(f"the last row of a pose matrix must be [0 0 0 1]; got {X[3]}")
        R = X[:3, :3]
        if orthonormalize:
            R = nearest_rotation(R)
        return Pose(R, X[:3, 3])

    @staticmethod
    def from_rotvec(rotvec: np.ndarray, p: np.ndarray) -> Pose:
        """From an axis-angle vector (rad) and a translation (m)."""
        return Pose(Rotation.from_rotvec(np.asarray(rotvec, dtype=float)).as_matrix(), p)

    @staticmethod
    def from_rpy(roll: float, pitch: float, yaw: float, p: np.ndarray) -> Pose:
        """From roll/pitch/yaw (rad) about fixed x, y, z (R = Rz(yaw)·Ry(pitch)·Rx(roll))."""
        return Pose(Rotation.from_euler("xyz", [roll, pitch, yaw]).as_matrix(), p)

    # --- views ----------------------------------------------------------------------------
    @property
    def matrix(self) -> np.ndarray:
        X = np.eye(4)
        X[:3, :3] = self.R
        X[:3, 3] = self.p
        return X

    @property
    def rotvec(self) -> np.ndarray:
        return Rotation.from_matrix(self.R).as_rotvec()

    @property
    def quat_xyzw(self) -> np.ndarray:
        return Rotation.from_matrix(self.R).as_quat()

    def to_list(self) -> list[list[float]]:
        """The 4×4 matrix as nested lists (for JSON)."""
        return self.matrix.tolist()

    # --- algebra --------------------------------------------------------------------------
    def inverse(self) -> Pose:
        """``X_BA`` from ``X_AB``."""
        return Pose.unchecked(self.R.T, -self.R.T @ self.p)

    def __matmul__(self, other: Pose) -> Pose:
        if not isinstance(other, Pose):
            return NotImplemented
        return Pose.unchecked(self.R @ other.R, self.R @ other.p + self.p)

    def apply(self, points_B: np.ndarray) -> np.ndarray:
        """Map points (N,3) or (3,) expressed in B to A."""
        single = np.ndim(points_B) == 1
        points = as_points(points_B, 3, "points_B")
        out = points @ self.R.T + self.p
        return out[0] if single else out

    def is_close(self, other: Pose, *, atol_m: float = 1e-9, atol_rad: float = 1e-9) -> bool:
        return (
            translation_error(self, other) <= atol_m
            and rotation_error_geodesic(self, other) <= atol_rad
        )

    def __repr__(self) -> str:
        rpy = np.degrees(Rotation.from_matrix(self.R).as_euler("xyz"))
        return (
            f"Pose(p=[{self.p[0]:.4f}, {self.p[1]:.4f}, {self.p[2]:.4f}] m, "
            f"rpy=[{rpy[0]:.2f}, {rpy[1]:.2f}, {rpy[2]:.2f}] deg)"
        )


def nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation matrix closest to ``M`` in the Frobenius norm (SVD, det forced to +1)."""
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=float))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def skew(v: np.ndarray) -> np.ndarray:
    """The cross-product matrix [v]ₓ, so that ``skew(a) @ b == np.cross(a, b)``."""
    x, y, z = np.asarray(v, dtype=float)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a × b of two 3-vectors — ``np.cross``'s own arithmetic without its overhead, which on a
    single pair is ten times the product's (the ellipse system's pose algebra makes hundreds a
    frame)."""
    a0, a1, a2 = a
    b0, b1, b2 = b
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def any_perpendicular(v: np.ndarray) -> np.ndarray:
    """A unit vector perpendicular to the unit vector ``v`` (from x, or y when ``v`` is
    near x)."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(v[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    p = helper - (helper @ v) * v
    return p / np.linalg.norm(p)


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking the direction of ``a`` onto that of ``b`` (a half turn
    about a perpendicular when they are opposite)."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    v = cross3(a, b)
    c = float(a @ b)
    if np.linalg.norm(v) < 1e-12:
        if c > 0:
            return np.eye(3)
        p = any_perpendicular(a)
        return 2.0 * np.outer(p, p) - np.eye(3)
    vx = skew(v)
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def look_at(p_AC: np.ndarray, p_A_target: np.ndarray, up_A: np.ndarray) -> Pose:
    """Pose ``X_AC`` of an optical camera frame at ``p_AC`` whose z axis points at a target.

    The image's "up" (−y of the optical frame) is as close to ``up_A`` as possible.
    """
    z = np.asarray(p_A_target, dtype=float) - np.asarray(p_AC, dtype=float)
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up_A, dtype=float))
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: the up vector is parallel to the viewing direction")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return Pose(np.column_stack([x, y, z]), p_AC)


# --- camera model ---------------------------------------------------------------------------

_SUPPORTED_DISTORTION_LENGTHS = (0, 4, 5, 8, 12, 14)


def check_distortion(dist: np.ndarray) -> np.ndarray:
    """Return ``dist`` as a float array of a supported OpenCV length (0, 4, 5, 8, 12 or 14)."""
    d = np.asarray(dist, dtype=float).reshape(-1)
    if d.size not in _SUPPORTED_DISTORTION_LENGTHS:
        raise ValueError(
            f"distortion must have 0, 4, 5, 8, 12 or 14 coefficients (OpenCV order); got {d.size}"
        )
    if not np.all(np.isfinite(d)):
        raise ValueError("distortion coefficients must be finite")
    return d


def padded_distortion(dist: np.ndarray) -> np.ndarray:
    """``dist`` zero-padded to the next length OpenCV knows (a model's missing trailing
    coefficients are zeros: the same lens); ValueError beyond 14."""
    d = np.asarray(dist, dtype=float).reshape(-1)
    longer = [n for n in _SUPPORTED_DISTORTION_LENGTHS if n >= d.size]
    if not longer:
        raise ValueError(f"distortion must have at most 14 coefficients; got {d.size}")
    return check_distortion(np.r_[d, np.zeros(longer[0] - d.size)])


def sensor_tilt_matrix(tau_x: float, tau_y: float) -> np.ndarray:
    """OpenCV's tilted-sensor projection (3×3) for tilts τx, τy (rad) of the image sensor.

    The sensor plane is rotated by R = Ry(τy)·Rx(τx) and the image re-projected onto it along
    the optical axis (Louhichi et al., "Self-calibration of Scheimpflug cameras", 2007; OpenCV's
    ``computeTiltProjectionMatrix``): M = P_z(R)·R with P_z = [[r22, 0, −r02], [0, r22, −r12],
    [0, 0, 1]]. A distorted point (x, y) maps to (M·[x, y, 1]) dehomogenised.
    """
    cx, sx = np.cos(tau_x), np.sin(tau_x)
    cy, sy = np.cos(tau_y), np.sin(tau_y)
    R_x = np.array([[1.0, 0.0, 0.0], [0.0, cx, sx], [0.0, -sx, cx]])
    R_y = np.array([[cy, 0.0, -sy], [0.0, 1.0, 0.0], [sy, 0.0, cy]])
    R = R_y @ R_x
    P_z = np.array([[R[2, 2], 0.0, -R[0, 2]], [0.0, R[2, 2], -R[1, 2]], [0.0, 0.0, 1.0]])
    return P_z @ R


def distort_normalized(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Apply OpenCV lens distortion to normalized image coordinates (N,2) → (N,2)."""
    xy = as_points(xy, 2, "xy")
    # Compiled, and imported here: importing this module (configuration, scenes, logs do)
    # does not load numba.
    from estimators.lens_distortion import distort

    return distort(np.ascontiguousarray(xy), *lens_terms(dist))


def lens_terms(dist: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """The distortion coefficients padded to 14, the tilted sensor's projection (identity
    without a tilt) and whether there is one — the compiled lens model's arguments (read-only:
    a camera's are computed once, as every projection asks for them)."""
    coeffs = check_distortion(dist)
    return _lens_terms_of(coeffs.tobytes())


@functools.lru_cache(maxsize=32)
def _lens_terms_of(coeffs_bytes: bytes) -> tuple[np.ndarray, np.ndarray, bool]:
    coeffs = np.frombuffer(coeffs_bytes)
    d = np.zeros(14)
    d[: coeffs.size] = coeffs
    tilted = bool(d[12] != 0.0 or d[13] != 0.0)
    M = sensor_tilt_matrix(d[12], d[13]) if tilted else np.eye(3)
    d.flags.writeable = False
    M.flags.writeable = False
    return d, M, tilted


def project(points_C: np.ndarray, K: np.ndarray, dist: np.ndarray | None = None) -> np.ndarray:
    """Pixel coordinates (N,2) of 3-D points (N,3) given in the camera optical frame C.

    Points must lie in front of the camera (z > 0); otherwise ValueError.
    """
    points = as_points(points_C, 3, "points_C")
    if np.any(points[:, 2] <= 0):
        raise ValueError("project: points must have positive depth z in the camera frame")
    if dist is not None and np.size(dist) > 0:
        from estimators.lens_distortion import project_distorted

        return project_distorted(
            np.ascontiguousarray(points), np.asarray(K, dtype=float), *lens_terms(dist)
        )
    xy = points[:, :2] / points[:, 2:3]
    K = np.asarray(K, dtype=float)
    uv = np.empty((len(xy), 2))
    uv[:, 0] = K[0, 0] * xy[:, 0] + K[0, 1] * xy[:, 1] + K[0, 2]
    uv[:, 1] = K[1, 1] * xy[:, 1] + K[1, 2]
    return uv


def project_from(
    X_CT: Pose, points_T: np.ndarray, K: np.ndarray, dist: np.ndarray | None = None
) -> np.ndarray:
    """Pixel coordinates of points given in frame T, seen by a camera at ``X_CT``."""
    return project(X_CT.apply(points_T), K, dist)


def undistort_pixels(uv: np.ndarray, K: np.ndarray, dist: np.ndarray | None) -> np.ndarray:
    """Normalized, undistorted image coordinates (N,2) of pixel coordinates (N,2).

    Inverts the distortion model iteratively (OpenCV's undistortPointsIter, to 1e-12).
    """
    uv = as_points(uv, 2, "uv")
    K = np.asarray(K, dtype=float)
    if dist is None or np.size(dist) == 0:
        x = (uv[:, 0] - K[0, 2] - K[0, 1] * (uv[:, 1] - K[1, 2]) / K[1, 1]) / K[0, 0]
        y = (uv[:, 1] - K[1, 2]) / K[1, 1]
        return np.column_stack([x, y])
    dist = check_distortion(dist)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    xy = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, dist, criteria=criteria).reshape(-1, 2)
    xy_d = np.column_stack(
        [
            (uv[:, 0] - K[0, 2] - K[0, 1] * (uv[:, 1] - K[1, 2]) / K[1, 1]) / K[0, 0],
            (uv[:, 1] - K[1, 2]) / K[1, 1],
        ]
    )
    # OpenCV's fixed-point iteration can stall short of the tolerance for strong distortion;
    # two Newton steps on distort(xy) = xy_d make the inverse exact to ~1e-12.
    from estimators.lens_distortion import refine_undistorted

    return refine_undistorted(np.ascontiguousarray(xy, dtype=float), xy_d, *lens_terms(dist), 2)


def field_radius(K: np.ndarray, dist: np.ndarray | None, width: int, height: int) -> float:
    """Largest normalized radius √(x² + y²) of a ray that reaches the image (its corners).

    Beyond its calibrated field a distortion polynomial can fold back, so that points far
    outside the view "project" into the image; ``in_view`` rejects them with this radius.
    """
    K = np.ascontiguousarray(K, dtype=float)
    dist = np.zeros(0) if dist is None else np.ascontiguousarray(dist, dtype=float)
    # A property of the camera asked for at every visibility test: computed once per camera.
    return _field_radius(K.tobytes(), dist.tobytes(), len(dist), int(width), int(height))


@functools.lru_cache(maxsize=32)
def _field_radius(K_bytes: bytes, dist_bytes: bytes, n_dist: int, width: int, height: int) -> float:
    K = np.frombuffer(K_bytes).reshape(3, 3)
    dist = np.frombuffer(dist_bytes) if n_dist else None
    corners = np.array(
        [[-0.5, -0.5], [width - 0.5, -0.5], [-0.5, height - 0.5], [width - 0.5, height - 0.5]]
    )
    return float(np.linalg.norm(undistort_pixels(corners, K, dist), axis=1).max())


def in_view(
    points_C: np.ndarray,
    K: np.ndarray,
    dist: np.ndarray | None,
    width: int,
    height: int,
    *,
    margin_px: float = 0.0,
) -> np.ndarray:
    """Boolean mask (N,) of points (N,3) in C that a camera images at least ``margin_px``
    inside its borders (the pixels' outer edges): in front of it, within its field (no
    fold-back), inside the image."""
    from estimators.lens_distortion import visible_pixels

    points = np.ascontiguousarray(as_points(points_C, 3, "points_C"))
    dist = np.zeros(0) if dist is None else np.asarray(dist, dtype=float)
    seen, _ = visible_pixels(
        points, np.asarray(K, dtype=float), *lens_terms(dist), dist.size > 0,
        1e-9, 1.02 * field_radius(K, dist, width, height),
        margin_px - 0.5, width - 0.5 - margin_px, margin_px - 0.5, height - 0.5 - margin_px,
    )  # fmt: skip
    return seen


def back_project(uv: np.ndarray, K: np.ndarray, dist: np.ndarray | None = None) -> np.ndarray:
    """Unit viewing rays (N,3) in the camera frame C through pixels (N,2)."""
    xy = undistort_pixels(uv, K, dist)
    rays = np.column_stack([xy, np.ones(len(xy))])
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def intrinsics_from_fov(width_px: int, height_px: int, hfov_deg: float) -> np.ndarray:
    """Pinhole K (square pixels) for a horizontal field of view, principal point centred.

    The centre of an image W pixels wide is at (W − 1)/2 with pixel centres at integers.
    """
    if not 0.0 < hfov_deg < 180.0:
        raise ValueError(f"hfov_deg must be in (0, 180); got {hfov_deg}")
    f = 0.5 * width_px / np.tan(np.radians(hfov_deg) / 2.0)
    return np.array([[f, 0.0, (width_px - 1) / 2.0], [0.0, f, (height_px - 1) / 2.0], [0, 0, 1]])


# --- error metrics --------------------------------------------------------------------------


def translation_error(X_true: Pose, X_est: Pose) -> float:
    """Euclidean distance between the two positions (m)."""
    return float(np.linalg.norm(X_true.p - X_est.p))


def rotation_error_geodesic(X_true: Pose, X_est: Pose) -> float:
    """Geodesic angle (rad) of R_true · R_estᵀ, in [0, π]."""
    R = X_true.R @ X_est.R.T
    cos_angle = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    # arccos loses precision near 0; the axis-angle norm does not.
    if cos_angle > 0.99:
        return float(np.linalg.norm(Rotation.from_matrix(R).as_rotvec()))
    return float(np.arccos(cos_angle))


def rotation_error_rpy_norm(X_true: Pose, X_est: Pose) -> float:
    """Norm (rad) of the roll/pitch/yaw of R_true · R_estᵀ — the reference study's metric."""
    rpy = Rotation.from_matrix(X_true.R @ X_est.R.T).as_euler("xyz")
    return float(np.linalg.norm(rpy))


def normal_angle(n_true: np.ndarray, n_est: np.ndarray) -> float:
    """Angle (rad) between two oriented normals (a flipped normal counts as π)."""
    a = np.asarray(n_true, dtype=float)
    b = np.asarray(n_est, dtype=float)
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    return float(np.arctan2(np.linalg.norm(cross3(a, b)), np.dot(a, b)))
