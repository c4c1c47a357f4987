"""Pose of a (nearly) planar target from image features: closed-form start, nonlinear least
squares on reprojection error with its covariance, an orthogonal-iteration alternative, and the
planar two-fold ambiguity.

Image measurements enter in *ideal pixels*: undistorted normalized coordinates mapped through
K (``ideal_pixels``), so that the pose math is a pinhole model for any camera.

Pose perturbation (matches ``estimators.measurement``): δ = [δθ, δp] with
R_true = Exp(δθ)·R_est and p_true = p_est + δp, in the camera frame C. A point P_T maps to
P_C = R·P_T + p, so ∂P_C/∂δθ = −[R·P_T]ₓ and ∂P_C/∂δp = I.

Algorithms:
* IPPE — T. Collins and A. Bartoli, "Infinitesimal Plane-Based Pose Estimation", IJCV 109(3),
  2014 (OpenCV's ``SOLVEPNP_IPPE``): both poses of the planar two-fold ambiguity in closed form.
* Gauss–Newton / Levenberg–Marquardt on the whitened reprojection residuals (the reference's
  GLSDC, "Gaussian least-squares differential correction", is Gauss–Newton on this cost);
  covariance s²·(JᵀJ)⁻¹ with s² = χ²/(m − 6) from the residuals. The loop is
  ``least_squares.solve`` (``PoseProblem`` adapts the observations to it): no loss for
  ``refine_pose``, Cauchy weights for ``refine_pose_robust``.
* Orthogonal iteration — C.-P. Lu, G. D. Hager and E. Mjolsness, "Fast and globally
  convergent pose estimation from video images", IEEE PAMI 22(6), 2000: minimises the
  object-space collinearity error by alternating translation and absolute orientation.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Literal, Protocol

import cv2
import numpy as np

from estimators.compiled import compiled
from estimators.geometry import (
    Pose,
    as_points,
    nearest_rotation,
    rotation_between,
    rotation_error_geodesic,
)
from estimators.geometry import undistort_pixels as _undistort
from estimators.least_squares import Cauchy, NoLoss, covariance, solve
from estimators.so3 import exp_so3, pose_error_C

PoseMethod = Literal["gauss_newton", "lhm"]
POSE_METHODS: tuple[str, ...] = ("gauss_newton", "lhm")
#: The variance factor of a fit whose observations carry their own σ (from their own fits, with
#: the models' errors as floors) never goes below 1: with the few degrees of freedom of a pose
#: fit a χ²/dof below 1 is luck, not precision (8 dof: 0.34–1.94 in 90 % of frames).
MIN_SCALE2 = 1.0


# --- camera coordinates ----------------------------------------------------------------------


def ideal_pixels(uv: np.ndarray, K: np.ndarray, dist: np.ndarray | None) -> np.ndarray:
    """Pixels (N,2) of a distorted camera mapped to the pinhole image with the same K."""
    uv = as_points(uv, 2, "uv")
    if dist is None or not np.any(np.asarray(dist) != 0) or len(uv) == 0:
        return uv.copy()
    xy = _undistort(uv, K, dist)
    return np.column_stack(
        [K[0, 0] * xy[:, 0] + K[0, 1] * xy[:, 1] + K[0, 2], K[1, 1] * xy[:, 1] + K[1, 2]]
    )


def ideal_pixel_jacobians(uv: np.ndarray, K: np.ndarray, dist: np.ndarray | None) -> np.ndarray:
    """∂(ideal pixel)/∂(pixel) (N,2,2) at each pixel, by central differences (identity without
    distortion) — maps a measured pixel covariance into ideal pixels."""
    uv = as_points(uv, 2, "uv")
    n = len(uv)
    if dist is None or not np.any(np.asarray(dist) != 0):
        return np.broadcast_to(np.eye(2), (n, 2, 2)).copy()
    h = 0.25
    # The four shifted copies mapped in one call (each point is undistorted on its own).
    steps = np.array([[h, 0.0], [-h, 0.0], [0.0, h], [0.0, -h]])
    shifted = ideal_pixels((uv[None, :, :] + steps[:, None, :]).reshape(-1, 2), K, dist)
    shifted = shifted.reshape(4, n, 2)
    J = np.empty((n, 2, 2))
    for axis in range(2):
        J[:, :, axis] = (shifted[2 * axis] - shifted[2 * axis + 1]) / (2 * h)
    return J


def project_ideal(X_CT: Pose, points_T: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Ideal (pinhole) pixels (N,2) of points in T; points behind the camera give NaN."""
    P = X_CT.apply(as_points(points_T, 3, "points_T"))
    z = np.where(P[:, 2] > 1e-9, P[:, 2], np.nan)
    x, y = P[:, 0] / z, P[:, 1] / z
    return np.column_stack([K[0, 0] * x + K[0, 1] * y + K[0, 2], K[1, 1] * y + K[1, 2]])


def projection_jacobian(X_CT: Pose, points_T: np.ndarray, K: np.ndarray):
    """Ideal pixels (N,2), their Jacobian (N,2,6) w.r.t. [δθ, δp], and the depths (N,); a
    point at or behind the camera (depth ≤ 1e-9) gives NaN pixels and NaN in its Jacobian."""
    return _projection(
        np.asarray(X_CT.R, dtype=float),
        np.asarray(X_CT.p, dtype=float),
        np.ascontiguousarray(points_T, dtype=float).reshape(-1, 3),
        np.asarray(K, dtype=float),
    )


