"""Conics: the image of a 3-D circle, and conversions between conic matrices and ellipses.

A conic is the symmetric 3×3 matrix Q with ``[u v 1] Q [u v 1]ᵀ = 0`` for its points (pixel
coordinates of an ideal pinhole camera: distortion must be removed first). Conics are defined
up to scale; functions here return them normalised to unit Frobenius norm with a sign that makes
the ellipse's interior negative.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimators.geometry import as_points
from estimators.least_squares import Huber, VectorProblem, solve


@dataclass(frozen=True, slots=True)
class Ellipse:
    """An ellipse in the image (pixels): centre, semi-axes a ≥ b, and angle of the a-axis (rad)."""

    cx: float
    cy: float
    a: float
    b: float
    angle: float

    def __post_init__(self) -> None:
        values = (self.cx, self.cy, self.a, self.b, self.angle)
        if not all(np.isfinite(values)):
            raise ValueError(f"Ellipse has non-finite parameters: {values}")
        if not (self.a >= self.b > 0):
            raise ValueError(f"Ellipse needs a ≥ b > 0; got a={self.a}, b={self.b}")

    @property
    def center(self) -> np.ndarray:
        return np.array([self.cx, self.cy])

    def points(self, n: int = 64) -> np.ndarray:
        """``n`` points (n,2) evenly spaced in the parametric angle."""
        t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
        c, s = np.cos(self.angle), np.sin(self.angle)
        x = self.a * np.cos(t)
        y = self.b * np.sin(t)
        return np.column_stack([self.cx + c * x - s * y, self.cy + s * x + c * y])


def normalize_conic(Q: np.ndarray) -> np.ndarray:
    """Scale a conic to unit Frobenius norm, with the sign making its centre's value negative."""
    Q = 0.5 * (np.asarray(Q, dtype=float) + np.asarray(Q, dtype=float).T)
    Q = Q / np.linalg.norm(Q)
    # For an ellipse the 2×2 block is definite; make it positive definite (interior negative).
    if np.trace(Q[:2, :2]) < 0:
        Q = -Q
    return Q


def conic_from_ellipse(e: Ellipse) -> np.ndarray:
    """The normalised conic matrix of an ellipse."""
    c, s = np.cos(e.angle), np.sin(e.angle)
    R = np.array([[c, -s], [s, c]])
    A = R @ np.diag([1.0 / e.a**2, 1.0 / e.b**2]) @ R.T
    centre = e.center
    Q = np.zeros((3, 3))
    Q[:2, :2] = A
    Q[:2, 2] = -A @ centre
    Q[2, :2] = -A @ centre
    Q[2, 2] = centre @ A @ centre - 1.0
    return normalize_conic(Q)


def ellipse_from_conic(Q: np.ndarray) -> Ellipse:
    """Centre, semi-axes and angle of a conic that is a real ellipse; ValueError otherwise."""
    Q = normalize_conic(Q)
    A = Q[:2, :2]
    b = Q[:2, 2]
    eigenvalues = np.linalg.eigvalsh(A)
    if eigenvalues[0] <= 0:
        raise ValueError("conic is not an ellipse (its quadratic part is not definite)")
    centre = -np.linalg.solve(A, b)
    # Value at the centre: k = Q33 − bᵀA⁻¹b; the ellipse is (x−c)ᵀ A (x−c) = −k.
    k = Q[2, 2] + b @ centre
    if k >= 0:
        raise ValueError("conic is an imaginary ellipse (no real points)")
    w, V = np.linalg.eigh(A / -k)
    # Smallest eigenvalue ↔ the major axis.
    a = 1.0 / np.sqrt(w[0])
    b_axis = 1.0 / np.sqrt(w[1])
    major = V[:, 0]
    angle = float(np.arctan2(major[1], major[0]))
    # Angle of an axis is defined modulo π; keep it in (−π/2, π/2].
    if angle <= -np.pi / 2:
        angle += np.pi
    elif angle > np.pi / 2:
        angle -= np.pi
    return Ellipse(float(centre[0]), float(centre[1]), float(a), float(b_axis), angle)


