"""Synthetic approach runs for the fusion tests: a target in the carriage frame M, a track that
moves the carriage, an arm that moves the camera, and three "systems" whose measurements are
sampled from the covariances they state (so their stated uncertainty is honest by construction,
unless a test makes them over-confident on purpose)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.stats import chi2

from estimators.conics import circle_plane_basis
from estimators.fusion import FusionParams, PoseFusion, pose_error_C
from estimators.geometry import (
    Pose,
    look_at,
    normal_angle,
    rotation_error_geodesic,
    translation_error,
)
from estimators.measurement import Measurement
from estimators.so3 import exp_so3
from estimators.target import Circle3D, PointFeature, TargetModel

DT = 1.0 / 30.0


def make_target() -> TargetModel:
    """The default mock-up's circles: ring at the origin, thruster off-axis (roll observable)."""
    z = np.array([0.0, 0.0, 1.0])
    corners = np.array([[0.15, 0.15, -0.05], [-0.15, 0.15, -0.05], [-0.15, -0.15, -0.05]])
    corners = np.vstack([corners, [0.15, -0.15, -0.05]])
    return TargetModel(
        name="synthetic",
        panel_corners_T=corners,
        point_features=tuple(
            PointFeature(f"c{i}", c, 0.0, "corner", True) for i, c in enumerate(corners)
        ),
        circles=(
            Circle3D("ring_outer", np.zeros(3), z, 0.30),
            Circle3D("thruster_exit", np.array([0.50, 0.42, 0.04]), z, 0.06),
        ),
    )


def covariance(rng: np.random.Generator, sigmas: np.ndarray, correlate: bool = True) -> np.ndarray:
    """A covariance with the given axis σ in a random (seeded) orientation of each 3-block."""
    D = np.diag(np.asarray(sigmas, dtype=float) ** 2)
    if not correlate:
        return D
    n = len(sigmas)
    T = np.eye(n)
    for start in range(0, n - n % 3, 3):
        T[start : start + 3, start : start + 3] = exp_so3(rng.normal(size=3))
    return T @ D @ T.T


def gaussian(rng: np.random.Generator, cov: np.ndarray) -> np.ndarray:
    """One sample of N(0, cov) (Cholesky: cheaper than multivariate_normal's SVD)."""
    return np.linalg.cholesky(cov) @ rng.normal(size=len(cov))


def sample_pose(
    rng: np.random.Generator, X_CT_true: Pose, cov: np.ndarray, scale_true: float = 1.0
) -> Pose:
    """X_CT_est with error δ ~ N(0, scale_true·cov): R_true = Exp(δθ)·R_est, p_true = p_est + δp."""
    delta = gaussian(rng, scale_true * cov)
    return Pose(exp_so3(-delta[:3]) @ X_CT_true.R, X_CT_true.p - delta[3:])


