"""A synthetic but realistic approach trial for tests of logs, reports and comparisons.

The camera closes from 2.5 m to a 0.5 m stand-off in front of the default mock-up (target at
the world origin, slightly displaced and turned), holds, grasps and retreats. Three systems
measure the target with known, distance-dependent errors — ``corners`` and ``lines`` give
6-DOF poses, ``ellipses`` the 5-DOF pose of ``ring_outer`` — and a fused estimate whose error
is 0.3–0.7 × the smallest error of the measurements valid at that tick (or, when the gate
accepted none, coasts and grows by 20 % per tick). Some measurements are lost and some
``lines`` outliers are rejected by the fusion gate.

Every injected error is returned (``SyntheticTrial.errors``), so analyses can be checked
against what was put in rather than against themselves. Deterministic for a seed.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from configuration.camera import load_camera
from configuration.mockup import load_mockup
from estimators.geometry import Pose
from estimators.measurement import Measurement
from hil.evaluation.scenarios import camera_pose_for, target_offset
from hil.logs.triallog import TrialLogWriter

SYSTEMS = ("corners", "lines", "ellipses")
#: 1σ-ish error scales: position (m) = k_p·d², attitude (rad) = k_θ·d, d in m.
ERROR_SCALES = {
    "corners": (0.003, math.radians(0.5)),
    "lines": (0.005, math.radians(0.8)),
    "ellipses": (0.002, math.radians(0.3)),
}
STANDOFF_M = 0.5
START_M = 2.5
#: Phase schedule: (phase, duration in s); approach lasts until the stand-off is reached.
SCHEDULE = (
    ("idle", 0.5),
    ("acquire", 1.0),
    ("approach", 16.0),
    ("standoff", 2.0),
    ("grasp", 1.0),
    ("retreat", 1.5),
    ("done", 0.0),
)


@dataclass
class SyntheticTrial:
    """Ticks and events as the sequencer would log them, and the errors injected per tick:
    ``errors[name]`` = (position error (m), attitude error (rad)) arrays over ticks, NaN where
    ``name`` (a system or ``fused``) gave nothing. ``status[system]`` per tick is one of
    accepted / rejected / lost / absent."""

    header: dict[str, Any]
    ticks: list[dict[str, Any]] = field(default_factory=list)
    events: list[tuple[float, str, str, dict]] = field(default_factory=list)
    errors: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    status: dict[str, list[str]] = field(default_factory=dict)


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _perturb(X: Pose, position_m: float, angle_rad: float, rng: np.random.Generator) -> Pose:
    """``X`` moved by ``position_m`` and turned by ``angle_rad`` (left-multiplied, in C)."""
    R = Rotation.from_rotvec(_unit(rng) * angle_rad).as_matrix() @ X.R
    return Pose(R, X.p + _unit(rng) * position_m)


def _turn(normal: np.ndarray, angle_rad: float, rng: np.random.Generator) -> np.ndarray:
    axis = np.cross(normal, _unit(rng))
    axis /= np.linalg.norm(axis)
    return Rotation.from_rotvec(axis * angle_rad).as_matrix() @ normal


def _distance(t_in_approach: float, duration: float) -> float:
    """Smooth (cosine) closing from START_M to STANDOFF_M."""
    s = min(max(t_in_approach / duration, 0.0), 1.0)
    return STANDOFF_M + (START_M - STANDOFF_M) * 0.5 * (1.0 + math.cos(math.pi * s))


def _phase_at(t: float) -> tuple[str, float]:
    start = 0.0
    for phase, duration in SCHEDULE:
        if t < start + duration or duration == 0.0:
            return phase, t - start
        start += duration
    return "done", 0.0


def make_trial(
    *,
    seed: int = 0,
    rate_hz: float = 10.0,
    with_truth: bool = True,
    abort_at_s: float | None = None,
    lost_probability: float = 0.03,
    outlier_probability: float = 0.04,
) -> SyntheticTrial:
    """Generate the trial (see the module docstring). ``abort_at_s`` ends it with an abort
    (stop commanded, ``abort`` event) at that time instead of completing."""
    rng = np.random.default_rng(seed)
    mockup = load_mockup("default")
    ring = mockup.target_model().circle("ring_outer")
    header = {
        "config": {
            "mockup": mockup.model_dump(mode="json"),
            "camera": load_camera("reference").model_dump(mode="json"),
            "sequencer": {"rate_hz": rate_hz, "standoff_m": STANDOFF_M},
            "backend": "sim" if with_truth else "real",
        },
        "seed": seed,
        "notes": "synthetic approach (tests/hil/synthetic_log.py)",
    }
    trial = SyntheticTrial(header=header)
    names = (*SYSTEMS, "fused")
    position = {n: [] for n in names}
    attitude = {n: [] for n in names}
    trial.status = {s: [] for s in SYSTEMS}
    offset = target_offset(0.03, -0.02, 0.0, math.radians(2.0), math.radians(-3.0), 0.04)
    total = sum(d for _, d in SCHEDULE)
    n_ticks = round(total * rate_hz) + 1
    previous_phase, fused_error = None, (0.02, 0.02)
    distance = START_M
    for tick in range(n_ticks):
        t = tick / rate_hz
        phase, t_phase = _phase_at(t)
        if abort_at_s is not None and t >= abort_at_s:
            phase = "abort"
        if phase == "approach":
            distance = _distance(t_phase, SCHEDULE[2][1])
        elif phase == "retreat":
            distance = STANDOFF_M + 0.15 * t_phase
        elif phase in ("standoff", "grasp"):
            distance = STANDOFF_M
        X_WC, X_CT = camera_pose_for(distance, offset)
        if phase != previous_phase:
            if previous_phase is not None:
                trial.events.append(
                    (
                        t,
                        "phase",
                        f"{previous_phase} → {phase}",
                        {"from": previous_phase, "to": phase},
                    )
                )
            if phase == "abort":
                trial.events.append(
                    (t, "abort", "estimate too old: 0.41 s > 0.30 s", {"age_s": 0.41})
                )
            previous_phase = phase

        measurements, accepted, rejected = [], [], []
        errors_now: dict[str, tuple[float, float]] = {}
        active = phase not in ("idle", "done")
        for system in SYSTEMS:
            if not active:
                trial.status[system].append("absent")
                errors_now[system] = (math.nan, math.nan)
                continue
            k_p, k_theta = ERROR_SCALES[system]
            e_p = k_p * distance**2 * float(np.linalg.norm(rng.normal(size=3)))
            e_theta = k_theta * distance * float(np.linalg.norm(rng.normal(size=3)))
            outlier = system == "lines" and rng.random() < outlier_probability
            if outlier:
                e_p, e_theta = 10 * e_p + 0.05, 10 * e_theta + math.radians(5)
            time_ms = float(rng.uniform(3.0, 12.0))
            if rng.random() < lost_probability:
                m = Measurement(
                    system,
                    "lost",
                    t,
                    tick,
                    reason="no candidate passed the checks",
                    time_ms=time_ms,
                )
                trial.status[system].append("lost")
                errors_now[system] = (math.nan, math.nan)
                measurements.append(m.to_dict())
                continue
            status = "acquired" if phase == "acquire" and t_phase == 0.0 else "tracking"
            if system == "ellipses":
                center_true = X_CT.apply(ring.center_T)
                normal_true = X_CT.R @ ring.normal_T
                m = Measurement(
                    system,
                    status,
                    t,
                    tick,
                    circle="ring_outer",
                    center_C=center_true + _unit(rng) * e_p,
                    normal_C=_turn(normal_true, e_theta, rng),
                    covariance_5dof=np.diag(
                        [(k_p * distance**2) ** 2] * 3 + [(k_theta * distance) ** 2] * 2
                    ),
                    residual_px=float(rng.uniform(0.1, 0.4)),
                    time_ms=time_ms,
                )
            else:
                m = Measurement(
                    system,
                    status,
                    t,
                    tick,
                    X_CT=_perturb(X_CT, e_p, e_theta, rng),
                    covariance=np.diag(
                        [(k_theta * distance) ** 2] * 3 + [(k_p * distance**2) ** 2] * 3
                    ),
                    residual_px=float(rng.uniform(0.2, 0.6)) * (8 if outlier else 1),
                    time_ms=time_ms,
                )
            measurements.append(m.to_dict())
            errors_now[system] = (e_p, e_theta)
            if outlier:
                rejected.append(
                    {"system": system, "reason": "Mahalanobis distance 31.2 > gate 16.8"}
                )
                trial.status[system].append("rejected")
            else:
                accepted.append(system)
                trial.status[system].append("accepted")

        valid = [errors_now[s] for s in SYSTEMS if not math.isnan(errors_now[s][0])]
        if not active:
            estimate, fused_now = None, (math.nan, math.nan)
        else:
            if accepted:  # fused: better than every valid measurement of this tick
                factor = float(rng.uniform(0.3, 0.7))
                fused_error = (factor * min(e[0] for e in valid), factor * min(e[1] for e in valid))
                health = "ok"
            else:  # nothing fused: the estimate coasts and its error grows
                fused_error = (fused_error[0] * 1.2, fused_error[1] * 1.2)
                health = "coasting"
            X_CT_fused = _perturb(X_CT, fused_error[0], fused_error[1], rng)
            estimate = {
                "health": health,
                "X_CT": X_CT_fused,
                "X_MT": X_CT_fused,  # the mock-up does not ride a track in this trial
                "covariance": np.diag([1e-6] * 3 + [1e-6] * 3),
                "accepted": accepted,
                "rejected": rejected,
                "age_s": 0.0 if accepted else 1.0 / rate_hz,
            }
            fused_now = fused_error
        for name in SYSTEMS:
            position[name].append(errors_now[name][0])
            attitude[name].append(errors_now[name][1])
        position["fused"].append(fused_now[0])
        attitude["fused"].append(fused_now[1])

        closing = 0.0
        if phase == "approach":
            closing = (
                (START_M - STANDOFF_M)
                * math.pi
                / (2 * SCHEDULE[2][1])
                * math.sin(math.pi * t_phase / SCHEDULE[2][1])
            )
        stop = phase in ("abort", "done", "idle")
        V_BE = np.zeros(6) if stop else np.array([0.002, -0.001, 0.2 * closing, 0.0, 0.0, 0.003])
        trial.ticks.append(
            {
                "t": t,
                "tick": tick,
                "phase": phase,
                "range_m": None if estimate is None else float(estimate["X_CT"].p[2]),
                "measurements": measurements,
                "estimate": estimate,
                "command": {
                    "V_BE": V_BE,
                    "stop": stop,
                    "reason": "estimate too old" if phase == "abort" else "",
                },
                "arm": {
                    "q": np.array([0.0, -1.2, 1.4, -0.2, 1.57, 0.0]) + 0.01 * t,
                    "X_BE": Pose(np.eye(3), np.array([0.4, 0.0, 0.5 + 0.002 * t])),
                    "V_BE": V_BE,
                    "protective_stop": False,
                    "fault": None,
                },
                "track": {"position": START_M - distance, "velocity": 0.8 * closing, "fault": None},
                "gripper": {
                    "position": 1.0 if phase in ("grasp", "retreat", "done") else 0.0,
                    "object_detected": phase in ("grasp", "retreat", "done"),
                },
                "truth": {"X_CT": X_CT, "X_WT": Pose.identity(), "X_WC": X_WC}
                if with_truth
                else None,
                "timing_ms": {
                    "estimators": {m["system"]: m["time_ms"] for m in measurements},
                    "fusion": 0.4,
                    "tick": 20.0,
                },
            }
        )
        if phase in ("abort", "done") and (phase == "done" or t - abort_at_s >= 0.5):
            break
    trial.errors = {n: (np.array(position[n]), np.array(attitude[n])) for n in names}
    return trial


def synthetic_frame(range_m: float | None, *, width: int = 160, height: int = 120) -> np.ndarray:
    """A small grey image with the ring drawn at the size it has at ``range_m``."""
    image = np.full((height, width), 40, np.uint8)
    if range_m:
        radius = int(min(0.6 * width, 0.3 * 0.5 * width / max(range_m, 0.1)))
        cv2.circle(image, (width // 2, height // 2), radius, 200, 3)
    return image


def write_trial(
    path: str | Path,
    trial: SyntheticTrial,
    *,
    frames_every: int = 0,
    flush_interval_s: float = 1.0,
    trial_clock: bool = False,
    close: bool = True,
) -> TrialLogWriter:
    """Write ``trial`` to an MCAP trial log (frames every ``frames_every`` ticks, 0: none).
    ``trial_clock`` makes the writer flush on the trial's own time (as a simulation running
    faster than real time would) instead of the wall clock."""
    now = [0.0]
    clock = (lambda: now[0]) if trial_clock else time.monotonic
    writer = TrialLogWriter(path, trial.header, flush_interval_s=flush_interval_s, clock=clock)
    events = sorted(trial.events, key=lambda e: e[0])
    for record in trial.ticks:
        now[0] = record["t"]
        while events and events[0][0] <= record["t"]:
            t, kind, message, data = events.pop(0)
            writer.write_event(t, kind, message, **data)
        writer.write_tick(record)
        if frames_every and record["tick"] % frames_every == 0:
            writer.write_frame(record["t"], synthetic_frame(record["range_m"]))
    for t, kind, message, data in events:
        writer.write_event(t, kind, message, **data)
    if close:
        writer.close()
    return writer
