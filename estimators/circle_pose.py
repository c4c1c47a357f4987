"""Pose of a 3-D circle of known radius from its image conic (closed form, two candidates).

The conic Q (pixels, ideal pinhole K) back-projects to the elliptical cone Xᵀ A X = 0 with
A = Kᵀ Q K in the camera frame C. Planes that cut the cone in a circle follow from its
eigen-decomposition (Shiu & Ahmad, IEEE T-RA 1989; Safaee-Rad, Tchoukanov, Smith & Benhabib,
IEEE T-RA 1992; Kanatani's "3-D interpretation of conics", 1993): with eigenvalues
λ1 ≥ λ2 > 0 > λ3 and eigenvectors e1, e2, e3,

    A − λ2·I = (λ1 − λ2)·e1e1ᵀ − (λ2 − λ3)·e3e3ᵀ = ½(q1q2ᵀ + q2q1ᵀ),
    q1,2 = √(λ1 − λ2)·e1 ∓ √(λ2 − λ3)·e3,

so every cone point satisfies λ2‖X‖² + (q1·X)(q2·X) = 0. On a plane q2·X = h this is a sphere,
and a sphere meets a plane in a circle: the circular sections have normals ∝ q2 (and, with e1
flipped, the second family — the two-fold ambiguity). Working the sphere out gives, for radius r,
the plane's distance d = r·λ2/√(−λ1λ3) and the circle's centre

    c = (h / 2λ2)·(−q1 + (λ1 + λ3)/(λ1 − λ3)·q2),  h = d·‖q2‖.

Head-on (λ1 = λ2) both candidates coincide and the normal is the cone axis e3.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimators.conics import normalize_conic


@dataclass(frozen=True, slots=True, eq=False)
class CirclePose:
    """A circle's centre (m) and unit normal in the camera frame C; the normal points toward
    the camera side of the circle's plane (normal · centre < 0)."""

    center_C: np.ndarray
    normal_C: np.ndarray

    def __post_init__(self) -> None:
        center = np.array(self.center_C, dtype=float).reshape(-1)
        normal = np.array(self.normal_C, dtype=float).reshape(-1)
        if center.shape != (3,) or normal.shape != (3,):
            raise ValueError("CirclePose needs a 3-vector centre and normal")
        if not (np.all(np.isfinite(center)) and np.all(np.isfinite(normal))):
            raise ValueError("CirclePose has non-finite values")
        normal = normal / np.linalg.norm(normal)
        center.flags.writeable = False
        normal.flags.writeable = False
        object.__setattr__(self, "center_C", center)
        object.__setattr__(self, "normal_C", normal)


def cone_from_conic(Q: np.ndarray, K: np.ndarray) -> np.ndarray:
    """The back-projected cone A = Kᵀ Q K (camera frame C), scaled to unit norm."""
    A = np.asarray(K, dtype=float).T @ normalize_conic(Q) @ np.asarray(K, dtype=float)
    A = 0.5 * (A + A.T)
    return A / np.linalg.norm(A)


def circle_poses_from_conic(Q: np.ndarray, radius: float, K: np.ndarray) -> tuple[CirclePose, ...]:
    """The two circles of ``radius`` (m) in front of the camera whose image is the conic Q.

    Returns two ``CirclePose`` (identical up to rounding when the view is head-on). ValueError
    if Q is not the image of a real ellipse in front of the camera.
    """
    if not radius > 0:
        raise ValueError(f"radius must be positive; got {radius}")
    A = cone_from_conic(Q, K)
    eigenvalues, eigenvectors = np.linalg.eigh(A)
    positive = int(np.sum(eigenvalues > 0))
    if positive == 1:  # make the signature (+, +, −)
        eigenvalues, eigenvectors = -eigenvalues[::-1], eigenvectors[:, ::-1]
    elif positive != 2:
        raise ValueError("the conic's cone is not elliptical (needs eigenvalue signs + + −)")
    # eigh sorts ascending: after the flip above the order is λ3 < 0 < λ2 ≤ λ1.
    order = np.argsort(eigenvalues)[::-1]
    l1, l2, l3 = eigenvalues[order]
    e1, e3 = eigenvectors[:, order[0]], eigenvectors[:, order[2]]
    if not (l1 >= l2 > 0 > l3):
        raise ValueError("the conic's cone is not elliptical (needs eigenvalue signs + + −)")
    g1 = np.sqrt(max(l1 - l2, 0.0))
    g3 = np.sqrt(l2 - l3)
    distance = radius * l2 / np.sqrt(-l1 * l3)
    poses = []
    for sign in (1.0, -1.0):
        q1 = sign * g1 * e1 - g3 * e3
        q2 = sign * g1 * e1 + g3 * e3
        h = distance * np.linalg.norm(q2)
        center = (h / (2.0 * l2)) * (-q1 + (l1 + l3) / (l1 - l3) * q2)
        normal = q2 / np.linalg.norm(q2)
        if center[2] < 0:  # the other nappe of the cone: the circle behind the camera
            center = -center
        if normal @ center > 0:  # orient the normal toward the camera
            normal = -normal
        poses.append(CirclePose(center, normal))
    return tuple(poses)
