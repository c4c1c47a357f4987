"""Pose of known 3-D circles by robust least squares on their image edge points.

The cost is the sum of squared geometric (Sampson) distances of observed edge points to the
image conics of the model circles (``conics.circle_image_conic``), minimised by Gauss–Newton
with Huber weights (iteratively reweighted least squares) — the geometric refinement of
Kanatani ("Statistical optimization for geometric computation", 1996) applied to the pose
instead of the conic, so that every circle constrains the same few parameters. Each edge set
carries its own noise scale (estimated from its residuals), and the covariance is the inverse
of the weighted normal matrix at the solution (the Gauss–Newton / Cramér–Rao approximation).

Two parametrisations, matching ``estimators.measurement``:

* 5-DOF (circles coaxial with a reference circle, e.g. the ring's two edges): centre c and unit
  normal n of the reference circle; update c ← c + δc, n ← normalise(n + α·u + β·v) with
  (u, v) = ``circle_plane_basis(n)``.
* 6-DOF (any circles of the target): ``X_CT`` with R ← Exp(δθ)·R, p ← p + δp.

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

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from estimators.circle_pose import CirclePose
from estimators.conics import circle_plane_basis
from estimators.geometry import Pose, as_points
from estimators.planar_pose import PointObservations
from estimators.robust_lsq import Solution, gauss_newton, marginal_covariance
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
        covariance=marginal_covariance(solution.information, n_pose),
        residuals=r,
        inliers=tuple(np.abs(ri) <= 3.0 * s for ri, s in zip(r, sigmas, strict=True)),
        sigma_px=sigmas,
        radius_offsets=tuple(float(o) for o in offsets),
        iterations=solution.iterations,
        point_residuals=points,
        point_sigma=point_sigma,
        edge_weight=edge_weight,
    )


class _ConicModel:
    """Residuals (Sampson distances of each edge set to its circle's image conic) and their
    Jacobian for a parameter increment.

    ``geometry(deltas)`` maps a batch of increments (B, P) to the circles' centres (B, S, 3),
    normals (B, S, 3) and radii (B, S) in C; their cones (``conics.circle_cone``) give the
    image conics. The Jacobian uses the chain rule through the 3×3 conics, with ∂Q/∂θ by
    differences of the (cheap, batched) conics: for r = f/g, f = hᵀQh and g = 2‖(Qh)₁,₂‖,
    ∂r/∂θ = (hᵀ Q' h)/g − f·(4 (Qh)₁,₂ · (Q'h)₁,₂ / g)/g².
    """

    _STEP = 1e-6

    def __init__(self, edge_sets: Sequence[EdgeSet], geometry, n_params: int, K: np.ndarray):
        self.h = [np.column_stack([s.uv, np.ones(len(s.uv))]) for s in edge_sets]
        self.geometry = geometry
        self.n_params = n_params
        self.K_inv = np.linalg.inv(K)

    def conics(self, deltas: np.ndarray) -> np.ndarray:
        """Image conics (B, S, 3, 3) for a batch of increments."""
        c, n, r = self.geometry(np.atleast_2d(deltas))
        n = n / np.linalg.norm(n, axis=-1, keepdims=True)
        s = np.einsum("...i,...i->...", n, c)
        cn = c[..., :, None] * n[..., None, :]
        nn = n[..., :, None] * n[..., None, :]
        A = (np.einsum("...i,...i->...", c, c) - r**2)[..., None, None] * nn
        A = A - s[..., None, None] * (cn + np.swapaxes(cn, -1, -2))
        A = A + (s**2)[..., None, None] * np.eye(3)
        return self.K_inv.T @ A @ self.K_inv

    def residuals(self, delta: np.ndarray) -> list[np.ndarray]:
        out = []
        for Q, h in zip(self.conics(delta)[0], self.h, strict=True):
            Qh = h @ Q
            value = np.einsum("ni,ni->n", Qh, h)
            out.append(value / np.maximum(2.0 * np.hypot(Qh[:, 0], Qh[:, 1]), 1e-300))
        return out

    def jacobian(self) -> np.ndarray:
        deltas = np.vstack([np.zeros(self.n_params), self._STEP * np.eye(self.n_params)])
        Q = self.conics(deltas)  # (P+1, S, 3, 3)
        dQ = (Q[1:] - Q[0]) / self._STEP  # (P, S, 3, 3)
        blocks = []
        for k, h in enumerate(self.h):
            Qh = h @ Q[0, k]
            f = np.einsum("ni,ni->n", Qh, h)
            g = np.maximum(2.0 * np.hypot(Qh[:, 0], Qh[:, 1]), 1e-300)
            DQh = np.einsum("ni,pij->npj", h, dQ[:, k])  # (N,P,3): (Q' h) per parameter
            df = np.einsum("npj,nj->np", DQh, h)
            dg = 4.0 * (Qh[:, 0:1] * DQh[:, :, 0] + Qh[:, 1:2] * DQh[:, :, 1]) / g[:, None]
            blocks.append(df / g[:, None] - (f / g**2)[:, None] * dg)
        return np.vstack(blocks)


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


def _circle_problem(edge_sets, reference, K, center, normal, radius_offsets=None):
    """The 5-DOF model at (centre, normal): (model, state, commit)."""
    heights = _coaxial_heights(edge_sets, reference)
    radii = np.array([s.circle.radius for s in edge_sets])
    free = [i for i, s in enumerate(edge_sets) if s.free_radius]
    state = {
        "c": np.asarray(center, dtype=float).copy(),
        "n": np.asarray(normal, dtype=float).copy(),
        "dr": np.zeros(len(free)) if radius_offsets is None else np.array(radius_offsets),
    }
    if state["n"] @ state["c"] > 0:  # on the camera side, so the fit stays there
        state["n"] = -state["n"]
    state["basis"] = np.array(circle_plane_basis(state["n"]))

    def moved(deltas: np.ndarray):
        """Centre (B,3), unit normal (B,3) and radius offsets (B,F) for increments (B,P)."""
        c = state["c"] + deltas[:, :3]
        n = state["n"] + deltas[:, 3:5] @ state["basis"]
        n = n / np.linalg.norm(n, axis=1, keepdims=True)
        return c, n, state["dr"] + deltas[:, 5:]

    def geometry(deltas: np.ndarray):
        c, n, dr = moved(deltas)
        r = np.broadcast_to(radii, (len(deltas), len(radii))).copy()
        r[:, free] += dr
        return (
            c[:, None, :] + heights[None, :, None] * n[:, None, :],
            n[:, None, :].repeat(len(radii), axis=1),
            r,
        )

    def commit(delta: np.ndarray) -> None:
        c, n, dr = moved(delta[None, :])
        state["c"], state["n"], state["dr"] = c[0], n[0], dr[0]
        state["basis"] = np.array(circle_plane_basis(state["n"]))

    return _ConicModel(edge_sets, geometry, 5 + len(free), K), state, commit


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
    model, state, commit = _circle_problem(
        edge_sets, reference, K, initial.center_C, initial.normal_C
    )
    solution = gauss_newton(
        model.residuals, model.n_params, commit, iterations=iterations, jacobian=model.jacobian
    )
    return _finish(CirclePose(state["c"], state["n"]), solution, 5, state["dr"])


def _exp_so3(w: np.ndarray) -> np.ndarray:
    """Rotation matrices (B,3,3) of rotation vectors (B,3) (Rodrigues' formula)."""
    w = np.atleast_2d(w)
    angle = np.linalg.norm(w, axis=1)
    W = np.zeros((len(w), 3, 3))
    W[:, 0, 1], W[:, 0, 2], W[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    W = W - np.swapaxes(W, 1, 2)
    small = angle < 1e-12
    a = np.where(small, 1.0, np.sin(angle) / np.where(small, 1.0, angle))
    b = np.where(small, 0.5, (1.0 - np.cos(angle)) / np.where(small, 1.0, angle) ** 2)
    return np.eye(3) + a[:, None, None] * W + b[:, None, None] * (W @ W)


def _target_problem(edge_sets, K, X_CT: Pose, radius_offsets=None):
    """The 6-DOF model at ``X_CT``: (model, state, commit)."""
    centers_T = np.array([s.circle.center_T for s in edge_sets])
    normals_T = np.array([s.circle.normal_T for s in edge_sets])
    radii = np.array([s.circle.radius for s in edge_sets])
    free = [i for i, s in enumerate(edge_sets) if s.free_radius]
    state = {
        "R": X_CT.R.copy(),
        "p": X_CT.p.copy(),
        "dr": np.zeros(len(free)) if radius_offsets is None else np.array(radius_offsets),
    }

    def moved(deltas: np.ndarray):
        R = _exp_so3(deltas[:, :3]) @ state["R"]
        return R, state["p"] + deltas[:, 3:6], state["dr"] + deltas[:, 6:]

    def geometry(deltas: np.ndarray):
        R, p, dr = moved(deltas)
        r = np.broadcast_to(radii, (len(deltas), len(radii))).copy()
        r[:, free] += dr
        centers = np.einsum("bij,sj->bsi", R, centers_T) + p[:, None, :]
        return centers, np.einsum("bij,sj->bsi", R, normals_T), r

    def commit(delta: np.ndarray) -> None:
        R, p, dr = moved(delta[None, :])
        U, _, Vt = np.linalg.svd(R[0])
        state["R"], state["p"], state["dr"] = U @ Vt, p[0], dr[0]

    return _ConicModel(edge_sets, geometry, 6 + len(free), K), state, commit


class _WithPoints:
    """A 6-DOF edge model plus labeled points: the points' whitened reprojection errors are
    one more residual group (no dependence on the nuisance radii)."""

    def __init__(self, model: _ConicModel, state: dict, points: PointObservations, K):
        self.model, self.state, self.points, self.K = model, state, points, K
        self.n_params = model.n_params

    def _pose(self, delta: np.ndarray) -> Pose:
        return Pose(_exp_so3(delta[None, :3])[0] @ self.state["R"], self.state["p"] + delta[3:6])

    def residuals(self, delta: np.ndarray) -> list[np.ndarray]:
        _, r_w, _ = self.points.linearize(self._pose(delta), self.K)
        return [*self.model.residuals(delta), r_w]

    def point_jacobian(self) -> np.ndarray:
        """The points' rows of the Jacobian (2N, P) at the current state."""
        _, _, J_w = self.points.linearize(self._pose(np.zeros(6)), self.K)
        padded = np.zeros((len(J_w), self.n_params))
        padded[:, :6] = J_w
        return padded

    def jacobian(self) -> np.ndarray:
        return np.vstack([self.model.jacobian(), self.point_jacobian()])


def _group_settings(n_sets: int, points, edge_weight: float):
    """(group weights, noise-scale floors) for edge sets followed by the points' group."""
    weights = [edge_weight] * n_sets
    floors = [0.05] * n_sets
    if points is not None:
        weights.append(1.0)
        floors.append(1.0)
    return weights, floors


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
    model, state, commit = _target_problem(edge_sets, K, initial)
    if points is not None and points.count:
        model = _WithPoints(model, state, points, K)
    else:
        points = None
    weights, floors = _group_settings(len(edge_sets), points, edge_weight)
    solution = gauss_newton(
        model.residuals,
        model.n_params,
        commit,
        iterations=iterations,
        jacobian=model.jacobian,
        group_weights=weights,
        sigma_floors=floors,
    )
    return _finish(
        Pose(state["R"], state["p"]),
        solution,
        6,
        state["dr"],
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
    if isinstance(pose, Pose):
        model, state, _ = _target_problem(edge_sets, K, pose, fit.radius_offsets)
        keep = 6
    else:
        if reference is None:
            raise ValueError("a 5-DOF covariance needs the reference circle")
        model, _, _ = _circle_problem(
            edge_sets, reference, K, pose.center_C, pose.normal_C, fit.radius_offsets
        )
        keep = 5
    J = model.jacobian()
    weights = np.concatenate(
        [
            np.full(len(h), fit.edge_weight / sigma**2)
            for h, sigma in zip(model.h, fit.sigma_px, strict=True)
        ]
    )
    information = J.T @ (J * weights[:, None])
    if points is not None and points.count:
        if keep != 6:
            raise ValueError("points need the 6-DOF pose")
        J_points = _WithPoints(model, state, points, K).point_jacobian()
        information = information + J_points.T @ J_points / fit.point_sigma**2
    return marginal_covariance(information, keep)
