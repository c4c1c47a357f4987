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
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from estimators.circle_pose import CirclePose
from estimators.conics import circle_plane_basis
from estimators.geometry import Pose, as_points
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
    ``sigma_px`` the per-set noise scales; ``radius_offsets`` the fitted nuisance radii (m)."""

    pose: CirclePose | Pose
    covariance: np.ndarray
    residuals: tuple[np.ndarray, ...]
    inliers: tuple[np.ndarray, ...]
    sigma_px: tuple[float, ...]
    radius_offsets: tuple[float, ...]
    iterations: int

    @property
    def rms_px(self) -> float:
        """RMS residual over the inliers of all sets."""
        r = np.concatenate([res[ok] for res, ok in zip(self.residuals, self.inliers, strict=True)])
        return float(np.sqrt(np.mean(r**2))) if len(r) else float("nan")

    @property
    def inlier_count(self) -> int:
        return int(sum(ok.sum() for ok in self.inliers))


def _finish(pose, solution: Solution, n_pose: int, offsets: np.ndarray) -> FitResult:
    r, sigmas = solution.residuals, solution.sigmas
    return FitResult(
        pose=pose,
        covariance=marginal_covariance(solution.information, n_pose),
        residuals=r,
        inliers=tuple(np.abs(ri) <= 3.0 * s for ri, s in zip(r, sigmas, strict=True)),
        sigma_px=sigmas,
        radius_offsets=tuple(float(o) for o in offsets),
        iterations=solution.iterations,
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


def fit_target_pose(
    edge_sets: Sequence[EdgeSet],
    initial: Pose,
    K: np.ndarray,
    *,
    iterations: int = 6,
) -> FitResult:
    """6-DOF pose ``X_CT`` from edge sets on any circles of the target."""
    model, state, commit = _target_problem(edge_sets, K, initial)
    solution = gauss_newton(
        model.residuals, model.n_params, commit, iterations=iterations, jacobian=model.jacobian
    )
    return _finish(Pose(state["R"], state["p"]), solution, 6, state["dr"])


def covariance_at(
    edge_sets: Sequence[EdgeSet],
    fit: FitResult,
    pose: CirclePose | Pose,
    K: np.ndarray,
    *,
    reference: Circle3D | None = None,
) -> np.ndarray:
    """The covariance of a fit (its noise scales and nuisance radii) linearised at another
    ``pose`` — a ``CirclePose`` (5-DOF, with ``reference``) or a ``Pose`` (6-DOF).

    Used where the linearisation at the solution is over-confident: near a head-on view a
    circle's tilt enters its image only quadratically, so at a slightly tilted estimate the
    tangent says the tilt is well known while the cost is nearly flat back to head-on; the
    covariance at the head-on pose does not make that mistake.
    """
    if isinstance(pose, Pose):
        model, _, _ = _target_problem(edge_sets, K, pose, fit.radius_offsets)
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
        [np.full(len(h), 1.0 / sigma**2) for h, sigma in zip(model.h, fit.sigma_px, strict=True)]
    )
    return marginal_covariance(J.T @ (J * weights[:, None]), keep)