def sample_circle(
    rng: np.random.Generator,
    X_CT_true: Pose,
    circle: Circle3D,
    cov5: np.ndarray,
    scale_true: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """(center_C, normal_C) with error [δc, α, β] ~ N(0, scale_true·cov5)."""
    delta = gaussian(rng, scale_true * cov5)
    center_true = X_CT_true.apply(circle.center_T)
    normal_true = X_CT_true.R @ circle.normal_T
    u, v = circle_plane_basis(normal_true)
    tilt = delta[3] * u + delta[4] * v  # n_true = n_est + t  ⇒  n_est = Exp_{n_true}(−t)
    axis = np.cross(normal_true, -tilt)
    normal_est = exp_so3(axis) @ normal_true
    return center_true - delta[:3], normal_est / np.linalg.norm(normal_est)


@dataclass(frozen=True)
class SystemModel:
    """A synthetic estimator: ``kind`` 'pose' (6-DOF) or 'circle' (5-DOF of ``circle``);
    σ grow with the distance d (m) as given by ``sigmas(d)``; ``scale_true`` > 1 makes the
    stated covariance over-confident by that factor."""

    name: str
    kind: str
    sigmas: Callable[[float], np.ndarray]
    circle: str = "ring_outer"
    scale_true: float = 1.0
    pose_every: int = 0  # circle systems: also give a 6-DOF pose on every n-th frame (thruster)


def corners_sigmas(d: float) -> np.ndarray:
    rot = np.radians([0.8, 0.8, 0.3]) * d / 2.0
    pos = np.array([0.003, 0.003, 0.012]) * d**2 / 4.0
    return np.concatenate([rot, pos])


def lines_sigmas(d: float) -> np.ndarray:
    rot = np.radians([1.2, 1.2, 0.5]) * d / 2.0
    pos = np.array([0.002, 0.002, 0.008]) * d**2 / 4.0
    return np.concatenate([rot, pos])


def ring_sigmas(d: float) -> np.ndarray:
    return np.concatenate([np.array([0.002, 0.002, 0.006]) * d / 2.0, np.radians([0.6, 0.6])])


def ellipse_pose_sigmas(d: float) -> np.ndarray:
    rot = np.radians([0.6, 0.6, 1.5]) * max(d, 0.5) / 2.0
    pos = np.array([0.002, 0.002, 0.006]) * d / 2.0
    return np.concatenate([rot, pos])


SYSTEMS = (
    SystemModel("corners", "pose", corners_sigmas),
    SystemModel("lines", "pose", lines_sigmas),
    SystemModel("ellipses", "circle", ring_sigmas),
)


def measure(
    rng: np.random.Generator,
    system: SystemModel,
    target: TargetModel,
    X_CT_true: Pose,
    stamp: float,
    seq: int,
    rotations: dict[str, np.ndarray],
) -> Measurement:
    """One measurement of ``system`` with its stated covariance (rotated per system)."""
    d = float(np.linalg.norm(X_CT_true.p))
    if system.kind == "pose" or (system.pose_every and seq % system.pose_every == 0):
        sig = system.sigmas(d) if system.kind == "pose" else ellipse_pose_sigmas(d)
        T = rotations[system.name + "6"]
        cov = T @ np.diag(sig**2) @ T.T
        X = sample_pose(rng, X_CT_true, cov, system.scale_true)
        extra = {}
        if system.kind == "circle":  # a 6-DOF ellipse measurement also states its ring
            circle = target.circle(system.circle)
            extra = dict(
                circle=circle.name,
                center_C=X.apply(circle.center_T),
                normal_C=X.R @ circle.normal_T,
                covariance_5dof=np.diag(ring_sigmas(d) ** 2),
            )
        return Measurement(
            system=system.name,
            status="tracking",
            stamp=stamp,
            seq=seq,
            X_CT=X,
            covariance=cov,
            **extra,
        )
    circle = target.circle(system.circle)
    T = rotations[system.name + "5"]
    cov5 = T @ np.diag(system.sigmas(d) ** 2) @ T.T
    center, normal = sample_circle(rng, X_CT_true, circle, cov5, system.scale_true)
    hint = Pose(exp_so3(rng.normal(scale=0.3) * normal) @ X_CT_true.R, X_CT_true.p)
    return Measurement(
        system=system.name,
        status="tracking",
        stamp=stamp,
        seq=seq,
        circle=circle.name,
        center_C=center,
        normal_C=normal,
        covariance_5dof=cov5,
        X_CT_hint=hint,
    )


def system_rotations(rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Fixed random orientations of each system's error axes (correlated covariances)."""
    out = {}
    for s in SYSTEMS:
        T6 = np.eye(6)
        T6[:3, :3] = exp_so3(rng.normal(scale=0.5, size=3))
        T6[3:, 3:] = exp_so3(rng.normal(scale=0.5, size=3))
        T5 = np.eye(5)
        T5[:3, :3] = exp_so3(rng.normal(scale=0.5, size=3))
        angle = rng.normal()
        T5[3:, 3:] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
        out[s.name + "6"], out[s.name + "5"] = T6, T5
    return out


@dataclass
class Scenario:
    """Truth of one approach: per step the stamp, X_CM (known to the caller) and X_MT, V_MT."""

    stamps: np.ndarray
    X_CM: list[Pose]
    X_MT: list[Pose]
    V_MT: np.ndarray
    X_BM: list[Pose] = field(default_factory=list)
    X_BC: list[Pose] = field(default_factory=list)

    def X_CT(self, k: int) -> Pose:
        return self.X_CM[k] @ self.X_MT[k]


def approach(
    rng: np.random.Generator,
    steps: int,
    *,
    start_m: float = 2.5,
    end_m: float = 0.6,
    track_speed: float = 0.2,
    target_motion: str = "static",
    omega: np.ndarray | None = None,
    velocity: np.ndarray | None = None,
    angular_accel_psd: float = 0.0,
    linear_accel_psd: float = 0.0,
) -> Scenario:
    """A closing approach: the carriage rides the track (along B's x) toward the arm and the
    camera closes from ``start_m`` to ``end_m``, off-centre, weaving and rolling.

    ``target_motion``: ``static`` (X_MT fixed), ``drift`` (constant ``omega``/``velocity`` in M),
    or ``process`` (a sample of the filter's own white-acceleration model).
    """
    X_MT0 = Pose.from_rpy(0.05, -0.08, 0.3, np.array([0.1, -0.05, 0.4]))
    R_BM = Pose.from_rpy(0.0, -np.pi / 2, 0.0, np.zeros(3)).R  # target's face looks at −x of B
    omega = np.zeros(3) if omega is None else np.asarray(omega, dtype=float)
    velocity = np.zeros(3) if velocity is None else np.asarray(velocity, dtype=float)
    stamps = np.arange(steps) * DT
    X_MT, V = [], []
    R, p, w, v = X_MT0.R, X_MT0.p, omega.copy(), velocity.copy()
    for _k in range(steps):
        X_MT.append(Pose(R, p))
        V.append(np.concatenate([w, v]))
        if target_motion == "process":
            # exact discretisation of white acceleration: (x, ẋ) increments with the Q blocks
            cov = np.array([[DT**3 / 3, DT**2 / 2], [DT**2 / 2, DT]])
            L = np.linalg.cholesky(cov)
            nw = L @ rng.normal(size=(2, 3)) * np.sqrt(angular_accel_psd)
            nv = L @ rng.normal(size=(2, 3)) * np.sqrt(linear_accel_psd)
            R = exp_so3(nw[0]) @ exp_so3(w * DT) @ R
            p = p + v * DT + nv[0]
            w = w + nw[1]
            v = v + nv[1]
        elif target_motion == "drift":
            R = exp_so3(w * DT) @ R
            p = p + v * DT
    X_BM, X_BC, X_CM = [], [], []
    for k, t in enumerate(stamps):
        s = k / max(steps - 1, 1)
        X_BMk = Pose(R_BM, np.array([3.2 - track_speed * t, 0.2, 0.5]))
        X_BT = X_BMk @ X_MT[k]
        distance = start_m + (end_m - start_m) * s
        normal_B = X_BT.R[:, 2]
        lateral = np.array([0.0, 0.25 * (1 - s) * np.cos(3 * t), 0.15 * (1 - s)])
        p_BC = X_BT.p + distance * normal_B + lateral
        look = X_BT.p + np.array([0.0, 0.05 * np.sin(2 * t), 0.0])
        X_BCk = look_at(p_BC, look, np.array([0.0, 0.0, 1.0]))
        X_BCk = X_BCk @ Pose.from_rpy(0.0, 0.0, 0.2 * np.sin(t), np.zeros(3))
        X_BM.append(X_BMk)
        X_BC.append(X_BCk)
        X_CM.append(X_BCk.inverse() @ X_BMk)
    return Scenario(stamps, X_CM, X_MT, np.array(V), X_BM, X_BC)


def run(
    scenario: Scenario,
    target: TargetModel,
    params: FusionParams | None = None,
    *,
    seed: int = 0,
    systems: tuple[SystemModel, ...] = SYSTEMS,
    absent: Callable[[int, str], bool] | None = None,
    blind: Callable[[int, str], bool] | None = None,
    extra: Callable[[int, Pose, float], list[Measurement]] | None = None,
    X_CM_override: Callable[[int], Pose] | None = None,
):
    """Feed a scenario to a fresh filter. ``absent(k, name)`` / ``blind(k, name)`` drop a
    system (no measurement / a ``lost`` one); ``extra(k, X_CT_true, stamp)`` adds measurements.

    Returns (fused, single, estimates, fusion): per-step errors of the fused estimate (``t`` m,
    ``r`` rad, ring ``center`` m and ``normal`` rad, pose ``nees``) and of each system (``t``,
    ``r``: pose errors, or centre/normal errors of a circle), NaN where there is none.
    """
    rng = np.random.default_rng(seed)
    rotations = system_rotations(rng)
    ring = target.circle("ring_outer")
    fusion = PoseFusion(target, params or FusionParams())
    n = len(scenario.stamps)
    fused = {key: np.full(n, np.nan) for key in ("t", "r", "center", "normal", "nees")}
    single = {s.name: {"t": np.full(n, np.nan), "r": np.full(n, np.nan)} for s in systems}
    estimates = []
    for k, stamp in enumerate(scenario.stamps):
        truth = scenario.X_CT(k)
        measurements = []
        for system in systems:
            if absent and absent(k, system.name):
                continue
            if blind and blind(k, system.name):
                measurements.append(
                    Measurement(system.name, "lost", stamp, k, reason="blinded by the test")
                )
                continue
            m = measure(rng, system, target, truth, stamp, k, rotations)
            measurements.append(m)
            if system.kind == "pose":
                single[system.name]["t"][k] = translation_error(truth, m.X_CT)
                single[system.name]["r"][k] = rotation_error_geodesic(truth, m.X_CT)
            else:
                circle = target.circle(m.circle)
                center_true = truth.apply(circle.center_T)
                single[system.name]["t"][k] = np.linalg.norm(m.center_C - center_true)
                single[system.name]["r"][k] = normal_angle(truth.R @ circle.normal_T, m.normal_C)
        if extra:
            measurements += extra(k, truth, stamp)
        X_CM = scenario.X_CM[k] if X_CM_override is None else X_CM_override(k)
        estimate = fusion.update(measurements, X_CM, stamp)
        estimates.append(estimate)
        if estimate.X_MT is not None:
            X_CT = estimate.X_CT(scenario.X_CM[k])
            fused["t"][k] = translation_error(truth, X_CT)
            fused["r"][k] = rotation_error_geodesic(truth, X_CT)
            fused["center"][k] = np.linalg.norm(
                truth.apply(ring.center_T) - X_CT.apply(ring.center_T)
            )
            fused["normal"][k] = normal_angle(truth.R @ ring.normal_T, X_CT.R @ ring.normal_T)
            error = pose_error_C(truth, X_CT)
            cov = estimate.pose_covariance_C(scenario.X_CM[k])
            fused["nees"][k] = error @ np.linalg.solve(cov, error)
    return fused, single, estimates, fusion


def measurement_stream(
    scenario: Scenario,
    target: TargetModel,
    *,
    seed: int = 0,
    systems: tuple[SystemModel, ...] = SYSTEMS,
) -> list[tuple[int, Measurement]]:
    """(step, measurement) of every system at every step of ``scenario``, in capture order —
    for tests that deliver them late, one system at a time."""
    rng = np.random.default_rng(seed)
    rotations = system_rotations(rng)
    return [
        (k, measure(rng, system, target, scenario.X_CT(k), stamp, k, rotations))
        for k, stamp in enumerate(scenario.stamps)
        for system in systems
    ]


def delivered_late(
    at_capture: bool, *, seed: int = 0, steps: int = 150, delay_frames: tuple[int, int] = (4, 5)
) -> tuple[np.ndarray, np.ndarray, int]:
    """A static target, a camera closing on it (``approach``: 2.5 → 0.6 m in ``steps`` frames),
    and every system's result delivered ``delay_frames`` frames after its capture (drawn per
    result: 4 or 5 frames of 1/30 s, 150 ms on average), so the systems' results cross.

    ``at_capture``: each result is fused at its capture stamp with X_CM at capture; otherwise
    re-stamped on arrival and fused with X_CM at arrival (a pipeline that ignores latency).
    Returns, over the second half, the error [δθ, δp] (rad, m) of the estimate at each frame's
    time ("now") in M, its 6-DOF NEES, and how many results the gate refused.
    """
    rng = np.random.default_rng(seed)
    target = make_target()
    scenario = approach(rng, steps)
    stream = measurement_stream(scenario, target, seed=seed + 10)
    delay = rng.integers(delay_frames[0], delay_frames[1] + 1, size=len(stream))
    order = sorted(range(len(stream)), key=lambda i: (stream[i][0] + delay[i], rng.random()))
    fusion = PoseFusion(target)
    errors, nees, rejected, i = [], [], 0, 0
    for now in range(steps):
        while i < len(order) and stream[order[i]][0] + delay[order[i]] == now:
            k, m = stream[order[i]]
            if at_capture:
                e = fusion.update([m], scenario.X_CM[k], scenario.stamps[k])
            else:
                arrived = dataclasses.replace(m, stamp=scenario.stamps[now])
                e = fusion.update([arrived], scenario.X_CM[now], scenario.stamps[now])
            rejected += len(e.rejected)
            i += 1
        estimate = fusion.estimate(scenario.stamps[now])
        if now >= steps // 2:
            error = pose_error_C(scenario.X_MT[now], estimate.X_MT)
            errors.append(error)
            nees.append(error @ np.linalg.solve(estimate.covariance[:6, :6], error))
    return np.array(errors), np.array(nees), rejected


def latency_summary(seeds: int = 3) -> str:
    """Markdown: mean error and NEES of the estimate "now" when results arrive 133–167 ms late,
    fused at capture vs at arrival (``python -m tests.estimators.fusion_sim --latency``)."""
    lines = [
        "| fused at | seed | mean error δp (mm, in M) | mean error δθ (°) | NEES (6 dof) | refused |",
        "|---|---|---|---|---|---|",
    ]
    for seed in range(seeds):
        for at_capture in (True, False):
            errors, nees, rejected = delivered_late(at_capture, seed=seed)
            p = ", ".join(f"{1000 * v:.2f}" for v in errors[:, 3:].mean(axis=0))
            r = ", ".join(f"{np.degrees(v):.3f}" for v in errors[:, :3].mean(axis=0))
            where = "capture" if at_capture else "arrival"
            lines.append(f"| {where} | {seed} | {p} | {r} | {nees.mean():.1f} | {rejected} |")
    return "\n".join(lines)


def rms(values) -> float:
    """Root mean square of the finite values."""
    values = np.asarray(values, dtype=float)
    values = values[np.isfinite(values)]
    return float(np.sqrt(np.mean(values**2)))


def process_model_nees(
    params: FusionParams, runs: int = 8, steps: int = 200, seed: int = 100
) -> tuple[np.ndarray, np.ndarray]:
    """Monte Carlo NEES (runs × steps) of the 6-DOF pose and of the 12-DOF state, with the
    truth sampled from the filter's own process model (initial rates from its initial σ)."""
    target = make_target()
    nees6 = np.zeros((runs, steps))
    nees12 = np.zeros((runs, steps))
    for r in range(runs):
        rng = np.random.default_rng(seed + r)
        scenario = approach(
            rng,
            steps,
            target_motion="process",
            omega=rng.normal(scale=params.initial_angular_velocity_sigma, size=3),
            velocity=rng.normal(scale=params.initial_linear_velocity_sigma, size=3),
            angular_accel_psd=params.angular_accel_psd,
            linear_accel_psd=params.linear_accel_psd,
        )
        fused, _, estimates, _ = run(scenario, target, params, seed=seed + 100 + r)
        nees6[r] = fused["nees"]
        for k, e in enumerate(estimates):
            error = np.concatenate(
                [pose_error_C(scenario.X_MT[k], e.X_MT), scenario.V_MT[k] - e.V_MT]
            )
            nees12[r, k] = error @ np.linalg.solve(e.covariance, error)
    return nees6, nees12


def fraction_in_band(nees: np.ndarray, dof: int, probability: float = 0.95) -> float:
    """Share of steps whose mean NEES over the runs lies in its two-sided χ² band."""
    runs = nees.shape[0]
    tail = (1.0 - probability) / 2.0
    low, high = chi2.ppf([tail, 1.0 - tail], runs * dof) / runs
    per_step = nees.mean(axis=0)
    return float(np.mean((per_step >= low) & (per_step <= high)))


def summary(steps: int = 300, seed: int = 10, runs: int = 5) -> str:
    """Markdown: RMS errors of each synthetic system and of the fused estimate over four
    distance bands of the approach, and NEES figures (``python -m tests.estimators.fusion_sim``).
    """
    target = make_target()
    bands = np.array_split(np.arange(steps), 4)
    errors: dict[tuple[str, str], list[np.ndarray]] = {}
    nees = []
    for r in range(runs):
        scenario = approach(np.random.default_rng(seed + r), steps)
        fused, single, _, _ = run(scenario, target, seed=seed + 100 + r)
        nees.append(fused["nees"])
        rows = {**single, "fused": fused}
        rows["fused (ring centre / normal)"] = {"t": fused["center"], "r": fused["normal"]}
        for name, row in rows.items():
            errors.setdefault((name, "t"), []).append(row["t"])
            errors.setdefault((name, "r"), []).append(row["r"])
    distances = [2.5 + (0.6 - 2.5) * b.mean() / (steps - 1) for b in bands]
    lines = ["| system | " + " | ".join(f"~{d:.1f} m" for d in distances) + " |"]
    lines.append("|---" * (len(bands) + 1) + "|")
    for name in ("corners", "lines", "fused", "ellipses", "fused (ring centre / normal)"):
        t = np.array(errors[(name, "t")])
        r = np.array(errors[(name, "r")])
        cells = [f"{1000 * rms(t[:, b]):.2f} mm / {np.degrees(rms(r[:, b])):.2f}°" for b in bands]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines.append(
        f"\nstatic target, {runs} runs × {steps} steps: fused pose NEES mean "
        f"{np.nanmean(nees):.2f} (6 dof)"
    )
    nees6, nees12 = process_model_nees(FusionParams())
    for values, dof in ((nees6, 6), (nees12, 12)):
        lines.append(
            f"truth from the process model, 8 runs × 200 steps: {dof}-dof NEES mean "
            f"{values.mean():.2f}, per-step mean inside its 95 % χ² band at "
            f"{100 * fraction_in_band(values, dof):.1f} % of steps"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    import sys

    print(latency_summary() if "--latency" in sys.argv[1:] else summary())