@compiled
def _projection(R, p, points_T, K):
    """``projection_jacobian`` point by point: as NumPy, calls on (N,2,3) and (N,3,6) arrays
    cost more than their arithmetic for the few dozen points of a fit."""
    n = len(points_T)
    uv, J, depth = np.empty((n, 2)), np.empty((n, 2, 6)), np.empty(n)
    fx, skew, cx, fy, cy = K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]
    q = np.empty(3)
    for i in range(n):
        for a in range(3):
            q[a] = R[a, 0] * points_T[i, 0] + R[a, 1] * points_T[i, 1] + R[a, 2] * points_T[i, 2]
        x, y, z = q[0] + p[0], q[1] + p[1], q[2] + p[2]
        depth[i] = z
        z = z if z > 1e-9 else np.nan
        uv[i, 0] = (fx * x + skew * y) / z + cx
        uv[i, 1] = fy * y / z + cy
        # ∂(u, v)/∂P, and ∂P/∂[δθ, δp] = [−[q]ₓ, I]
        du0, du1, du2 = fx / z, skew / z, -(fx * x + skew * y) / (z * z)
        dv1, dv2 = fy / z, -fy * y / (z * z)
        J[i, 0, 0] = du1 * -q[2] + du2 * q[1]
        J[i, 0, 1] = du0 * q[2] + du2 * -q[0]
        J[i, 0, 2] = du0 * -q[1] + du1 * q[0]
        J[i, 0, 3], J[i, 0, 4], J[i, 0, 5] = du0, du1, du2
        J[i, 1, 0] = dv1 * -q[2] + dv2 * q[1]
        J[i, 1, 1] = dv2 * -q[0]
        J[i, 1, 2] = dv1 * q[0]
        J[i, 1, 3], J[i, 1, 4], J[i, 1, 5] = 0.0, dv1, dv2
    return uv, J, depth


@compiled
def _whitened_reprojection(R, p, points_T, K, L, uv_measured):
    """``PointObservations.linearize`` compiled: each point's reprojection error and its
    Jacobian (``_projection``), whitened by its L (2×2) — the corner system linearises a few
    dozen points some twenty times a frame."""
    n = len(points_T)
    uv, J, _ = _projection(R, p, points_T, K)
    r, r_w, J_w = np.empty(2 * n), np.empty(2 * n), np.empty((2 * n, 6))
    for i in range(n):
        ru, rv = uv[i, 0] - uv_measured[i, 0], uv[i, 1] - uv_measured[i, 1]
        r[2 * i], r[2 * i + 1] = ru, rv
        for a in range(2):
            r_w[2 * i + a] = L[i, a, 0] * ru + L[i, a, 1] * rv
            for c in range(6):
                J_w[2 * i + a, c] = L[i, a, 0] * J[i, 0, c] + L[i, a, 1] * J[i, 1, c]
    return r, r_w, J_w


# --- observations ----------------------------------------------------------------------------


