"""What an estimator returns, the estimator protocol, and the tracker that carries the prior.

Covariance conventions (used by fusion; estimators must follow them):

* 6-DOF ``covariance`` (6×6) is over the error δ = [δθ, δp] of ``X_CT`` with the rotation error
  applied on the left, in the camera frame C: R_true = Exp(δθ)·R_est, p_true = p_est + δp
  (δθ in rad, δp in m; rotation first).
* 5-DOF ``covariance_5dof`` (5×5) is over [δc, α, β] of a circle's centre ``center_C`` (m, in C)
  and unit normal ``normal_C``: n_true ≈ n_est + α·u + β·v with (u, v) =
  ``estimators.conics.circle_plane_basis(normal_C)``.

Ambiguity (issue 13). Some targets look the same in two or more poses: a lone circle in its
two closed-form poses (its mirror), a square panel under its quarter turns. A measurement says
what the frame decided and what it did not:

* ``ambiguous``: the frame could not tell the answer from another pose, and nothing else did;
  ``alternative_center_C`` / ``alternative_normal_C`` carry a circle's other pose.
* ``from_prior``: the frame could not decide, and the answer took the pose nearer the prior.
  That is evidence only if the prior itself was decided: the ``Tracker`` keeps whether it was
  and, when it was not, reports the answer as undecided (ambiguous, or 5-DOF without the roll
  that nothing measured) — a guess carried from frame to frame never becomes a lock. A circle
  seen within its noise of head-on decided no side of the line of sight (``faces_a_side``).
* A pose whose roll no part in view can decide (a square panel with nothing asymmetric in
  sight) comes as 5-DOF: the circle of the ring about the panel's axis, centre and normal,
  with the pose (any roll) as ``X_CT_hint``.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Literal, Protocol, runtime_checkable

import numpy as np

from estimators.conics import circle_plane_basis
from estimators.frame import Frame
from estimators.geometry import Pose, skew
from estimators.target import Circle3D

Status = Literal["acquired", "tracking", "lost"]
SYSTEMS = ("corners", "lines", "ellipses")
#: The systems whose answers choose between a circle's two poses (``faces_a_side``).
CIRCLE_SYSTEMS = ("ellipses",)


def _readonly(array: np.ndarray | None, shape: tuple[int, ...], name: str) -> np.ndarray | None:
    if array is None:
        return None
    out = np.array(array, dtype=float)
    if out.shape != shape:
        raise ValueError(f"Measurement.{name} must have shape {shape}; got {out.shape}")
    if not np.all(np.isfinite(out)):
        raise ValueError(f"Measurement.{name} contains NaN or infinite values")
    out.flags.writeable = False
    return out


@dataclass(frozen=True, slots=True, eq=False)
class Measurement:
    """One estimator's answer for one frame.

    ``status``: ``acquired`` (found without using a prior), ``tracking`` (found using the prior)
    or ``lost`` (``reason`` says why; no pose). A valid measurement has ``X_CT`` (6-DOF) and/or
    ``center_C`` + ``normal_C`` (5-DOF circle pose of ``circle``). ``X_CT_hint`` is a full pose
    an estimator proposes as the next prior when it measured only 5 DOF (roll not measured).
    ``features`` holds image points for overlays and logs (name → (N,2) pixels), e.g.
    ``extracted``, ``labeled``, ``reprojected``. ``ambiguous``, ``from_prior`` and the
    circle's ``alternative_*`` pose: see the module docstring.
    """

    system: str
    status: Status
    stamp: float
    seq: int
    reason: str = ""
    X_CT: Pose | None = None
    covariance: np.ndarray | None = None
    circle: str | None = None
    center_C: np.ndarray | None = None
    normal_C: np.ndarray | None = None
    covariance_5dof: np.ndarray | None = None
    X_CT_hint: Pose | None = None
    residual_px: float = float("nan")
    ambiguous: bool = False
    features: Mapping[str, np.ndarray] = field(default_factory=dict)
    time_ms: float = 0.0
    from_prior: bool = False
    alternative_center_C: np.ndarray | None = None
    alternative_normal_C: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.status not in ("acquired", "tracking", "lost"):
            raise ValueError(
                f"Measurement.status must be acquired, tracking or lost; got {self.status!r}"
            )
        object.__setattr__(self, "covariance", _readonly(self.covariance, (6, 6), "covariance"))
        object.__setattr__(self, "center_C", _readonly(self.center_C, (3,), "center_C"))
        object.__setattr__(self, "normal_C", _readonly(self.normal_C, (3,), "normal_C"))
        object.__setattr__(
            self, "covariance_5dof", _readonly(self.covariance_5dof, (5, 5), "covariance_5dof")
        )
        for name in ("alternative_center_C", "alternative_normal_C"):
            object.__setattr__(self, name, _readonly(getattr(self, name), (3,), name))
        if (self.alternative_center_C is None) != (self.alternative_normal_C is None):
            raise ValueError("Measurement.alternative_center_C and _normal_C go together")
        if self.alternative_center_C is not None and self.center_C is None:
            raise ValueError("a circle's alternative pose needs the circle (center_C, normal_C)")
        if self.status == "lost":
            if not self.reason:
                raise ValueError("a lost Measurement must say why (reason)")
            if self.X_CT is not None or self.center_C is not None:
                raise ValueError("a lost Measurement carries no pose")
        else:
            if self.X_CT is None and self.center_C is None:
                raise ValueError(f"a {self.status} Measurement needs X_CT or center_C/normal_C")
            if self.X_CT is not None and self.covariance is None:
                raise ValueError("Measurement.X_CT needs its 6x6 covariance")
            if (self.center_C is None) != (self.normal_C is None):
                raise ValueError("Measurement.center_C and normal_C go together")
            if self.center_C is not None and (self.covariance_5dof is None or self.circle is None):
                raise ValueError("a 5-DOF Measurement needs circle and covariance_5dof")
            if self.normal_C is not None and abs(np.linalg.norm(self.normal_C) - 1) > 1e-6:
                raise ValueError("Measurement.normal_C must be a unit vector")

    @property
    def valid(self) -> bool:
        return self.status != "lost"

    @property
    def has_pose(self) -> bool:
        return self.X_CT is not None

    @property
    def prior(self) -> Pose | None:
        """The pose to hand the estimator as prior for the next frame."""
        return self.X_CT if self.X_CT is not None else self.X_CT_hint

    def to_dict(self, *, with_features: bool = False) -> dict:
        """JSON-ready view: poses as 4×4 nested lists, arrays as lists, NaN as None."""

        def listed(value):
            return None if value is None else np.asarray(value).tolist()

        out = {
            "system": self.system,
            "status": self.status,
            "reason": self.reason,
            "stamp": self.stamp,
            "seq": self.seq,
            "X_CT": None if self.X_CT is None else self.X_CT.to_list(),
            "covariance": listed(self.covariance),
            "circle": self.circle,
            "center_C": listed(self.center_C),
            "normal_C": listed(self.normal_C),
            "covariance_5dof": listed(self.covariance_5dof),
            "residual_px": None if not np.isfinite(self.residual_px) else float(self.residual_px),
            "ambiguous": self.ambiguous,
            "time_ms": self.time_ms,
            "from_prior": self.from_prior,
            "alternative_center_C": listed(self.alternative_center_C),
            "alternative_normal_C": listed(self.alternative_normal_C),
        }
        if with_features:
            out["features"] = {k: np.asarray(v).tolist() for k, v in self.features.items()}
        return out

    @staticmethod
    def from_dict(record: Mapping) -> Measurement:
        """Inverse of ``to_dict`` (e.g. for a measurement read back from a trial log); raises
        ``ValueError`` or ``KeyError`` for a record that is not a valid measurement."""

        def pose(value) -> Pose | None:
            return None if value is None else Pose.from_matrix(np.asarray(value, dtype=float))

        residual = record.get("residual_px")
        return Measurement(
            system=record["system"],
            status=record["status"],
            stamp=float(record.get("stamp", 0.0)),
            seq=int(record.get("seq", 0)),
            reason=record.get("reason") or "",
            X_CT=pose(record.get("X_CT")),
            covariance=record.get("covariance"),
            circle=record.get("circle"),
            center_C=record.get("center_C"),
            normal_C=record.get("normal_C"),
            covariance_5dof=record.get("covariance_5dof"),
            residual_px=float("nan") if residual is None else float(residual),
            ambiguous=bool(record.get("ambiguous", False)),
            features={k: np.asarray(v, dtype=float) for k, v in record.get("features", {}).items()},
            time_ms=float(record.get("time_ms") or 0.0),
            from_prior=bool(record.get("from_prior", False)),
            alternative_center_C=record.get("alternative_center_C"),
            alternative_normal_C=record.get("alternative_normal_C"),
        )

    @staticmethod
    def lost(
        system: str,
        frame: Frame,
        reason: str,
        *,
        started: float | None = None,
        features: Mapping[str, np.ndarray] | None = None,
    ) -> Measurement:
        """A ``lost`` measurement for ``frame``; ``started`` (perf_counter) sets ``time_ms``."""
        elapsed = 0.0 if started is None else 1000.0 * (time.perf_counter() - started)
        return Measurement(
            system=system,
            status="lost",
            stamp=frame.stamp,
            seq=frame.seq,
            reason=reason,
            features=features or {},
            time_ms=elapsed,
        )


def circle_covariance_from_pose(covariance: np.ndarray, X_CT: Pose, circle: Circle3D) -> np.ndarray:
    """5×5 covariance of a circle's (centre, normal) from the 6×6 covariance of ``X_CT``.

    With R_true = Exp(δθ)·R and p_true = p + δp: δc = δp − [R·c_T]ₓ·δθ and δn = δθ × n, whose
    components on (u, v) = circle_plane_basis(n) are (α, β)."""
    n = X_CT.R @ circle.normal_T
    u, v = circle_plane_basis(n)
    J = np.zeros((5, 6))
    J[:3, :3] = -skew(X_CT.R @ circle.center_T)
    J[:3, 3:] = np.eye(3)
    J[3, :3] = u @ -skew(n)  # δθ × n = −[n]ₓ δθ
    J[4, :3] = v @ -skew(n)
    out = J @ covariance @ J.T
    return 0.5 * (out + out.T)


def circle_of_pose(
    X_CT: Pose, covariance: np.ndarray, circle: Circle3D
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(centre_C, normal_C, 5×5 covariance) of a model circle under a 6-DOF pose."""
    return (
        X_CT.apply(circle.center_T[None])[0],
        X_CT.R @ circle.normal_T,
        circle_covariance_from_pose(covariance, X_CT, circle),
    )


