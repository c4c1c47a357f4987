"""Pose of known 3-D circles by robust least squares on their image edge points.

The cost is the sum of squared geometric (Sampson) distances of observed edge points to the
image conics of the model circles (``conics.circle_image_conic``), minimised by Gauss–Newton
with Huber weights (iteratively reweighted least squares) — the geometric refinement of
Kanatani ("Statistical optimization for geometric computation", 1996) applied to the pose
instead of the conic, so that every circle constrains the same few parameters. Each edge set
carries its own noise scale (estimated from its residuals), and the covariance is the inverse
of the weighted normal matrix at the last linearisation (the Gauss–Newton / Cramér–Rao
approximation). The loop is ``least_squares.solve`` with its ``Huber`` loss;
``ConicObservations`` gives the residuals and their analytic Jacobian.

Two parametrisations, matching ``estimators.measurement`` (``CircleProblem``, ``TargetProblem``):

* 5-DOF (circles coaxial with a reference circle, e.g. the ring's two edges): centre c and unit
  normal n of the reference circle; update c ← c + δc, n ← normalise(n + α·u + β·v) with
  (u, v) = ``circle_plane_basis(n)``.
* 6-DOF (any circles of the target): ``X_CT`` with R ← Exp(δθ)·R, p ← p + δp (rotation
  perturbed on the left, translation added).

An edge set may have a free radius (a nuisance parameter, metres): its circle then contributes
its position and shape but not its size — for circles whose apparent size is biased (a thin
lip blurred into its neighbour, an edge whose exact radius is uncertain).

The 6-DOF fit may also take labeled points with 2×2 covariances (``PointObservations``, e.g.
small holes on the ring fitted as discs): their whitened reprojection errors join the cost as
one more group, whose noise scale is at least 1 (the covariances are trusted as a floor). Edge
samples that share pixels through the smoothing are not independent: ``edge_weight`` (< 1)
scales their information so that they and the points are weighted by what they really hold.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from estimators.circle_pose import CirclePose
from estimators.compiled import compiled
from estimators.conics import circle_plane_basis
from estimators.geometry import Pose, as_points
from estimators.least_squares import Huber, Solution, covariance, solve
from estimators.planar_pose import PointObservations, retract_raw
from estimators.target import Circle3D


@dataclass(frozen=True, slots=True, eq=False)
class EdgeSet:
    """Edge points (N,2) in ideal-pinhole pixels (distortion removed) on one model circle."""

    circle: Circle3D
    uv: np.ndarray
    free_radius: bool = False

    def __post_init__(self) -> None:
        uv = as_points(self.uv, 2, f"EdgeSet({self.circle.name}).uv").copy()
        uv.flags.writeable = False
        object.__setattr__(self, "uv", uv)


@dataclass(frozen=True, slots=True, eq=False)
class FitResult:
    """A converged fit. ``pose`` is a ``CirclePose`` (5-DOF) or ``Pose`` X_CT (6-DOF);
    ``covariance`` is 5×5 or 6×6 in the conventions of ``estimators.measurement`` (nuisance
    radii marginalised out); ``residuals`` and ``inliers`` are per edge set (px, bool);
    ``sigma_px`` the per-set noise scales; ``radius_offsets`` the fitted nuisance radii (m);
    ``point_residuals`` the whitened residuals (2N,) of the points and ``point_sigma`` their
    noise scale (NaN without points); ``edge_weight`` the information scale of edge samples."""

    pose: CirclePose | Pose
    covariance: np.ndarray
    residuals: tuple[np.ndarray, ...]
    inliers: tuple[np.ndarray, ...]
    sigma_px: tuple[float, ...]
    radius_offsets: tuple[float, ...]
    iterations: int
    point_residuals: np.ndarray = field(default_factory=lambda: np.zeros(0))
    point_sigma: float = float("nan")
    edge_weight: float = 1.0

    @property
    def rms_px(self) -> float:
        """RMS residual over the inliers of all sets."""
        r = np.concatenate([res[ok] for res, ok in zip(self.residuals, self.inliers, strict=True)])
        return float(np.sqrt(np.mean(r**2))) if len(r) else float("nan")

    @property
    def inlier_count(self) -> int:
        return int(sum(ok.sum() for ok in self.inliers))


def _finish(
    pose,
    solution: Solution,
    n_pose: int,
    offsets: np.ndarray,
    *,
    with_points: bool = False,
    edge_weight: float = 1.0,
) -> FitResult:
    r, sigmas = solution.residuals, solution.sigmas
    points, point_sigma = np.zeros(0), float("nan")
    if with_points:
        points, point_sigma = r[-1], sigmas[-1]
        r, sigmas = r[:-1], sigmas[:-1]
    return FitResult(
        pose=pose,
        covariance=covariance(solution.information, keep=n_pose),
        residuals=r,
        inliers=tuple(np.abs(ri) <= 3.0 * s for ri, s in zip(r, sigmas, strict=True)),
        sigma_px=sigmas,
        radius_offsets=tuple(float(o) for o in offsets),
        iterations=solution.iterations,
        point_residuals=points,
        point_sigma=point_sigma,
        edge_weight=edge_weight,
    )


# --- the conic observation -------------------------------------------------------------------


@dataclass(frozen=True, slots=True, eq=False)
class ConicObservations:
    """Edge sets against the image conics of their circles: residuals and their analytic
    Jacobian w.r.t. the circles' geometry.

    A circle (centre c, unit normal n, radius ρ, in C) is the base of the cone of rays x with
    xᵀ·A·x = 0, A = a·n nᵀ − s·(c nᵀ + n cᵀ) + s²·I, a = c·c − ρ², s = n·c
    (``conics.circle_cone``); its image conic is Q = K⁻ᵀ·A·K⁻¹. An edge point h = (u, v, 1),
    x = K⁻¹·h, has the Sampson distance r = f/g with f = hᵀQh = xᵀAx and
    g = 2‖(Qh)₁,₂‖ = 2‖(K⁻ᵀ·A·x)₁,₂‖ (Kanatani 1996). Differentiating,
    ∂r = (xᵀA'x)/g − (f/g²)·4·((Qh)₁(K⁻ᵀA'x)₁ + (Qh)₂(K⁻ᵀA'x)₂)/g with
    A' = M + Mᵀ + a'·n nᵀ + 2 s s'·I, M = (a·n' − s·c')·nᵀ − s·c n'ᵀ − s'·c nᵀ,
    a' = 2 c·c' − 2ρρ', s' = n'·c + n·c' (n' ⊥ n keeps n a unit vector). The
    parametrisations (``CircleProblem``, ``TargetProblem``) supply c', n' and ρ' for each
    parameter. The points of all sets are kept in one array, each set a contiguous slice.
    """

    edge_sets: tuple[EdgeSet, ...]
    K: np.ndarray
    _x: np.ndarray = field(default=None, repr=False)  # type: ignore[assignment]
    _ends: np.ndarray = field(default=None, repr=False)  # type: ignore[assignment]
    _K_inv_T2: np.ndarray = field(default=None, repr=False)  # type: ignore[assignment]
    _model: tuple = field(default=(), repr=False)

    def __post_init__(self) -> None:
        sets = tuple(self.edge_sets)
        object.__setattr__(
            self,
            "_model",
            (
                np.array([s.circle.center_T for s in sets], dtype=float).reshape(-1, 3),
                np.array([s.circle.normal_T for s in sets], dtype=float).reshape(-1, 3),
                np.array([s.circle.radius for s in sets], dtype=float),
                [i for i, s in enumerate(sets) if s.free_radius],
            ),
        )
        K_inv = np.linalg.inv(np.asarray(self.K, dtype=float))
        uv = np.concatenate([s.uv for s in sets]) if sets else np.zeros((0, 2))
        x = np.column_stack([uv, np.ones(len(uv))]) @ K_inv.T  # rays K⁻¹·h (N,3)
        ends = np.cumsum([0] + [len(s.uv) for s in sets])
        object.__setattr__(self, "edge_sets", sets)
        object.__setattr__(self, "_x", np.ascontiguousarray(x))
        object.__setattr__(self, "_ends", np.asarray(ends, dtype=np.int64))
        object.__setattr__(self, "_K_inv_T2", np.ascontiguousarray(K_inv.T[:2]))

    @property
    def sizes(self) -> tuple[int, ...]:
        return tuple(len(s.uv) for s in self.edge_sets)

    @property
    def circles_T(self) -> tuple[np.ndarray, np.ndarray]:
        """The model circles' centres and normals (S,3) in T."""
        return self._model[0], self._model[1]

    @property
    def free_count(self) -> int:
        """How many sets have a free (nuisance) radius."""
        return len(self._model[3])

    def offsets(self, radius_offsets=None) -> np.ndarray:
        """The nuisance radii (m) as an array (zeros when not given)."""
        if radius_offsets is None:
            return np.zeros(self.free_count)
        return np.array(radius_offsets, dtype=float).reshape(self.free_count)

    def radii(self, offsets: np.ndarray) -> np.ndarray:
        """The circles' radii (S,) with the nuisance ``offsets`` added to the free ones."""
        radii = self._model[2].copy()
        radii[self._model[3]] += offsets
        return radii

    def radius_jacobian(self, n_params: int, first: int) -> np.ndarray:
        """∂ρ/∂δ (P,S) for nuisance radii at parameters ``first``, ``first`` + 1, …"""
        d = np.zeros((n_params, len(self.edge_sets)))
        d[first + np.arange(self.free_count), self._model[3]] = 1.0
        return d

    def _split(self, values: np.ndarray) -> list[np.ndarray]:
        return [values[a:b] for a, b in zip(self._ends[:-1], self._ends[1:], strict=True)]

    def residuals(
        self, centers: np.ndarray, normals: np.ndarray, radii: np.ndarray
    ) -> list[np.ndarray]:
        """Sampson distances (px) of each set's points to its circle's image conic."""
        if not self.edge_sets:
            return []
        no_parameters = np.zeros((0, len(radii), 3))  # distances only, no Jacobian
        r, _ = _sampson_distances(
            self._x, self._ends, self._K_inv_T2, *_as_float(centers, normals, radii),
            no_parameters, no_parameters, np.zeros((0, len(radii))),
        )  # fmt: skip
        return self._split(r)

    def linearize(
        self,
        centers: np.ndarray,
        normals: np.ndarray,
        radii: np.ndarray,
        d_centers: np.ndarray,
        d_normals: np.ndarray,
        d_radii: np.ndarray,
    ) -> tuple[list[np.ndarray], np.ndarray]:
        """Residual groups and their Jacobian (N_total, P), given the derivatives of the
        circles' centres (P,S,3), normals (P,S,3) and radii (P,S) w.r.t. P parameters."""
        P = d_radii.shape[0]
        if not self.edge_sets:
            return [], np.zeros((0, P))
        r, J = _sampson_distances(
            self._x, self._ends, self._K_inv_T2, *_as_float(centers, normals, radii),
            *_as_float(d_centers, d_normals, d_radii),
        )  # fmt: skip
        return self._split(r), J


def _as_float(*arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    return tuple(np.ascontiguousarray(a, dtype=float) for a in arrays)


@compiled
def _sampson_distances(x, ends, K_inv_T2, c, n, rho, d_centers, d_normals, d_radii):
    """Sampson distances r = f/g (N,) of rays ``x`` (N,3; set k is rows ``ends[k]`` to
    ``ends[k + 1]``) to the cones of circles (centres ``c``, normals ``n``, radii ``rho``)
    and their Jacobian (N,P) from the circles' derivatives (P,S,3), (P,S,3), (P,S) — the
    formulas of the class docstring, compiled: as NumPy they were dozens of calls on (P,S,3,3)
    arrays for every linearisation of every fit."""
    P = d_radii.shape[0]
    N = len(x)
    r = np.empty(N)
    J = np.empty((N, P))
    A = np.empty((3, 3))
    B = np.empty((2, 3))
    M = np.empty((3, 3))
    dA = np.empty((P, 3, 3))
    dB = np.empty((P, 2, 3))
    for k in range(len(rho)):
        a = c[k, 0] * c[k, 0] + c[k, 1] * c[k, 1] + c[k, 2] * c[k, 2] - rho[k] * rho[k]
        s = n[k, 0] * c[k, 0] + n[k, 1] * c[k, 1] + n[k, 2] * c[k, 2]
        # The cone A = M + Mᵀ + s²·I with M = (a/2·n − s·c)·nᵀ.
        for i in range(3):
            for j in range(3):
                M[i, j] = (0.5 * a * n[k, i] - s * c[k, i]) * n[k, j]
        for i in range(3):
            for j in range(3):
                A[i, j] = M[i, j] + M[j, i] + (s * s if i == j else 0.0)
        for i in range(2):
            for j in range(3):
                B[i, j] = (
                    K_inv_T2[i, 0] * A[0, j] + K_inv_T2[i, 1] * A[1, j] + K_inv_T2[i, 2] * A[2, j]
                )
        for p in range(P):
            dc, dn = d_centers[p, k], d_normals[p, k]
            da = (
                2.0 * (dc[0] * c[k, 0] + dc[1] * c[k, 1] + dc[2] * c[k, 2])
                - 2.0 * rho[k] * d_radii[p, k]
            )
            ds = dn[0] * c[k, 0] + dn[1] * c[k, 1] + dn[2] * c[k, 2]
            ds += n[k, 0] * dc[0] + n[k, 1] * dc[1] + n[k, 2] * dc[2]
            for i in range(3):
                for j in range(3):
                    M[i, j] = (a * dn[i] - s * dc[i] - ds * c[k, i]) * n[k, j] - s * c[k, i] * dn[j]
            for i in range(3):
                for j in range(3):
                    dA[p, i, j] = M[i, j] + M[j, i] + da * n[k, i] * n[k, j]
                dA[p, i, i] += 2.0 * s * ds
            for i in range(2):
                for j in range(3):
                    dB[p, i, j] = (
                        K_inv_T2[i, 0] * dA[p, 0, j]
                        + K_inv_T2[i, 1] * dA[p, 1, j]
                        + K_inv_T2[i, 2] * dA[p, 2, j]
                    )
        for m in range(ends[k], ends[k + 1]):
            x0, x1, x2 = x[m, 0], x[m, 1], x[m, 2]
            f = 0.0
            for i in range(3):
                f += x[m, i] * (A[i, 0] * x0 + A[i, 1] * x1 + A[i, 2] * x2)
            q0 = B[0, 0] * x0 + B[0, 1] * x1 + B[0, 2] * x2
            q1 = B[1, 0] * x0 + B[1, 1] * x1 + B[1, 2] * x2
            g = max(2.0 * math.hypot(q0, q1), 1e-300)
            r[m] = f / g
            for p in range(P):
                df = 0.0
                for i in range(3):
                    df += x[m, i] * (dA[p, i, 0] * x0 + dA[p, i, 1] * x1 + dA[p, i, 2] * x2)
                dq0 = dB[p, 0, 0] * x0 + dB[p, 0, 1] * x1 + dB[p, 0, 2] * x2
                dq1 = dB[p, 1, 0] * x0 + dB[p, 1, 1] * x1 + dB[p, 1, 2] * x2
                dg = 4.0 * (q0 * dq0 + q1 * dq1) / g
                J[m, p] = df / g - f / (g * g) * dg
    return r, J


# --- the 5-DOF circle ------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, eq=False)
class CircleState:
    """Centre c (m, C), unit normal n, the tangent basis (u, v) of n, nuisance radii (m)."""

    c: np.ndarray
    n: np.ndarray
    basis: np.ndarray
    dr: np.ndarray


def _circle_state(center, normal, radius_offsets: np.ndarray) -> CircleState:
    """The 5-DOF state at a centre and normal, the normal turned to the camera side (so a fit
    stays there)."""
    c = np.asarray(center, dtype=float).copy()
    n = np.asarray(normal, dtype=float)
    n = n / np.linalg.norm(n)
    if n @ c > 0:
        n = -n
    return CircleState(c, n, np.array(circle_plane_basis(n)), radius_offsets)


def _retract_circle(state: CircleState, delta: np.ndarray) -> CircleState:
    """``state`` moved by an increment [δc, α, β, δr…]: the normal turned within its tangent
    basis."""
    n = state.n + delta[3:5] @ state.basis
    n = n / np.linalg.norm(n)
    return CircleState(
        state.c + delta[:3], n, np.array(circle_plane_basis(n)), state.dr + delta[5:]
    )


def _coaxial_heights(edge_sets: Sequence[EdgeSet], reference: Circle3D) -> np.ndarray:
    heights = []
    for s in edge_sets:
        offset = s.circle.center_T - reference.center_T
        height = float(offset @ reference.normal_T)
        lateral = offset - height * reference.normal_T
        if np.linalg.norm(lateral) > 1e-9 or abs(s.circle.normal_T @ reference.normal_T) < 1 - 1e-9:
            raise ValueError(
                f"circle {s.circle.name!r} is not coaxial with {reference.name!r}; "
                "use the 6-DOF fit"
            )
        heights.append(height)
    return np.array(heights)


@dataclass(frozen=True, slots=True, eq=False)
class CircleProblem:
    """Edge sets on circles coaxial with ``reference``, as a ``least_squares.Problem`` over
    [δc, α, β, δρ_free…] (c ← c + δc, n ← normalise(n + α·u + β·v), ρ ← ρ + δρ)."""

    observations: ConicObservations
    reference: Circle3D
    _heights: np.ndarray = field(default=None, repr=False)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        heights = _coaxial_heights(self.observations.edge_sets, self.reference)
        object.__setattr__(self, "_heights", heights)

    @property
    def n_params(self) -> int:
        return 5 + self.observations.free_count

    def state(self, center, normal, radius_offsets=None) -> CircleState:
        """The state at a centre and normal (``_circle_state``)."""
        return _circle_state(center, normal, self.observations.offsets(radius_offsets))

    def _geometry(self, state: CircleState):
        radii = self.observations.radii(state.dr)
        centers = state.c + self._heights[:, None] * state.n
        return centers, np.broadcast_to(state.n, centers.shape), radii

    def residuals(self, state: CircleState) -> list[np.ndarray]:
        return self.observations.residuals(*self._geometry(state))

    def linearize(self, state: CircleState) -> tuple[list[np.ndarray], np.ndarray]:
        S, P = len(self._heights), self.n_params
        dN = np.zeros((P, S, 3))
        dN[3:5] = state.basis[:, None, :]
        dC = self._heights[None, :, None] * dN
        dC[0:3] = np.eye(3)[:, None, :]
        return self.observations.linearize(
            *self._geometry(state), dC, dN, self.observations.radius_jacobian(P, 5)
        )

    def retract(self, state: CircleState, delta: np.ndarray) -> CircleState:
        return _retract_circle(state, delta)


def fit_circle_pose(
    edge_sets: Sequence[EdgeSet],
    initial: CirclePose,
    reference: Circle3D,
    K: np.ndarray,
    *,
    iterations: int = 6,
) -> FitResult:
    """5-DOF pose (centre, normal) of ``reference`` from edge sets on circles coaxial with it.

    ValueError if a circle is not coaxial (its centre off the reference axis or its normal not
    parallel) — such circles need the 6-DOF ``fit_target_pose``.
    """
    problem = CircleProblem(ConicObservations(tuple(edge_sets), K), reference)
    solution = solve(
        problem,
        problem.state(initial.center_C, initial.normal_C),
        loss=Huber(),
        iterations=iterations,
    )
    state = solution.state
    return _finish(CirclePose(state.c, state.n), solution, 5, state.dr)


# --- the 6-DOF target ------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, eq=False)
class TargetState:
    """``X_CT`` as (R, p) and the nuisance radii (m)."""

    R: np.ndarray
    p: np.ndarray
    dr: np.ndarray


def _axes_cross(v: np.ndarray) -> np.ndarray:
    """e_j × v_s (3,S,3) for the unit axes e_j and vectors v (S,3) (np.cross is slow here)."""
    out = np.zeros((3, len(v), 3))
    out[0, :, 1], out[0, :, 2] = -v[:, 2], v[:, 1]
    out[1, :, 0], out[1, :, 2] = v[:, 2], -v[:, 0]
    out[2, :, 0], out[2, :, 1] = -v[:, 1], v[:, 0]
    return out


@dataclass(frozen=True, slots=True, eq=False)
class TargetProblem:
    """Edge sets on any circles of the target (and labeled points, whose whitened
    reprojection errors are one more residual group), as a ``least_squares.Problem`` over
    [δθ, δp, δρ_free…] (R ← Exp(δθ)·R, p ← p + δp, ρ ← ρ + δρ)."""

    observations: ConicObservations
    points: PointObservations | None = None

    @property
    def n_params(self) -> int:
        return 6 + self.observations.free_count

    def state(self, X_CT: Pose, radius_offsets=None) -> TargetState:
        dr = self.observations.offsets(radius_offsets)
        return TargetState(np.array(X_CT.R, dtype=float), np.array(X_CT.p, dtype=float), dr)

    def _geometry(self, state: TargetState):
        centers_T, normals_T = self.observations.circles_T
        # R·c_T and R·n_T (S,3)
        return centers_T @ state.R.T, normals_T @ state.R.T, self.observations.radii(state.dr)

    def _point_group(self, state: TargetState, jacobian: bool):
        if self.points is None:
            return [], None
        _, r_w, J_w = self.points.linearize(state, self.observations.K)  # type: ignore[arg-type]
        if not jacobian:
            return [r_w], None
        padded = np.zeros((len(J_w), self.n_params))
        padded[:, :6] = J_w
        return [r_w], padded

    def residuals(self, state: TargetState) -> list[np.ndarray]:
        q, m, radii = self._geometry(state)
        edges = self.observations.residuals(q + state.p, m, radii)
        return edges + self._point_group(state, False)[0]

    def linearize(self, state: TargetState) -> tuple[list[np.ndarray], np.ndarray]:
        q, m, radii = self._geometry(state)
        S, P = len(q), self.n_params
        dC = np.zeros((P, S, 3))
        dN = np.zeros((P, S, 3))
        dC[0:3] = _axes_cross(q)  # e_j × R·c_T
        dN[0:3] = _axes_cross(m)  # e_j × R·n_T
        dC[3:6] = np.eye(3)[:, None, :]
        groups, J = self.observations.linearize(
            q + state.p, m, radii, dC, dN, self.observations.radius_jacobian(P, 6)
        )
        point_groups, J_points = self._point_group(state, True)
        if J_points is not None:
            J = np.vstack([J, J_points])
        return groups + point_groups, J

    def retract(self, state: TargetState, delta: np.ndarray) -> TargetState:
        X_CT = retract_raw(state, delta[:6])
        return TargetState(X_CT.R, X_CT.p, state.dr + delta[6:])


def _group_settings(n_sets: int, points, edge_weight: float) -> Huber:
    """The Huber loss for edge sets followed by the points' group: edge sets with information
    scale ``edge_weight`` and noise floor 0.05 px, points with weight 1 and floor 1."""
    weights = [edge_weight] * n_sets
    floors = [0.05] * n_sets
    if points is not None:
        weights.append(1.0)
        floors.append(1.0)
    return Huber(floors=tuple(floors), group_weights=tuple(weights))


def fit_target_pose(
    edge_sets: Sequence[EdgeSet],
    initial: Pose,
    K: np.ndarray,
    *,
    iterations: int = 6,
    points: PointObservations | None = None,
    edge_weight: float = 1.0,
) -> FitResult:
    """6-DOF pose ``X_CT`` from edge sets on any circles of the target (and labeled points,
    when given; see the module docstring for ``edge_weight``)."""
    if points is not None and not points.count:
        points = None
    problem = TargetProblem(ConicObservations(tuple(edge_sets), K), points)
    solution = solve(
        problem,
        problem.state(initial),
        loss=_group_settings(len(edge_sets), points, edge_weight),
        iterations=iterations,
    )
    state = solution.state
    return _finish(
        Pose(state.R, state.p),
        solution,
        6,
        state.dr,
        with_points=points is not None,
        edge_weight=edge_weight,
    )


def covariance_at(
    edge_sets: Sequence[EdgeSet],
    fit: FitResult,
    pose: CirclePose | Pose,
    K: np.ndarray,
    *,
    reference: Circle3D | None = None,
    points: PointObservations | None = None,
) -> np.ndarray:
    """The covariance of a fit (its noise scales, nuisance radii, edge weight and points)
    linearised at another ``pose`` — a ``CirclePose`` (5-DOF, with ``reference``) or a
    ``Pose`` (6-DOF, the only one that takes ``points``).

    Used where the linearisation at the solution is over-confident: near a head-on view a
    circle's tilt enters its image only quadratically, so at a slightly tilted estimate the
    tangent says the tilt is well known while the cost is nearly flat back to head-on; the
    covariance at the head-on pose does not make that mistake.
    """
    J, w, keep = _weighted_jacobian(edge_sets, fit, pose, K, reference, points)
    return covariance(J.T @ (J * w[:, None]), keep=keep)


def pose_response(
    edge_sets: Sequence[EdgeSet],
    fit: FitResult,
    pose: CirclePose | Pose,
    K: np.ndarray,
    *,
    reference: Circle3D | None = None,
    points: PointObservations | None = None,
) -> np.ndarray:
    """The fit's linear response at ``pose``: how far its pose parameters (5 or 6, as
    ``covariance_at``'s) move when the residuals move by b (px) is this matrix times b,
    −(JᵀWJ)⁻¹JᵀW·b with the nuisance radii refitted; (5 or 6) × (residuals), edge samples in
    set order then the points' residuals (``stacked_displacements`` builds b).

    A systematic error of known shape and unknown size — an unmodelled feature that can pull
    the edges by up to b — enters the covariance as shift·shiftᵀ times its size's second
    moment: a "consider" parameter (Schmidt; Tapley, Schutz & Born, *Statistical Orbit
    Determination*, 2004, §6.3), estimated by no one and accounted for.
    """
    J, w, keep = _weighted_jacobian(edge_sets, fit, pose, K, reference, points)
    information = J.T @ (J * w[:, None])
    return -np.linalg.solve(information, (J * w[:, None]).T)[:keep]


def stacked_displacements(response: np.ndarray, displacements: Sequence[np.ndarray]) -> np.ndarray:
    """Per-set displacements (px) as one vector for ``response``, the points' residuals
    (after the edge samples) unmoved."""
    b = np.concatenate([np.asarray(d, dtype=float) for d in displacements])
    size = response.shape[1]
    if len(b) > size:
        raise ValueError(f"{len(b)} displacements for {size} residuals")
    return np.concatenate([b, np.zeros(size - len(b))])


def moved(pose: CirclePose | Pose, delta: np.ndarray) -> CirclePose | Pose:
    """``pose`` moved by an increment of the fit's parameters (``covariance_at``'s: 5-DOF
    [δc, α, β], 6-DOF [δθ, δp]), by the retractions the fits use."""
    delta = np.asarray(delta, dtype=float)
    if isinstance(pose, Pose):
        raw = retract_raw(pose, delta[:6])
        return Pose(raw.R, raw.p)
    state = _retract_circle(_circle_state(pose.center_C, pose.normal_C, np.zeros(0)), delta[:5])
    return CirclePose(state.c, state.n)


def _weighted_jacobian(
    edge_sets: Sequence[EdgeSet],
    fit: FitResult,
    pose: CirclePose | Pose,
    K: np.ndarray,
    reference: Circle3D | None,
    points: PointObservations | None,
) -> tuple[np.ndarray, np.ndarray, int]:
    """The fit's residual Jacobian at ``pose``, the residuals' weights (edge sets first, then
    the points) and the number of pose parameters."""
    observations = ConicObservations(tuple(edge_sets), K)
    if points is not None and not points.count:
        points = None
    if isinstance(pose, Pose):
        problem = TargetProblem(observations, points)
        _, J = problem.linearize(problem.state(pose, fit.radius_offsets))
        keep = 6
    else:
        if reference is None:
            raise ValueError("a 5-DOF covariance needs the reference circle")
        if points is not None:
            raise ValueError("points need the 6-DOF pose")
        circle = CircleProblem(observations, reference)
        _, J = circle.linearize(circle.state(pose.center_C, pose.normal_C, fit.radius_offsets))
        keep = 5
    weights = [
        np.full(size, fit.edge_weight / sigma**2)
        for size, sigma in zip(observations.sizes, fit.sigma_px, strict=True)
    ]
    if points is not None:
        weights.append(np.full(points.size, 1.0 / fit.point_sigma**2))
    return J, np.concatenate(weights), keep
