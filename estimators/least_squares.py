"""The one robust least-squares solver: Gauss–Newton / Levenberg–Marquardt with iteratively
reweighted residuals, for every pose, circle and ellipse fit of the estimators.

A ``Problem`` owns the model: from a state (whatever the model keeps — a pose, a circle, ellipse
parameters) it gives the residual groups and their Jacobian with respect to a parameter
increment δ, and it moves the state by δ (``retract``), which keeps rotations and unit normals on
their manifolds. The observation types that build problems give analytic Jacobians:

* points and straight edges (``planar_pose.PointObservations``, ``EdgeObservations``,
  ``CorrelatedEdgeObservations``) and circle edges against a projected conic
  (``circle_fit.ConicObservations``) w.r.t. a pose increment δ = [δθ, δp] with
  R ← Exp(δθ)·R and p ← p + δp — the rotation perturbed on the left, the translation added (the
  SO(3) × ℝ³ convention of ``estimators.measurement``, not SE(3)'s, whose δp would be rotated);
* circle edges w.r.t. the 5-DOF circle increment [δc, α, β]: c ← c + δc,
  n ← normalise(n + α·u + β·v), (u, v) = ``conics.circle_plane_basis(n)``.

The loop (Nocedal & Wright, "Numerical Optimization", 2006, §10.3):

* weights: a ``Loss`` turns residual groups into per-residual weights w — ``NoLoss`` (w = 1, for
  residuals already whitened by their covariance), ``Huber`` (IRLS with k = 1.345·σ_g, σ_g the
  per-group noise scale by the median absolute deviation; Huber 1964, Holland & Welsch 1977) or
  ``Cauchy`` (w = 1/(1 + χ²ᵢ/c²) on blocks of whitened residuals; Black & Anandan 1996);
* normal equations H = Jᵀ·W·J, g = Jᵀ·W·r, step δ = −H⁻¹·g;
* Gauss–Newton (``levenberg=False``) takes every step and stops when δᵀ·H·δ < ``tolerance``²
  (the step is a small fraction of a standard deviation); Levenberg–Marquardt
  (``levenberg=True``) damps H by λ·diag(H) until the cost falls and stops when it falls by
  less than 10⁻⁶·(1 + cost) or no step lowers it (Marquardt 1963).

Covariance (one recipe, ``covariance``): s²·H⁻¹ with H the weighted information Jᵀ·W·J of the
last linearisation (a direction H leaves unobserved taken as barely measured, never as known)
and s² the caller's variance factor — 1 for the Huber fits, whose weights already carry
1/σ_g², and χ²/dof for the whitened reprojection fits (``planar_pose``) — symmetrised, with
the marginal block of the first ``keep`` parameters (nuisances such as free radii
marginalised out).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from estimators.compiled import compiled
from estimators.small_linalg import at_least

HUBER_K = 1.345


class Problem(Protocol):
    """A least-squares model: residual groups at a state, their Jacobian (rows in group order,
    columns the increment's ``n_params``), and the state moved by an increment."""

    @property
    def n_params(self) -> int: ...

    def residuals(self, state: Any) -> list[np.ndarray]: ...

    def linearize(self, state: Any) -> tuple[list[np.ndarray], np.ndarray]: ...

    def retract(self, state: Any, delta: np.ndarray) -> Any: ...


# --- losses ----------------------------------------------------------------------------------


def robust_sigma(residuals: np.ndarray, floor: float = 0.05) -> float:
    """Noise scale of residuals: 1.4826 × median absolute deviation, at least ``floor``."""
    r = np.ascontiguousarray(residuals, dtype=float).reshape(-1)
    return float(_robust_sigma(r, float(floor)))


@compiled
def _robust_sigma(r, floor):
    if len(r) == 0:
        return 1.0
    scale = 1.4826 * _median(np.abs(r - _median(r)))
    return at_least(scale, floor)


@compiled
def _huber_group(r, floor, k):
    """One group's Huber IRLS weights (1 inside k·σ, k·σ/|r| outside, divided by σ²) at its
    own noise scale σ (``robust_sigma``), and σ — one call per group and iteration of a fit."""
    sigma = _robust_sigma(r, floor)
    w = np.empty(len(r))
    for i in range(len(r)):
        a = abs(r[i]) / (k * sigma)
        w[i] = (1.0 if a <= 1.0 else 1.0 / max(a, 1e-12)) / sigma**2
    return w, sigma


def median(values: np.ndarray) -> float:
    """``np.median`` of a non-empty 1-D array (np.median's overhead dominates the short arrays
    of a fit)."""
    values = np.ascontiguousarray(values)
    if values.size == 0:
        raise ValueError("median of an empty array")
    return float(_median(values.reshape(-1)))


@compiled
def _median(values):
    """The middle value, or the mean of the two middle values of an even count (in the array's
    own precision, as NumPy adds them)."""
    ordered = np.sort(values)
    half = len(ordered) // 2
    if len(ordered) % 2:
        return ordered[half]
    return 0.5 * (ordered[half - 1] + ordered[half])


def _huber_rho(residuals: np.ndarray, sigma: float) -> np.ndarray:
    """Huber's ρ(r/σ) (½u² inside k, k|u| − ½k² outside)."""
    u = np.abs(residuals) / sigma
    return np.where(u <= HUBER_K, 0.5 * u**2, HUBER_K * u - 0.5 * HUBER_K**2)


class Loss(Protocol):
    """Weights (flat, one per residual) and noise scales (one per group) of residual groups,
    and the cost Σρ that Levenberg–Marquardt compares between steps."""

    def weights(self, groups: Sequence[np.ndarray]) -> tuple[np.ndarray, tuple[float, ...]]: ...

    def cost(self, groups: Sequence[np.ndarray], sigmas: Sequence[float]) -> float: ...


@dataclass(frozen=True, slots=True)
class NoLoss:
    """Plain least squares on residuals already whitened (unit noise): w = 1, σ = 1."""

    def weights(self, groups: Sequence[np.ndarray]) -> tuple[np.ndarray, tuple[float, ...]]:
        flat = _flatten(groups)
        return np.ones(len(flat)), tuple(1.0 for _ in groups)

    def cost(self, groups: Sequence[np.ndarray], sigmas: Sequence[float]) -> float:
        flat = _flatten(groups)
        return float(flat @ flat)


@dataclass(frozen=True, slots=True)
class Huber:
    """Huber weights with each group's own noise scale (MAD, at least its floor): a group's
    weights are the Huber weights at σ_g (``_huber_group``) × ``group_weights[g]``
    (information scale, e.g. < 1 for samples that are not independent). ``floors`` per group
    (default ``floor``)."""

    floor: float = 0.05
    floors: tuple[float, ...] | None = None
    group_weights: tuple[float, ...] | None = None

    def sigmas(self, groups: Sequence[np.ndarray]) -> tuple[float, ...]:
        floors = self.floors if self.floors is not None else (self.floor,) * len(groups)
        return tuple(robust_sigma(r, f) for r, f in zip(groups, floors, strict=True))

    def weights(self, groups: Sequence[np.ndarray]) -> tuple[np.ndarray, tuple[float, ...]]:
        floors = self.floors if self.floors is not None else (self.floor,) * len(groups)
        scale = self.group_weights
        w, sigmas = [], []
        for g, (r, floor) in enumerate(zip(groups, floors, strict=True)):
            weights, sigma = _huber_group(
                np.ascontiguousarray(r, dtype=float).reshape(-1), float(floor), HUBER_K
            )
            w.append(weights if scale is None else weights * scale[g])
            sigmas.append(float(sigma))
        return (np.concatenate(w) if w else np.zeros(0)), tuple(sigmas)

    def cost(self, groups: Sequence[np.ndarray], sigmas: Sequence[float]) -> float:
        scale = self.group_weights
        return float(
            sum(
                np.sum(_huber_rho(r, s)) * (1.0 if scale is None else scale[g])
                for g, (r, s) in enumerate(zip(groups, sigmas, strict=True))
            )
        )


@dataclass(frozen=True, slots=True)
class Cauchy:
    """Cauchy (Lorentzian) weights on whitened residuals taken ``block`` at a time (a point's
    two pixel coordinates): w = 1/(1 + χ²ᵢ/c²) with χ²ᵢ the block's squared norm, c² =
    ``scale2`` — an M-estimator that a good share of gross outliers cannot pull far."""

    scale2: float = 9.0
    block: int = 2

    def chi2(self, groups: Sequence[np.ndarray]) -> np.ndarray:
        """Each block's χ²."""
        flat = _flatten(groups)
        return np.sum(flat.reshape(-1, self.block) ** 2, axis=1)

    def weights(self, groups: Sequence[np.ndarray]) -> tuple[np.ndarray, tuple[float, ...]]:
        w = 1.0 / (1.0 + self.chi2(groups) / self.scale2)
        return np.repeat(w, self.block), tuple(1.0 for _ in groups)

    def cost(self, groups: Sequence[np.ndarray], sigmas: Sequence[float]) -> float:
        return float(np.sum(self.scale2 * np.log1p(self.chi2(groups) / self.scale2)))


def _flatten(groups: Sequence[np.ndarray]) -> np.ndarray:
    return np.concatenate(groups) if len(groups) else np.zeros(0)


# --- the loop --------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, eq=False)
class Solution:
    """The solved ``state``; ``information`` H = JᵀWJ at the last linearisation (identity if
    there was none); the final residual groups; the noise scales of the last weighting; the
    iteration count; whether a stopping test (not the iteration limit) ended the loop."""

    state: Any
    information: np.ndarray
    residuals: tuple[np.ndarray, ...]
    sigmas: tuple[float, ...]
    iterations: int
    converged: bool


def _step(H: np.ndarray, g: np.ndarray, damping: np.ndarray) -> np.ndarray | None:
    """δ = −(H + damping)⁻¹·g, None when it does not exist."""
    try:
        delta = -np.linalg.solve(H + damping, g)
    except np.linalg.LinAlgError:
        return None
    return delta if np.all(np.isfinite(delta)) else None


def _normal_equations(J, w, flat, B, unit: bool):
    """(information JᵀWJ, H = (JB)ᵀW(JB), g = (JB)ᵀW·r); ``unit`` weights skip the products."""
    information = J.T @ (J if unit else J * w[:, None])
    if B is None:
        return information, information, J.T @ (flat if unit else w * flat)
    JB = J @ B
    return (
        information,
        JB.T @ (JB if unit else JB * w[:, None]),
        JB.T @ (flat if unit else w * flat),
    )


@dataclass(frozen=True, slots=True, eq=False)
class _Linearized:
    """A state with its residual groups, Jacobian, weights, noise scales and (for
    Levenberg–Marquardt) cost, ∞ where the residuals are not finite."""

    state: Any
    groups: list[np.ndarray]
    J: np.ndarray
    w: np.ndarray
    sigmas: tuple[float, ...]
    cost: float


def _linearized(problem: Problem, loss: Loss, state: Any, with_cost: bool) -> _Linearized:
    groups, J = problem.linearize(state)
    w, sigmas = loss.weights(groups)
    cost = 0.0
    if with_cost:
        cost = loss.cost(groups, sigmas) if np.all(np.isfinite(_flatten(groups))) else np.inf
    return _Linearized(state, groups, J, w, sigmas, cost)


def solve(
    problem: Problem,
    state: Any,
    *,
    loss: Loss,
    iterations: int = 8,
    tolerance: float = 0.05,
    levenberg: bool = False,
    basis: np.ndarray | None = None,
) -> Solution:
    """Minimise Σρ(r) over increments of ``problem`` from ``state`` (see the module docstring).

    ``basis`` (n_params×k) restricts the steps to δ = basis·x. Gauss–Newton adds a touch of
    damping (10⁻⁹·diag(H) + 10⁻¹²) so that nearly unobservable directions cannot explode.
    Levenberg–Marquardt needs finite residuals at the start (ValueError otherwise) and
    refuses steps to non-finite ones.
    """
    n = problem.n_params
    B = None if basis is None else np.asarray(basis, dtype=float).reshape(n, -1)
    k = n if B is None else B.shape[1]
    unit = isinstance(loss, NoLoss)
    information = np.eye(n)
    now = _linearized(problem, loss, state, levenberg)
    if levenberg and not np.isfinite(now.cost):
        raise ValueError("least squares: the residuals at the start are not finite")
    done, converged, damping = 0, False, 0.0
    for done in range(1, iterations + 1):
        flat = _flatten(now.groups)
        if len(flat) < k:
            break
        information, H, g = _normal_equations(now.J, now.w, flat, B, unit)
        if not levenberg:  # Gauss–Newton: take the step
            delta = _step(H, g, np.diag(np.diag(H)) * 1e-9 + np.eye(k) * 1e-12)
            if delta is None:
                break
            state = problem.retract(state, delta if B is None else B @ delta)
            if float(delta @ H @ delta) < tolerance**2:
                converged = True
                break
            if done < iterations:
                now = _linearized(problem, loss, state, False)
            continue
        # Levenberg–Marquardt: damp the step until the cost falls.
        before = now.cost
        for _ in range(12):
            damped = damping * np.diag(np.diag(H) + 1e-12)
            delta = _step(H, g, damped)
            if delta is None:
                delta = -np.linalg.lstsq(H + damped, g, rcond=None)[0]
            moved = problem.retract(now.state, delta if B is None else B @ delta)
            candidate = _linearized(problem, loss, moved, True)
            if candidate.cost <= now.cost:
                now = candidate
                damping = 0.0 if damping < 1e-3 else damping / 10.0
                break
            damping = 1e-4 if damping == 0.0 else damping * 10.0
        state = now.state
        # Converged when no step lowers the cost (a minimum to numerical precision) or the last
        # one changed it by a negligible fraction of one unit of χ²: further digits are noise.
        if before - now.cost <= 1e-6 * (1.0 + now.cost):
            converged = True
            break
    final = now.groups if levenberg else problem.residuals(state)
    sigmas = now.sigmas if len(now.sigmas) == len(final) else loss.weights(final)[1]
    return Solution(state, information, tuple(final), tuple(sigmas), done, converged)


#: Information below this fraction of the strongest direction's is taken as none: such a
#: direction's variance is capped at 1 / (UNOBSERVED_INFORMATION · λ_max).
UNOBSERVED_INFORMATION = 1e-10


def covariance(
    information: np.ndarray, *, keep: int | None = None, scale2: float = 1.0
) -> np.ndarray:
    """s²·H⁻¹, symmetrised; the block of the first ``keep`` parameters — the others
    (nuisances) marginalised out.

    A direction H leaves unobserved (a circle's tilt seen head-on enters its image only to
    second order) holds nothing but round-off, of either sign: its plain inverse has
    eigenvalues of ±10¹⁰ and a pseudo-inverse's zero claims it known exactly. There the
    eigenvalues of H are floored at ``UNOBSERVED_INFORMATION`` of the largest — a large
    positive variance: "not measured", and the covariance stays positive definite."""
    information = np.asarray(information, dtype=float)
    symmetric = 0.5 * (information + information.T)
    spectrum = np.linalg.eigvalsh(symmetric)
    floor = UNOBSERVED_INFORMATION * max(float(spectrum[-1]), 0.0)
    if spectrum[0] > floor:
        cov = np.linalg.inv(information)
    else:
        if floor <= 0.0:
            raise np.linalg.LinAlgError("the information holds nothing: no covariance")
        values, vectors = np.linalg.eigh(symmetric)
        cov = (vectors / np.maximum(values, floor)) @ vectors.T
    if keep is not None:
        cov = cov[:keep, :keep]
    cov = cov * scale2
    return 0.5 * (cov + cov.T)


# --- problems built from functions -----------------------------------------------------------


@dataclass(frozen=True, slots=True, eq=False)
class VectorProblem:
    """A problem on a plain parameter vector (state + δ): residuals from ``function``, and
    residuals with their analytic Jacobian from ``linearized``, in one pass where they share
    their work (``conics.refine_ellipse``)."""

    function: Callable[[np.ndarray], list[np.ndarray]]
    n_params: int
    linearized: Callable[[np.ndarray], tuple[list[np.ndarray], np.ndarray]]

    def residuals(self, state: np.ndarray) -> list[np.ndarray]:
        return self.function(state)

    def linearize(self, state: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
        return self.linearized(state)

    def retract(self, state: np.ndarray, delta: np.ndarray) -> np.ndarray:
        return state + delta