def circle_plane_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane orthogonal to ``normal`` (any fixed choice)."""
    x, y, z = np.asarray(normal, dtype=float) / np.sqrt(np.dot(normal, normal))
    # u = n × helper, v = n × u, written out (np.cross is slow on single vectors).
    u = np.array([0.0, z, -y]) if abs(x) < 0.9 else np.array([-z, 0.0, x])  # helper x or y
    u /= np.sqrt(u @ u)
    v = np.array([y * u[2] - z * u[1], z * u[0] - x * u[2], x * u[1] - y * u[0]])
    return u, v


def circle_points(
    center: np.ndarray,
    normal: np.ndarray,
    radius: float,
    n: int = 64,
    *,
    angles: np.ndarray | None = None,
) -> np.ndarray:
    """``n`` points (n,3) evenly spaced on a 3-D circle, or the points at ``angles`` (rad,
    measured in the ``circle_plane_basis`` of the normal)."""
    u, v = circle_plane_basis(normal)
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False) if angles is None else np.asarray(angles)
    return (
        np.asarray(center, dtype=float)
        + radius * np.outer(np.cos(t), u)
        + radius * np.outer(np.sin(t), v)
    )


def circle_cone(center_C: np.ndarray, normal_C: np.ndarray, radius: float) -> np.ndarray:
    """The cone Xᵀ A X = 0 of the rays from the camera centre through a 3-D circle (frame C).

    A ray X meets the circle's plane n·Y = n·c at Y = X (n·c)/(n·X); requiring ‖Y − c‖ = r and
    multiplying by (n·X)² gives ‖(n·c) X − (n·X) c‖² = r² (n·X)², i.e.

        A = (n·c)² I − (n·c)(c nᵀ + n cᵀ) + (‖c‖² − r²) n nᵀ,

    negative inside the cone (at X = c it is −r²(n·c)²). Basis-free, so it is also an
    independent check of the plane-homography form below.
    """
    c = np.asarray(center_C, dtype=float)
    n = np.asarray(normal_C, dtype=float)
    n = n / np.sqrt(n @ n)
    nc = float(n @ c)
    cn = c[:, None] * n[None, :]
    A = (c @ c - radius * radius) * (n[:, None] * n[None, :]) - nc * (cn + cn.T)
    A[np.diag_indices(3)] += nc * nc
    return A


def circle_image_conic(
    center_C: np.ndarray, normal_C: np.ndarray, radius: float, K: np.ndarray
) -> np.ndarray:
    """Image conic (pixels, pinhole K) of a 3-D circle given in the camera frame C.

    The circle's plane maps to the image by the homography H = K [u v c] (u, v an orthonormal
    basis of the plane, c the centre); the circle is x² + y² = r² in plane coordinates, i.e.
    the conic diag(1, 1, −r²), and conics map as Q = H⁻ᵀ diag(1, 1, −r²) H⁻¹.
    """
    if radius <= 0:
        raise ValueError(f"radius must be positive; got {radius}")
    u, v = circle_plane_basis(normal_C)
    H = np.asarray(K, dtype=float) @ np.column_stack([u, v, np.asarray(center_C, dtype=float)])
    if abs(np.linalg.det(H)) < 1e-12 * np.linalg.norm(H) ** 3:
        raise ValueError("the circle's plane passes through the camera centre (degenerate image)")
    H_inv = np.linalg.inv(H)
    return normalize_conic(H_inv.T @ np.diag([1.0, 1.0, -(radius**2)]) @ H_inv)


def conic_residuals(Q: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Algebraic values [u v 1] Q [u v 1]ᵀ of points (N,2) — zero on the conic."""
    uv = as_points(uv, 2, "uv")
    h = np.column_stack([uv, np.ones(len(uv))])
    return np.einsum("ni,ij,nj->n", h, Q, h)