def without_roll(m: Measurement) -> Measurement:
    """The 5-DOF part of a measurement that carries both a pose and its circle: the roll
    about the circle's axis is dropped (``X_CT`` becomes the hint)."""
    if m.X_CT is None or m.center_C is None:
        raise ValueError("without_roll needs a measurement with a pose and its circle")
    return replace(m, X_CT=None, covariance=None, X_CT_hint=m.X_CT, from_prior=False)


@runtime_checkable
class Estimator(Protocol):
    """A FEDALPE pose estimator: a pure function of (frame, prior) given its configuration.

    ``estimate`` never raises for a bad image: it returns a ``lost`` Measurement with a reason.
    With ``prior_X_CT`` None it searches the whole image (acquisition).
    """

    system: str

    def estimate(self, frame: Frame, prior_X_CT: Pose | None = None) -> Measurement: ...


class Tracker:
    """Carries the prior from frame to frame — the explicit state of a tracking estimator.

    The prior is the last valid measurement's pose. A lost frame drops it at once, so the next
    frame is searched globally: a lost system re-acquires by itself.

    It also carries what the last measurement decided: its roll (a 6-DOF pose, not ambiguous)
    and its circle (which of the two poses). An answer that took the undecided part from the
    prior (``from_prior``) is reported as what it is when the prior had not decided it either:
    a pose without its roll (5-DOF), or an ambiguous circle.
    """

    def __init__(self, estimator: Estimator):
        self.estimator = estimator
        self.prior_X_CT: Pose | None = None
        self.roll_decided = False
        self.circle_decided = False

    def reset(self) -> None:
        self.prior_X_CT = None
        self.roll_decided = self.circle_decided = False

    def update(self, frame: Frame, prior_X_CT: Pose | None = None) -> Measurement:
        """Estimate on ``frame`` with the given prior (e.g. from fusion) or the tracker's own."""
        prior = prior_X_CT if prior_X_CT is not None else self.prior_X_CT
        try:
            measurement = self.estimator.estimate(frame, prior)
        except Exception as exc:  # an estimator bug must not take the loop down
            measurement = Measurement.lost(
                self.estimator.system, frame, f"estimator raised {type(exc).__name__}: {exc}"
            )
        measurement = honest(measurement, self.roll_decided, self.circle_decided)
        self.prior_X_CT = measurement.prior if measurement.valid else None
        self.roll_decided, self.circle_decided = decided_parts(measurement)
        return measurement


