"""Conics: the image of a 3-D circle, and conversions between conic matrices and ellipses.

A conic is the symmetric 3×3 matrix Q with ``[u v 1] Q [u v 1]ᵀ = 0`` for its points (pixel
coordinates of an ideal pinhole camera: distortion must be removed first). Conics are defined
up to scale; functions here return them normalised to unit Frobenius norm with a sign that makes
the ellipse's interior negative.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimators.geometry import as_points


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
    n = np.asarray(normal, dtype=float)
    n = n / np.linalg.norm(n)
    helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(n, helper)
    u /= np.linalg.norm(u)
    return u, np.cross(n, u)


def circle_points(center: np.ndarray, normal: np.ndarray, radius: float, n: int = 64) -> np.ndarray:
    """``n`` points (n,3) evenly spaced on a 3-D circle."""
    u, v = circle_plane_basis(normal)
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    return (
        np.asarray(center, dtype=float)
        + radius * np.outer(np.cos(t), u)
        + radius * np.outer(np.sin(t), v)
    )


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