class Observations(Protocol):
    """Something that gives whitened residuals and their Jacobian at a pose: ``size``
    residuals from ``count`` measured image features."""

    @property
    def size(self) -> int: ...

    @property
    def count(self) -> int: ...

    def linearize(self, X_CT: Pose, K: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...


def _whitener(covariance: np.ndarray) -> np.ndarray:
    """L (N,2,2) with Lᵀ·L = Σ⁻¹ for each 2×2 covariance Σ (so L·r has unit covariance)."""
    info = np.linalg.inv(covariance)
    return np.linalg.cholesky(info).transpose(0, 2, 1)


@dataclass(frozen=True, slots=True, eq=False)
class PointObservations:
    """Image points ``uv`` (N,2, ideal px) of model points ``points_T`` (N,3) with 2×2 pixel
    covariances ``covariance`` (N,2,2). Residual: projected minus measured."""

    points_T: np.ndarray
    uv: np.ndarray
    covariance: np.ndarray
    _whitening: np.ndarray = field(default=None, repr=False)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        points = as_points(self.points_T, 3, "points_T")
        uv = as_points(self.uv, 2, "uv")
        cov = np.asarray(self.covariance, dtype=float)
        if cov.shape != (len(points), 2, 2) or len(uv) != len(points):
            raise ValueError(
                f"PointObservations: {len(points)} points need {len(points)} uv and (N,2,2) "
                f"covariances; got {uv.shape} and {cov.shape}"
            )
        object.__setattr__(self, "points_T", points)
        object.__setattr__(self, "uv", uv)
        object.__setattr__(self, "covariance", cov)
        object.__setattr__(self, "_whitening", _whitener(cov) if len(cov) else np.zeros((0, 2, 2)))

    @classmethod
    def from_image(
        cls,
        points_T: np.ndarray,
        uv: np.ndarray,
        covariance: np.ndarray,
        K: np.ndarray,
        dist: np.ndarray | None,
    ) -> PointObservations:
        """Observations measured in a distorted camera's pixels (N,2) with covariances
        (N,2,2): mapped to ideal pixels, the covariances through the mapping's Jacobian."""
        if dist is not None and np.any(np.asarray(dist) != 0):
            J = ideal_pixel_jacobians(uv, K, dist)
            covariance = J @ covariance @ J.transpose(0, 2, 1)
        return cls(points_T, ideal_pixels(uv, K, dist), covariance)

    @property
    def size(self) -> int:
        return 2 * len(self.points_T)

    @property
    def count(self) -> int:
        """Measured points (the RMS residual is per point, in px)."""
        return len(self.points_T)

    def linearize(self, X_CT: Pose, K: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(residuals in px (2N,), whitened residuals (2N,), whitened Jacobian (2N,6))."""
        return _whitened_reprojection(
            np.asarray(X_CT.R, dtype=float),
            np.asarray(X_CT.p, dtype=float),
            self.points_T,
            np.asarray(K, dtype=float),
            self._whitening,
            self.uv,
        )


@dataclass(frozen=True, slots=True, eq=False)
class EdgeObservations:
    """Points measured on the images of straight model edges.

    ``ends_T`` (E,2,3): each edge's end points in T. ``edge`` (M,): which edge each measured
    point ``uv`` (M,2, ideal px) lies on, with standard deviation ``sigma_px`` (M,) across the
    edge. Residual: the signed distance of the point from the line through the projected ends
    (the point's position along the edge carries no information and is not modelled).
    """

    ends_T: np.ndarray
    edge: np.ndarray
    uv: np.ndarray
    sigma_px: np.ndarray

    def __post_init__(self) -> None:
        ends = np.asarray(self.ends_T, dtype=float)
        if ends.ndim != 3 or ends.shape[1:] != (2, 3):
            raise ValueError(f"EdgeObservations.ends_T must be (E,2,3); got {ends.shape}")
        uv = as_points(self.uv, 2, "uv")
        edge = np.asarray(self.edge, dtype=int).reshape(-1)
        sigma = np.asarray(self.sigma_px, dtype=float).reshape(-1)
        if not (len(edge) == len(uv) == len(sigma)):
            raise ValueError("EdgeObservations: edge, uv and sigma_px must have the same length")
        if len(edge) and (edge.min() < 0 or edge.max() >= len(ends)):
            raise ValueError("EdgeObservations.edge indexes an edge that does not exist")
        if np.any(sigma <= 0):
            raise ValueError("EdgeObservations.sigma_px must be positive")
        for name, value in (("ends_T", ends), ("edge", edge), ("uv", uv), ("sigma_px", sigma)):
            object.__setattr__(self, name, value)

    @property
    def size(self) -> int:
        return len(self.uv)

    @property
    def count(self) -> int:
        return len(self.uv)

    def linearize(self, X_CT: Pose, K: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return _edge_residuals(
            np.asarray(X_CT.R, dtype=float),
            np.asarray(X_CT.p, dtype=float),
            np.ascontiguousarray(self.ends_T.reshape(-1, 3)),
            np.asarray(K, dtype=float),
            self.edge,
            self.uv,
            self.sigma_px,
        )


@compiled
def _edge_residuals(R, p, ends_T, K, edge, uv, sigma):
    """``EdgeObservations.linearize`` compiled, point by point: each point's signed distance r
    from the line through its edge's projected ends a, b (n·(m − a), n = (−e_y, e_x)/|e|,
    e = b − a) and ∂r/∂[δθ, δp] through the ends' projection Jacobians; r, r/σ and J/σ."""
    ends_uv, J_ends, _ = _projection(R, p, ends_T, K)
    m = len(uv)
    r, r_w, J_w = np.empty(m), np.empty(m), np.empty((m, 6))
    for i in range(m):
        a, b = 2 * edge[i], 2 * edge[i] + 1
        ex, ey = ends_uv[b, 0] - ends_uv[a, 0], ends_uv[b, 1] - ends_uv[a, 1]
        length = math.sqrt(ex * ex + ey * ey)
        wx, wy = uv[i, 0] - ends_uv[a, 0], uv[i, 1] - ends_uv[a, 1]
        ri = (ex * wy - ey * wx) / length
        # ∂r/∂b; moving a, b and the point together leaves r unchanged, so ∂r/∂a = −n − ∂r/∂b
        db_x = wy / length - ri / length**2 * ex
        db_y = -wx / length - ri / length**2 * ey
        da_x = ey / length - db_x
        da_y = -ex / length - db_y
        for c in range(6):
            J = (da_x * J_ends[a, 0, c] + da_y * J_ends[a, 1, c]) + (
                db_x * J_ends[b, 0, c] + db_y * J_ends[b, 1, c]
            )
            J_w[i, c] = J / sigma[i]
        r[i] = ri
        r_w[i] = ri / sigma[i]
    return r, r_w, J_w


@dataclass(frozen=True, slots=True, eq=False)
class CorrelatedEdgeObservations:
    """Edge observations whose errors along one edge are not independent: besides each
    point's own noise (``edges.sigma_px``) every edge carries a common error — an offset of
    standard deviation ``offset_sigma_px`` and a turn that moves the ends of its measured
    stretch by ``turn_sigma_px`` (both (E,) px, one per model edge) — the signature of what the
    point noise does not describe: pixel quantisation of the edge, unmodelled relief beside it
    (a plate's side wall), shading. The covariance of edge e's residuals is
    Σ_e = D_e + A_e·Q_e·A_eᵀ with D_e the points' variances, A_e = [1, τ] (τ ∈ [−1, 1] the
    point's place along the measured stretch) and Q_e = diag(σ_offset², σ_turn²).

    Whitening without forming Σ_e: with ĉ = (Q⁻¹ + AᵀD⁻¹A)⁻¹AᵀD⁻¹r (the common error that best
    explains r), the residuals [D^−½(r − A·ĉ); Q^−½·ĉ] are a linear map M·r with MᵀM = Σ⁻¹
    (Woodbury), so least squares on them is generalised least squares under Σ, and (JᵀΣ⁻¹J)⁻¹
    its covariance. ``size`` counts the measured points (the degrees of freedom), not the two
    extra pseudo-residuals per edge.
    """

    edges: EdgeObservations
    offset_sigma_px: np.ndarray
    turn_sigma_px: np.ndarray
    _groups: tuple = field(default=(), repr=False)

    def __post_init__(self) -> None:
        count = len(self.edges.ends_T)
        offset = np.broadcast_to(np.asarray(self.offset_sigma_px, dtype=float), (count,)).copy()
        turn = np.broadcast_to(np.asarray(self.turn_sigma_px, dtype=float), (count,)).copy()
        if np.any(offset <= 0) or np.any(turn <= 0) or not np.all(np.isfinite(offset + turn)):
            raise ValueError(
                "CorrelatedEdgeObservations: offset_sigma_px and turn_sigma_px must be positive"
            )
        object.__setattr__(self, "offset_sigma_px", offset)
        object.__setattr__(self, "turn_sigma_px", turn)
        groups = _edge_groups(self.edges.edge, self.edges.uv, self.edges.sigma_px, offset, turn)
        object.__setattr__(self, "_groups", groups)

    @property
    def size(self) -> int:
        return self.edges.size

    @property
    def count(self) -> int:
        return self.edges.count

    @property
    def group_points(self) -> tuple[np.ndarray, ...]:
        """Per measured edge, in order of edge index, its points' indices (ascending) — the
        pseudo-residuals of the k-th group follow the points' residuals at 2k, 2k + 1."""
        order, bounds = self._groups[0], self._groups[1]
        return tuple(order[a:b] for a, b in itertools.pairwise(bounds))

    def whiten(self, values_w: np.ndarray) -> np.ndarray:
        """M applied to point-whitened values (M,) or (M,k): (M + 2·edges,) or (M + 2·edges, k)."""
        values = np.asarray(values_w, dtype=float)
        out = _whiten(np.ascontiguousarray(values.reshape(len(values), -1)), *self._groups)
        return out.reshape(-1) if values.ndim == 1 else out

    def linearize(self, X_CT: Pose, K: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        r, r_w, J_w = self.edges.linearize(X_CT, K)
        whitened = self.whiten(np.column_stack([r_w, J_w]))  # one pass over the edges for both
        return r, whitened[:, 0], whitened[:, 1:]


@compiled
def _edge_groups(edge, uv, sigma, offset, turn):
    """The whitening's pieces per measured edge (``CorrelatedEdgeObservations``): the points in
    order of edge (``order``, group k is ``order[bounds[k]:bounds[k + 1]]``), each point's
    row of A_w = [1, τ]/σ and of the gain (Q⁻¹ + A_wᵀA_w)⁻¹A_wᵀ (transposed, both (M,2) in
    that order), and each group's Q^−½ diagonal (G,2). τ is the point's place along the
    stretch's principal direction (the larger eigenvector of the points' scatter), scaled to
    [−1, 1]."""
    m = len(edge)
    order = np.argsort(edge, kind="mergesort")
    count = 0
    for k in range(m):
        if k == 0 or edge[order[k]] != edge[order[k - 1]]:
            count += 1
    bounds = np.empty(count + 1, np.int64)
    g = 0
    for k in range(m):
        if k == 0 or edge[order[k]] != edge[order[k - 1]]:
            bounds[g] = k
            g += 1
    bounds[count] = m
    A_w, gain, q_half = np.empty((m, 2)), np.empty((m, 2)), np.empty((count, 2))
    for g in range(count):
        lo, hi = bounds[g], bounds[g + 1]
        e = edge[order[lo]]
        cx = cy = 0.0
        for k in range(lo, hi):
            cx += uv[order[k], 0]
            cy += uv[order[k], 1]
        cx, cy = cx / (hi - lo), cy / (hi - lo)
        sxx = sxy = syy = 0.0
        for k in range(lo, hi):
            dx, dy = uv[order[k], 0] - cx, uv[order[k], 1] - cy
            sxx += dx * dx
            sxy += dx * dy
            syy += dy * dy
        angle = 0.5 * math.atan2(2.0 * sxy, sxx - syy) if hi - lo > 1 else 0.0
        ux, uy = math.cos(angle), math.sin(angle)
        half = 1e-9
        for k in range(lo, hi):
            half = max(half, abs((uv[order[k], 0] - cx) * ux + (uv[order[k], 1] - cy) * uy))
        h00, h01, h11 = offset[e] ** -2, 0.0, turn[e] ** -2
        for k in range(lo, hi):
            i = order[k]
            along = (uv[i, 0] - cx) * ux + (uv[i, 1] - cy) * uy
            A_w[k, 0], A_w[k, 1] = 1.0 / sigma[i], along / half / sigma[i]
            h00 += A_w[k, 0] * A_w[k, 0]
            h01 += A_w[k, 0] * A_w[k, 1]
            h11 += A_w[k, 1] * A_w[k, 1]
        det = h00 * h11 - h01 * h01
        for k in range(lo, hi):
            gain[k, 0] = (h11 * A_w[k, 0] - h01 * A_w[k, 1]) / det
            gain[k, 1] = (h00 * A_w[k, 1] - h01 * A_w[k, 0]) / det
        q_half[g, 0], q_half[g, 1] = 1.0 / offset[e], 1.0 / turn[e]
    return order, bounds, A_w, gain, q_half


@compiled
def _whiten(values, order, bounds, A_w, gain, q_half):
    """``CorrelatedEdgeObservations.whiten`` on (M,k) values: per group and column the common
    error ĉ = gain·v, the points' values less A_w·ĉ, then Q^−½·ĉ as two rows per group."""
    m, columns = values.shape
    count = len(bounds) - 1
    out = np.empty((m + 2 * count, columns))
    out[:m] = values
    for g in range(count):
        lo, hi = bounds[g], bounds[g + 1]
        for c in range(columns):
            c0 = c1 = 0.0
            for k in range(lo, hi):
                c0 += gain[k, 0] * values[order[k], c]
                c1 += gain[k, 1] * values[order[k], c]
            for k in range(lo, hi):
                out[order[k], c] -= A_w[k, 0] * c0 + A_w[k, 1] * c1
            out[m + 2 * g, c] = q_half[g, 0] * c0
            out[m + 2 * g + 1, c] = q_half[g, 1] * c1
    return out


def _linearize_all(observations: Sequence[Observations], X_CT: Pose, K: np.ndarray):
    parts = [o.linearize(X_CT, K) for o in observations]
    return (
        np.concatenate([p[0] for p in parts]),
        np.concatenate([p[1] for p in parts]),
        np.concatenate([p[2] for p in parts]),
    )


# --- least squares ---------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, eq=False)
class PoseFit:
    """A refined pose ``X_CT`` with its 6×6 covariance over [δθ, δp] (see module docstring).

    ``chi2`` is the whitened cost at the solution, ``dof`` = residuals − 6, ``scale2`` the
    variance factor χ²/dof that multiplies (JᵀJ)⁻¹, ``rms_px`` the RMS residual in pixels.
    """

    X_CT: Pose
    covariance: np.ndarray
    chi2: float
    dof: int
    scale2: float
    rms_px: float
    iterations: int
    converged: bool
    method: str = "gauss_newton"
    unit_covariance: np.ndarray | None = None  # (JᵀJ)⁻¹: the covariance for s² = 1

    @property
    def reduced_chi2(self) -> float:
        return self.chi2 / max(self.dof, 1)


def retract(X_CT: Pose, delta: np.ndarray) -> Pose:
    """The pose moved by δ = [δθ, δp]: (Exp(δθ)·R, p + δp)."""
    moved = retract_raw(X_CT, delta)
    return Pose(moved.R, moved.p)


@dataclass(frozen=True, slots=True)
class RawPose:
    """R and p without ``Pose``'s validation, for the inner loop of the least squares (the
    result is validated once, when it becomes a ``Pose``)."""

    R: np.ndarray
    p: np.ndarray

    def apply(self, points: np.ndarray) -> np.ndarray:
        return points @ self.R.T + self.p


def retract_raw(X_CT: Pose | RawPose, delta: np.ndarray) -> RawPose:
    """``retract`` without validation: R re-orthonormalised only when rounding has drifted."""
    R = exp_so3(np.asarray(delta[:3], dtype=float)) @ X_CT.R
    if abs(float(np.linalg.det(R)) - 1.0) > 1e-9:
        R = nearest_rotation(R)
    return RawPose(R, X_CT.p + delta[3:])


@dataclass(frozen=True, slots=True, eq=False)
class PoseProblem:
    """Observations of a pose ``X_CT`` as a ``least_squares.Problem``: one group of whitened
    residuals, their analytic Jacobian w.r.t. δ = [δθ, δp] (module docstring), and the
    retraction. ``strict``: residuals that are not finite (model points behind the camera)
    raise ValueError instead of being returned (for a solver that cannot refuse a step)."""

    observations: Sequence[Observations]
    K: np.ndarray
    strict: bool = False

    @property
    def n_params(self) -> int:
        return 6

    def residuals(self, X_CT: Pose | RawPose) -> list[np.ndarray]:
        return self.linearize(X_CT)[0]

    def linearize(self, X_CT: Pose | RawPose) -> tuple[list[np.ndarray], np.ndarray]:
        _, r_w, J_w = _linearize_all(self.observations, X_CT, self.K)  # type: ignore[arg-type]
        if self.strict and not np.all(np.isfinite(r_w)):
            raise ValueError("model points behind the camera")
        return [r_w], J_w

    def retract(self, X_CT: Pose | RawPose, delta: np.ndarray) -> RawPose:
        return retract_raw(X_CT, delta)


def _fit_at(
    observations: Sequence[Observations],
    X_CT: Pose,
    K: np.ndarray,
    iterations: int,
    converged: bool,
    method: str,
    min_scale2: float,
) -> PoseFit:
    r_px, r_w, J_w = _linearize_all(observations, X_CT, K)
    chi2 = float(r_w @ r_w)
    dof = sum(o.size for o in observations) - 6
    scale2 = max(chi2 / dof, min_scale2) if dof > 0 else 1.0
    count = sum(o.count for o in observations)
    rms = float(np.sqrt(np.sum(r_px**2) / count)) if count else math.nan
    unit = covariance(J_w.T @ J_w)
    return PoseFit(
        X_CT=X_CT,
        covariance=unit * scale2,
        chi2=chi2,
        dof=dof,
        scale2=scale2,
        rms_px=rms,
        iterations=iterations,
        converged=converged,
        method=method,
        unit_covariance=unit,
    )


def refine_pose(
    observations: Sequence[Observations],
    X0_CT: Pose,
    K: np.ndarray,
    *,
    max_iterations: int = 30,
    min_scale2: float = 0.0,
    free: np.ndarray | None = None,
) -> PoseFit:
    """Levenberg–Marquardt (Gauss–Newton with damping only when a step fails) on the whitened
    reprojection residuals of ``observations`` from ``X0_CT``.

    The covariance is s²·(JᵀJ)⁻¹ at the solution with s² = max(χ²/dof, ``min_scale2``).
    ``free`` (6×k) restricts the steps to δ = free·x (e.g. keep the start's tilt: rotations
    about one axis and translations only); the covariance is then not meaningful.
    """
    total = sum(o.size for o in observations)
    if total < 6:
        raise ValueError(f"refine_pose needs at least 6 residuals; got {total}")
    try:
        solution = solve(
            PoseProblem(observations, K),
            X0_CT,
            loss=NoLoss(),
            iterations=max_iterations,
            levenberg=True,
            basis=free,
        )
    except ValueError as error:
        raise ValueError(
            "refine_pose: the start pose puts model points behind the camera"
        ) from error
    X, iteration, converged = solution.state, solution.iterations, solution.converged
    X_final = Pose(nearest_rotation(X.R), X.p)
    return _fit_at(observations, X_final, K, iteration, converged, "gauss_newton", min_scale2)


def refine_pose_robust(
    observations: PointObservations,
    X0_CT: Pose,
    K: np.ndarray,
    *,
    cauchy_scale2: float = 9.0,
    iterations: int = 12,
) -> tuple[Pose, np.ndarray]:
    """Gauss–Newton with Cauchy reweighting per point (weight 1/(1 + χ²ᵢ/c²) on each point's
    whitened χ², c² = ``cauchy_scale2``), re-weighted every step: an M-estimator that a good
    share of wrong correspondences cannot pull far from a nearby start. Returns the pose and
    each point's χ² there (for an inlier test); the covariance comes from ``refine_pose`` on
    the inliers."""
    n = len(observations.points_T)
    try:
        solution = solve(
            PoseProblem([observations], K, strict=True),
            X0_CT,
            loss=Cauchy(scale2=cauchy_scale2),
            iterations=iterations,
            tolerance=1e-3,
        )
    except ValueError as error:
        raise ValueError("refine_pose_robust: model points behind the camera") from error
    X = Pose(nearest_rotation(solution.state.R), solution.state.p)
    _, r_w, _ = observations.linearize(X, K)
    return X, np.sum(r_w.reshape(n, 2) ** 2, axis=1)


def with_min_scale2(fit: PoseFit, min_scale2: float) -> PoseFit:
    """``fit`` with its variance factor no lower than ``min_scale2`` (its covariance scaled)."""
    if fit.scale2 >= min_scale2:
        return fit
    if fit.unit_covariance is not None:
        covariance = fit.unit_covariance * min_scale2
    else:
        covariance = fit.covariance * (min_scale2 / fit.scale2)
    return replace(fit, covariance=covariance, scale2=min_scale2)


def profile_widened(
    observations: Sequence[Observations],
    fit: PoseFit,
    K: np.ndarray,
    *,
    directions: int = 2,
    level: float = 3.0,
    reach: float = 4.0,
) -> PoseFit:
    """``fit`` with its covariance widened where the χ² rises slower than the quadratic model
    its covariance stands for.

    A planar target seen nearly square-on from afar has a tilt whose χ² valley is flat and bent:
    the foreshortening is of second order in the tilt and the perspective is weak, so the
    Hessian at the minimum claims a few degrees where the data admit ten or more. Along each of
    the ``directions`` weakest rotation directions (largest variances of the rotation block),
    on both sides, the χ² at ``level`` σ is compared with its quadratic model; where they differ
    by more than 10 %, the profile χ² — the other five parameters refitted — is followed
    outward from ``level`` σ, doubling, until it reaches ``level``² (in units of the fit's
    variance factor) or ``reach``·``level`` σ. Each profile pose δ whose rise Δχ² is smaller
    than its Mahalanobis distance² m under the covariance P widens it by the rank-one
    P + βδδᵀ, β = 1/Δχ² − 1/m: the least that puts δ at its profile-likelihood distance √Δχ²
    (the likelihood-ratio interval, Wilks 1938; Y. Pawitan, *In All Likelihood*, 2001, ch. 3).
    Never narrowed."""
    P = np.asarray(fit.covariance, dtype=float)
    scale2 = max(fit.scale2, 1e-12)
    variances, axes = np.linalg.eigh(P[:3, :3])
    widened = P.copy()
    for k in range(3 - directions, 3):
        if not variances[k] > 0:
            continue
        axis, sigma = axes[:, k], math.sqrt(variances[k])
        # The whole-state direction whose rotation part is ``axis``: the translation moves
        # with it as the covariance correlates them (the profile's start).
        along = P[:, :3] @ np.linalg.solve(P[:3, :3], axis)
        free = np.zeros((6, 5))
        free[:3, :2] = np.linalg.svd(np.eye(3) - np.outer(axis, axis))[0][:, :2]
        free[3:, 2:] = np.eye(3)
        for sign in (1.0, -1.0):
            # Where the χ² at ``level`` σ along the direction is its quadratic model's to 10 %,
            # the covariance holds there and the profile need not be followed.
            _, r_w, _ = _linearize_all(
                observations, retract_raw(fit.X_CT, sign * level * sigma * along), K
            )
            if abs((float(r_w @ r_w) - fit.chi2) / scale2 - level**2) <= 0.1 * level**2:
                continue
            c = level
            while c <= reach * level:
                start = retract(fit.X_CT, sign * c * sigma * along)
                try:
                    profile = refine_pose(observations, start, K, max_iterations=10, free=free)
                except (ValueError, np.linalg.LinAlgError):
                    break  # the model behind the camera: that side is closed
                rise = max((profile.chi2 - fit.chi2) / scale2, 1.0)
                delta = pose_error_C(profile.X_CT, fit.X_CT)
                m = float(delta @ np.linalg.solve(widened, delta))
                if m > rise:
                    widened += (1.0 / rise - 1.0 / m) * np.outer(delta, delta)
                if rise >= level**2:
                    break
                c *= 2.0
    if np.array_equal(widened, P):
        return fit
    return replace(fit, covariance=0.5 * (widened + widened.T))


# --- closed-form starts ----------------------------------------------------------------------


def plane_frame(points_T: np.ndarray) -> Pose:
    """``X_TP``: a frame P whose xy plane is the least-squares plane of ``points_T`` (N≥3)."""
    points = as_points(points_T, 3, "points_T")
    centre = points.mean(axis=0)
    _, _, Vt = np.linalg.svd(points - centre)
    z = Vt[2]
    if z[2] < 0:
        z = -z
    x = Vt[0]
    y = np.cross(z, x)
    return Pose(np.column_stack([x, y, z]), centre)


def planar_flip(X_CT: Pose, points_T: np.ndarray, K: np.ndarray) -> Pose | None:
    """The other pose of the planar two-fold ambiguity of the coplanar ``points_T`` (N ≥ 4,
    e.g. the panel's corners), exactly: the IPPE pose (``ippe_poses``) that images them where
    ``X_CT`` does, when it differs from ``X_CT`` by more than a degree (near head-on the two are
    one); None otherwise. For judging the flip as it is, unrefined."""
    uv = project_ideal(X_CT, points_T, K)
    others = [
        X
        for X in ippe_poses(points_T, uv, K)
        if rotation_error_geodesic(X, X_CT) > math.radians(1.0)
    ]
    return max(others, key=lambda X: rotation_error_geodesic(X, X_CT)) if others else None


def weak_perspective_flip(X_CT: Pose, points_T: np.ndarray) -> Pose:
    """The other pose of the planar two-fold ambiguity, as a start to refine: the points'
    plane turned about its centre so that its normal is mirrored about the line of sight to the
    centre — under weak perspective both normals project the plane alike (D. Oberkampf,
    D. DeMenthon and L. Davis, "Iterative pose estimation using coplanar feature points", CVIU
    63(3), 1996; G. Schweighofer and A. Pinz, "Robust pose estimation from a planar target",
    PAMI 28(12), 2006). Cheaper than ``planar_flip``, and it keeps the points' offsets from their
    plane (a disc on the ring, a head's height), which IPPE ignores."""
    X_TP = plane_frame(points_T)
    centre_C = X_CT.apply(X_TP.p)
    normal_C = X_CT.R @ X_TP.R[:, 2]
    sight = centre_C / np.linalg.norm(centre_C)
    mirrored = 2.0 * float(normal_C @ sight) * sight - normal_C
    R = rotation_between(normal_C, mirrored) @ X_CT.R
    return Pose(R, centre_C - R @ X_TP.p)


def ippe_poses(points_T: np.ndarray, uv_ideal: np.ndarray, K: np.ndarray) -> list[Pose]:
    """Both poses of the planar two-fold ambiguity (IPPE, Collins & Bartoli 2014) from N ≥ 4
    points near a plane; off-plane offsets are ignored (use the result as a start)."""
    points = as_points(points_T, 3, "points_T")
    uv = as_points(uv_ideal, 2, "uv_ideal")
    if len(points) < 4 or len(points) != len(uv):
        raise ValueError(f"ippe_poses needs ≥ 4 matched points; got {len(points)} and {len(uv)}")
    X_TP = plane_frame(points)
    flat = X_TP.inverse().apply(points)
    flat[:, 2] = 0.0
    try:
        count, rvecs, tvecs, _ = cv2.solvePnPGeneric(
            flat.reshape(-1, 1, 3),
            uv.reshape(-1, 1, 2),
            np.asarray(K, dtype=float),
            None,
            flags=cv2.SOLVEPNP_IPPE,
        )
    except cv2.error:
        return []
    poses = []
    for rvec, tvec in zip(rvecs[:count], tvecs[:count], strict=True):
        rvec, tvec = np.asarray(rvec).reshape(3), np.asarray(tvec).reshape(3)
        if np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec)):
            poses.append(Pose.from_rotvec(rvec, tvec) @ X_TP.inverse())
    return poses


# --- orthogonal iteration ---------------------------------------------------------------------


def _absolute_orientation(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """R minimising Σ|R·(p_i − p̄) − (q_i − q̄)|² (Horn/Arun, SVD)."""
    M = (q - q.mean(axis=0)).T @ (p - p.mean(axis=0))
    return nearest_rotation(M)


def orthogonal_iteration(
    points_T: np.ndarray,
    xy_normalized: np.ndarray,
    R0_CT: np.ndarray,
    *,
    max_iterations: int = 200,
    tolerance: float = 1e-12,
) -> tuple[Pose, int]:
    """Lu–Hager–Mjolsness orthogonal iteration from rotation ``R0_CT``.

    Minimises the object-space error Σ‖(I − V_i)(R·p_i + t)‖² with V_i = v_i v_iᵀ / v_iᵀv_i the
    projector onto the line of sight v_i = (x_i, y_i, 1). Returns (X_CT, iterations).
    """
    p = as_points(points_T, 3, "points_T")
    xy = as_points(xy_normalized, 2, "xy_normalized")
    n = len(p)
    v = np.column_stack([xy, np.ones(n)])
    V = np.einsum("ni,nj->nij", v, v) / np.einsum("ni,ni->n", v, v)[:, None, None]
    I3 = np.eye(3)
    # t(R) = (1/n)(I − (1/n)ΣV_i)⁻¹ Σ(V_i − I)·R·p_i
    F = np.linalg.inv(I3 - V.mean(axis=0)) / n
    VmI = V - I3

    def translation(R: np.ndarray) -> np.ndarray:
        return F @ np.einsum("nij,nj->i", VmI, p @ R.T)

    def error(R: np.ndarray, t: np.ndarray) -> float:
        e = np.einsum("nij,nj->ni", VmI, p @ R.T + t)
        return float(np.sum(e * e))

    R = nearest_rotation(R0_CT)
    t = translation(R)
    previous = error(R, t)
    iteration = 0
    for iteration in range(1, max_iterations + 1):  # noqa: B007
        q = np.einsum("nij,nj->ni", V, p @ R.T + t)
        R = _absolute_orientation(p, q)
        t = translation(R)
        current = error(R, t)
        if abs(previous - current) <= tolerance * max(previous, 1e-30):
            break
        previous = current
    return Pose(R, t), iteration


def lhm_fit(
    observations: PointObservations, X0_CT: Pose, K: np.ndarray, *, min_scale2: float = 0.0
) -> PoseFit:
    """Orthogonal iteration on point observations from ``X0_CT``'s rotation; covariance and
    residuals from the image-space linearisation at its solution (same convention as
    ``refine_pose``)."""
    K = np.asarray(K, dtype=float)
    y = (observations.uv[:, 1] - K[1, 2]) / K[1, 1]
    x = (observations.uv[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
    X, iterations = orthogonal_iteration(observations.points_T, np.column_stack([x, y]), X0_CT.R)
    if np.any(X.apply(observations.points_T)[:, 2] <= 0):
        raise ValueError("orthogonal iteration ended with model points behind the camera")
    return _fit_at([observations], X, K, iterations, True, "lhm", min_scale2)


# --- choosing among local minima -------------------------------------------------------------


@dataclass(frozen=True, slots=True, eq=False)
class PoseChoice:
    """The chosen fit, the best distinct alternative (or None), and how the choice was made:
    ``residual`` (decisively lower χ²), ``prior`` (closer to the prior when χ² did not decide),
    ``lower_residual`` (no prior; lower χ² but not decisively) or ``only``.
    ``ambiguous`` is set when the residuals did not decide between distinct poses."""

    fit: PoseFit
    alternative: PoseFit | None
    decided_by: str

    @property
    def ambiguous(self) -> bool:
        return self.decided_by in ("prior", "lower_residual")


#: Floor of the variance factor when judging minima: noise-free data (χ² → 0) must not make
#: two numerically equal solutions look distinct.
_MIN_SCALE2 = 0.25


def _distinct(a: PoseFit, b: PoseFit, mahalanobis2: float) -> bool:
    delta = pose_error_C(b.X_CT, a.X_CT)
    unit = (
        a.unit_covariance if a.unit_covariance is not None else a.covariance / max(a.scale2, 1e-300)
    )
    covariance = unit * max(a.scale2, _MIN_SCALE2)
    try:
        d2 = float(delta @ np.linalg.solve(covariance, delta))
    except np.linalg.LinAlgError:
        d2 = math.inf
    return d2 > mahalanobis2


def choose_pose(
    fits: Sequence[PoseFit],
    prior_X_CT: Pose | None = None,
    *,
    decisive_chi2: float = 9.0,
    same_mahalanobis2: float = 25.0,
) -> PoseChoice:
    """Resolve among local minima (e.g. the planar two-fold ambiguity).

    A fit whose χ² is lower than every distinct alternative's by ``decisive_chi2`` (in units
    of the best fit's variance factor) wins outright. Otherwise the prior decides (the fit
    closest to it in rotation), or without a prior the lower χ² — and the choice is marked
    ambiguous. Fits within ``same_mahalanobis2`` of the best (under its covariance) count as
    the same solution.
    """
    if not fits:
        raise ValueError("choose_pose needs at least one fit")
    ordered = sorted(fits, key=lambda f: f.chi2)
    best = ordered[0]
    distinct = [f for f in ordered[1:] if _distinct(best, f, same_mahalanobis2)]
    if not distinct:
        return PoseChoice(best, None, "only")
    runner_up = distinct[0]
    scale2 = max(best.scale2, _MIN_SCALE2)
    if (runner_up.chi2 - best.chi2) / scale2 >= decisive_chi2:
        return PoseChoice(best, runner_up, "residual")
    contenders = [best, *[f for f in distinct if (f.chi2 - best.chi2) / scale2 < decisive_chi2]]
    if prior_X_CT is not None:
        chosen = min(contenders, key=lambda f: rotation_error_geodesic(prior_X_CT, f.X_CT))
        other = next(f for f in contenders if f is not chosen)
        return PoseChoice(chosen, other, "prior")
    return PoseChoice(best, runner_up, "lower_residual")


def against_flip(
    choice: PoseChoice,
    observations: PointObservations,
    K: np.ndarray,
    prior_X_CT: Pose,
    *,
    method: PoseMethod = "gauss_newton",
    same_mahalanobis2: float = 25.0,
) -> PoseChoice:
    """``choice``, a fit from the prior alone, weighed against the planar flip of its points.

    A track that starts on the wrong flip of a small or distant plate stays in that minimum: a
    fit from the prior never sees the other one. The flip of the fit
    (``weak_perspective_flip``) is refined, and ``choose_pose`` decides with the prior: by the
    residuals, or by the prior, which the answer must then say (``decided_by == "prior"``) so
    that a prior that had not decided the flip either is not taken for evidence. (The start is
    refined even when it lies within the fit's own covariance: a wide one may hold both minima
    of a bent valley.)"""
    flipped = weak_perspective_flip(choice.fit.X_CT, observations.points_T)
    fits = fit_from_starts([observations], [flipped], K, method=method)
    return choose_pose([choice.fit, *fits], prior_X_CT, same_mahalanobis2=same_mahalanobis2)


def fit_from_starts(
    observations: Sequence[Observations],
    starts: Sequence[Pose],
    K: np.ndarray,
    *,
    method: PoseMethod = "gauss_newton",
    lhm_points: PointObservations | None = None,
    min_scale2: float = 0.0,
) -> list[PoseFit]:
    """Refine every start with ``method``; starts that fail (points behind the camera, no
    convergence to a finite cost) are dropped. ``lhm`` needs ``lhm_points`` (the point
    observations it iterates on); its covariance is then evaluated on ``observations``."""
    if method not in POSE_METHODS:
        raise ValueError(f"pose method must be one of {', '.join(POSE_METHODS)}; got {method!r}")
    fits = []
    for X0 in starts:
        try:
            if method == "gauss_newton":
                fits.append(refine_pose(observations, X0, K, min_scale2=min_scale2))
            else:
                points = lhm_points if lhm_points is not None else observations[0]
                if not isinstance(points, PointObservations):
                    raise ValueError("the lhm pose method needs point observations")
                solved = lhm_fit(points, X0, K, min_scale2=min_scale2)
                fits.append(
                    _fit_at(
                        observations, solved.X_CT, K, solved.iterations, True, "lhm", min_scale2
                    )
                )
        except (ValueError, np.linalg.LinAlgError):
            continue
    return fits