def decided_parts(m: Measurement) -> tuple[bool, bool]:
    """(roll, circle): what ``m`` decided, for the frame that takes its pose as prior — its
    roll (a 6-DOF pose, not ambiguous) and its circle (which of the two poses: not ambiguous,
    and for a system that chooses between a circle's two poses, a circle facing a side of its
    line of sight — ``faces_a_side``). (A panel system's circle is its panel's axis, reported
    when the panel's roll is undecided; an answer of theirs that kept the prior's roll then
    loses it, ``honest``, rather than being flagged for a side it judged itself.)"""
    side = m.system not in CIRCLE_SYSTEMS or faces_a_side(m)
    return (
        m.valid and m.X_CT is not None and not m.ambiguous,
        m.valid and not m.ambiguous and side,
    )


def normal_sigma(covariance_5dof: np.ndarray, *, weak: bool = False) -> float:
    """Root of the total variance (rad²) of a circle's normal in its 5-DOF covariance, or of
    its larger principal variance (``weak``)."""
    block = covariance_5dof[3:5, 3:5]
    if weak:
        return float(np.sqrt(max(np.linalg.eigvalsh(block)[-1], 0.0)))
    return float(np.sqrt(max(np.trace(block), 0.0)))


def normals_apart(angle_rad: float, covariance_5dof: np.ndarray) -> bool:
    """Whether two normals ``angle_rad`` apart are two poses of a circle measured with
    ``covariance_5dof``, not one: more than 3σ of its normal (``normal_sigma``), and 1°."""
    return angle_rad >= max(np.radians(1.0), 3.0 * normal_sigma(covariance_5dof))