def sampson_distances(Q: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Signed Sampson distances (px) of points (N,2) to the conic Q: the algebraic value divided
    by the norm of its gradient, a first-order approximation of the geometric distance that is
    exact to O(d²/R) for points near the curve (Kanatani, "Statistical optimization for
    geometric computation", 1996). Negative inside a normalised ellipse."""
    uv = as_points(uv, 2, "uv")
    h = np.column_stack([uv, np.ones(len(uv))])
    Qh = h @ np.asarray(Q, dtype=float)  # Q symmetric: rows are (Q h)ᵀ
    value = np.einsum("ni,ni->n", Qh, h)
    gradient_norm = 2.0 * np.hypot(Qh[:, 0], Qh[:, 1])
    return value / np.maximum(gradient_norm, 1e-300)


def fit_ellipse_direct(uv: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Direct least-squares ellipse fit of points (N,2), N ≥ 5; returns the normalised conic.

    Fitzgibbon, Pilu & Fisher, "Direct least square fitting of ellipses" (IEEE PAMI 1999):
    minimise the algebraic distance subject to 4ac − b² = 1, which always yields an ellipse;
    solved in the numerically stable block form of Halíř & Flusser (WSCG 1998). Points are
    first centred and scaled (Hartley normalisation) so the fit is independent of pixel scale.
    ``weights`` (N,) weight each point's algebraic residual. ValueError if the points do not
    determine an ellipse (fewer than 5, collinear, ...).
    """
    uv = as_points(uv, 2, "uv")
    if len(uv) < 5:
        raise ValueError(f"an ellipse fit needs at least 5 points; got {len(uv)}")
    H, D1, D2 = _normalised_design(uv)
    if weights is not None:
        w = np.sqrt(np.clip(np.asarray(weights, dtype=float).reshape(-1), 0.0, None))
        if w.shape != (len(uv),):
            raise ValueError(f"weights must have shape ({len(uv)},); got {np.shape(weights)}")
        D1 = D1 * w[:, None]
        D2 = D2 * w[:, None]
    return _ellipse_from_scatter(D1.T @ D1, D1.T @ D2, D2.T @ D2, H)


def _normalised_design(uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The Hartley normalisation H of points (N,2) (centred, mean distance √2) and the direct
    fit's design matrices of the normalised points: quadratic (x², xy, y²) and linear (x, y, 1)
    columns."""
    mean = uv.mean(axis=0)
    scale = np.sqrt(2.0) / max(np.sqrt(((uv - mean) ** 2).sum(axis=1).mean()), 1e-12)
    x = (uv[:, 0] - mean[0]) * scale
    y = (uv[:, 1] - mean[1]) * scale
    # x_n = H x with H = [[s, 0, −s·mx], [0, s, −s·my], [0, 0, 1]].
    H = np.array([[scale, 0.0, -scale * mean[0]], [0.0, scale, -scale * mean[1]], [0, 0, 1.0]])
    return H, np.column_stack([x * x, x * y, y * y]), np.column_stack([x, y, np.ones_like(x)])


def _ellipse_from_scatter(
    S1: np.ndarray, S2: np.ndarray, S3: np.ndarray, H: np.ndarray
) -> np.ndarray:
    """The direct fit's ellipse from the scatter blocks S1 = D1ᵀD1, S2 = D1ᵀD2, S3 = D2ᵀD2 of
    points normalised by H (Halíř & Flusser's reduced 3×3 eigenproblem), as the normalised
    conic in pixel coordinates. ValueError when they determine no ellipse."""
    try:
        T = -np.linalg.solve(S3, S2.T)
    except np.linalg.LinAlgError as exc:
        raise ValueError("points do not determine an ellipse (degenerate layout)") from exc
    M = S1 + S2 @ T
    # Premultiply by the inverse of the constraint matrix C1 = [[0,0,2],[0,-1,0],[2,0,0]].
    M = np.array([M[2] / 2.0, -M[1], M[0] / 2.0])
    eigenvalues, eigenvectors = np.linalg.eig(M)
    eigenvectors = np.real(eigenvectors)
    condition = 4.0 * eigenvectors[0] * eigenvectors[2] - eigenvectors[1] ** 2
    candidates = np.flatnonzero((condition > 0) & np.isfinite(np.real(eigenvalues)))
    if len(candidates) == 0:
        raise ValueError("points do not determine an ellipse (no elliptical solution)")
    a1 = eigenvectors[:, candidates[np.argmin(np.abs(np.real(eigenvalues[candidates])))]]
    a2 = T @ a1
    A, B, C = a1
    Dx, Ey, F = a2
    Q_normalised = np.array([[A, B / 2, Dx / 2], [B / 2, C, Ey / 2], [Dx / 2, Ey / 2, F]])
    Q = H.T @ Q_normalised @ H
    if not np.all(np.isfinite(Q)):
        raise ValueError("points do not determine an ellipse (non-finite fit)")
    return normalize_conic(Q)


def fit_ellipse_leaving_out_an_arc(uv: np.ndarray, *, blocks: int = 8) -> np.ndarray:
    """Direct ellipse fit (``fit_ellipse_direct``) of points (N,2) ordered along their curve,
    robust to one wrong arc: every fit that leaves out a quarter of the curve (two adjacent of
    ``blocks`` runs of points) competes with the fit of all, by the median absolute Sampson
    distance of *all* points (least median of squares, Rousseeuw 1984, over contiguous
    subsets). A least-squares fit, even a Huber one, leans toward a clustered wrong arc: a lit
    bore wall a ring's width inside its edge, found by the edge search on one side, flattened
    the ellipse by 9 % (b/a 0.91 for 0.99) and still fitted its points to 0.9 px rms. A subset
    must be clearly better (median 0.8× the full fit's) to win. Returns the normalised conic.

    The scatter matrices of the direct fit add over points, so each subset's is the whole
    curve's less its two runs' (normalised once, for all points: the direct fit is invariant
    under similarities, Fitzgibbon et al. 1999, so the subset's own normalisation would give
    the same ellipse) — a 3×3 problem per subset instead of a fit."""
    uv = as_points(uv, 2, "uv")
    if len(uv) < 8 * blocks:
        return fit_ellipse_direct(uv)
    H, D1, D2 = _normalised_design(uv)
    scatter_all = (D1.T @ D1, D1.T @ D2, D2.T @ D2)
    Q_all = _ellipse_from_scatter(*scatter_all, H)  # = fit_ellipse_direct(uv)
    best, best_score = Q_all, 0.8 * float(np.median(np.abs(sampson_distances(Q_all, uv))))
    runs = np.array_split(np.arange(len(uv)), blocks)
    scatter_runs = [(D1[r].T @ D1[r], D1[r].T @ D2[r], D2[r].T @ D2[r]) for r in runs]
    for i in range(blocks):
        a, b = scatter_runs[i], scatter_runs[(i + 1) % blocks]
        S1, S2, S3 = (total - a[k] - b[k] for k, total in enumerate(scatter_all))
        try:
            Q = _ellipse_from_scatter(S1, S2, S3, H)
        except ValueError:
            continue
        score = float(np.median(np.abs(sampson_distances(Q, uv))))
        if score < best_score:
            best, best_score = Q, score
    return best


def ellipse_angles(e: Ellipse, uv: np.ndarray) -> np.ndarray:
    """Parametric angles (rad, in (−π, π]) of points (N,2) about an ellipse: the angle t with
    the point ≈ centre + R(angle)·[a cos t, b sin t]."""
    uv = as_points(uv, 2, "uv")
    d = uv - e.center
    c, s = np.cos(e.angle), np.sin(e.angle)
    return np.arctan2((-s * d[:, 0] + c * d[:, 1]) / e.b, (c * d[:, 0] + s * d[:, 1]) / e.a)


def covered_angle(angles: np.ndarray) -> float:
    """Angular extent (rad, in [0, 2π]) of a set of angles on the circle: 2π minus the largest
    gap between neighbours."""
    angles = np.sort(np.mod(np.asarray(angles, dtype=float).reshape(-1), 2.0 * np.pi))
    if len(angles) < 2:
        return 0.0
    gaps = np.diff(np.concatenate([angles, [angles[0] + 2.0 * np.pi]]))
    return float(2.0 * np.pi - gaps.max())


def conic_from_parameters(cx: float, cy: float, a: float, b: float, angle: float) -> np.ndarray:
    """Conic of an ellipse given by its centre, semi-axes and the angle (rad) of axis ``a``,
    without the a ≥ b ordering (for fitting and for other libraries' ellipses)."""
    c, s = np.cos(angle), np.sin(angle)
    R = np.array([[c, -s], [s, c]])
    A = R @ np.diag([1.0 / a**2, 1.0 / b**2]) @ R.T
    centre = np.array([cx, cy])
    Q = np.empty((3, 3))
    Q[:2, :2] = A
    Q[:2, 2] = Q[2, :2] = -A @ centre
    Q[2, 2] = centre @ A @ centre - 1.0
    return Q


#: Semi-axes (px) the refinement keeps to: under a tenth of a pixel or beyond 10⁶ px is no ellipse.
_LOG_AXIS_MIN, _LOG_AXIS_MAX = float(np.log(0.1)), float(np.log(1e6))


def refine_ellipse(
    uv: np.ndarray, initial: Ellipse, *, iterations: int = 6
) -> tuple[Ellipse, np.ndarray, float]:
    """Geometric refinement of an ellipse on points (N,2): robust Gauss–Newton on (centre,
    log-axes, angle) minimising Sampson distances (Kanatani 1996) with Huber weights — the
    step after a direct algebraic fit, which is biased toward small ellipses on short arcs.

    Returns (ellipse, residuals (N,) px, robust noise scale px).
    """
    uv = as_points(uv, 2, "uv")
    start = _state_of(initial)
    problem = VectorProblem(
        lambda state: [ellipse_sampson_distances(state, uv)[0]],
        5,
        linearized=lambda state: _as_groups(ellipse_sampson_distances(state, uv, jacobian=True)),
    )
    solution = solve(problem, start, loss=Huber(floor=0.02), iterations=iterations)
    cx, cy, a, b, angle = _ellipse_parameters(solution.state)
    ellipse = ellipse_from_conic(conic_from_parameters(cx, cy, a, b, angle))
    return ellipse, solution.residuals[0], solution.sigmas[0]


def major_axis_log_sd(uv: np.ndarray, ellipse: Ellipse, sigma_px: float) -> float:
    """Standard deviation of log a — the major axis's relative uncertainty — of ``ellipse``
    fitted to points ``uv`` (N,2) with residual noise ``sigma_px``: from the Sampson
    distances' Jacobian on (centre, log-axes, angle), σ²·(JᵀJ)⁻¹ (inf when singular). Short
    arcs on opposite sides of a thin ellipse — the curvature barely seen — fit its length
    loosely."""
    uv = as_points(uv, 2, "uv")
    _, J = ellipse_sampson_distances(_state_of(ellipse), uv, jacobian=True)
    assert J is not None
    try:
        covariance = sigma_px**2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return math.inf
    variance = float(covariance[2, 2])
    return math.sqrt(variance) if math.isfinite(variance) and variance >= 0.0 else math.inf


def _state_of(ellipse: Ellipse) -> np.ndarray:
    """The refinement state (cx, cy, log a, log b, angle) of an ellipse."""
    return np.array([ellipse.cx, ellipse.cy, np.log(ellipse.a), np.log(ellipse.b), ellipse.angle])


def _ellipse_parameters(state: np.ndarray) -> tuple[float, float, float, float, float]:
    """(cx, cy, a, b, angle) of a refinement state (cx, cy, log a, log b, angle). A trial step
    on a short, noisy arc may ask for absurd axes: they are kept finite (the step is then
    refused for its cost, not for an overflow)."""
    cx, cy, log_a, log_b, angle = (float(x) for x in state)
    a, b = np.exp(np.clip([log_a, log_b], _LOG_AXIS_MIN, _LOG_AXIS_MAX))
    return cx, cy, float(a), float(b), angle


def _as_groups(
    distances: tuple[np.ndarray, np.ndarray | None],
) -> tuple[list[np.ndarray], np.ndarray]:
    d, J = distances
    assert J is not None
    return [d], J


def ellipse_sampson_distances(
    state: np.ndarray, uv: np.ndarray, *, jacobian: bool = False
) -> tuple[np.ndarray, np.ndarray | None]:
    """Signed Sampson distances (N,) of points (N,2) to the ellipse of ``state`` (cx, cy,
    log a, log b, angle), as ``sampson_distances`` of its conic, and, if asked (``jacobian``),
    their Jacobian (N,5; else None).

    In the ellipse's own axes — x = Rᵀ(p − c) with R the rotation by the angle — the conic's
    value is F = x₁²/a² + x₂²/b² − 1 and its gradient's norm 2‖k‖ with k = (x₁/a², x₂/b²), so
    d = F / (2‖k‖): the derivatives follow by the chain rule through x (centre and angle:
    ∂x/∂c = −Rᵀ, ∂x/∂angle = (x₂, −x₁)) and through 1/a² = e^(−2 log a). An axis held at its
    bound (``_ellipse_parameters``) does not move with its state."""
    cx, cy, a, b, angle = _ellipse_parameters(state)
    cos, sin = np.cos(angle), np.sin(angle)
    px, py = uv[:, 0] - cx, uv[:, 1] - cy
    x1, x2 = cos * px + sin * py, -sin * px + cos * py
    k1, k2 = x1 / a**2, x2 / b**2
    norm = np.maximum(np.hypot(k1, k2), 1e-300)
    F = x1 * k1 + x2 * k2 - 1.0
    d = F / (2.0 * norm)
    if not jacobian:
        return d, None
    # ∂d/∂x₁, ∂d/∂x₂: F's gradient is 2k, the norm's (k₁/a², k₂/b²)/‖k‖
    scale = F / (2.0 * norm**3)
    d_x1 = k1 / norm - scale * k1 / a**2
    d_x2 = k2 / norm - scale * k2 / b**2
    # through 1/a² and 1/b²: ∂F/∂log a = −2 x₁k₁, ∂‖k‖/∂log a = −2 k₁²/‖k‖ (b alike)
    d_log_a = -x1 * k1 / norm + 2.0 * scale * k1**2
    d_log_b = -x2 * k2 / norm + 2.0 * scale * k2**2
    held = np.clip(state[2:4], _LOG_AXIS_MIN, _LOG_AXIS_MAX) != state[2:4]
    J = np.column_stack(
        [
            -cos * d_x1 + sin * d_x2,
            -sin * d_x1 - cos * d_x2,
            np.zeros_like(d) if held[0] else d_log_a,
            np.zeros_like(d) if held[1] else d_log_b,
            x2 * d_x1 - x1 * d_x2,
        ]
    )
    return d, J