def faces_a_side(m: Measurement) -> bool:
    """Whether a circle measurement says which side of its line of sight the circle faces (True
    for a measurement without a circle). A circle's two poses are its normal and that normal
    reflected about the line of sight to its centre — 2τ apart for a normal τ off that line
    (exactly so on the optical axis, nearly elsewhere). Within its noise of head-on
    (``normals_apart`` false) the two are one pose, which the measurement reports as decided,
    and it decides nothing about the side the circle will face once it turns: held-out
    random:119 at 3 m, high noise, acquired head-on with its normal 3.4° off to one side; one
    frame later, the ring turned 8.7° to the other, the track kept the side of that prior and
    locked 18° off."""
    if m.center_C is None or m.normal_C is None or m.covariance_5dof is None:
        return True
    line_of_sight = m.center_C / np.linalg.norm(m.center_C)
    tilt = float(np.arccos(min(1.0, abs(float(m.normal_C @ line_of_sight)))))
    return normals_apart(2.0 * tilt, m.covariance_5dof)


def honest(m: Measurement, roll_decided: bool, circle_decided: bool) -> Measurement:
    """``m`` as what it is when it took its undecided part from a prior (``from_prior``) whose
    roll and circle were decided as given: an undecided normal (a circle's mirror, a plate's
    planar flip) stays ambiguous; a roll kept from a prior that had none is dropped (5-DOF) —
    or flagged when there is no circle to keep. Any other measurement is returned as it is."""
    if not (m.valid and m.from_prior):
        return m
    if not circle_decided:
        return replace(m, ambiguous=True)
    if m.X_CT is not None and not roll_decided:
        if m.center_C is not None:
            return without_roll(m)
        return replace(m, ambiguous=True)
    return m
