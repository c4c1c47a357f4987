"""What a trial log says about the trial: errors against ground truth, measurement outcomes,
phases, commands and a summary — computed from the log alone (``hil.logs.triallog.TrialLog``).

Errors are judged only against the simulator ground truth logged with each tick, with
``hil.evaluation.errors.measurement_error`` for the measurements (6-DOF: translation and the
reference's roll/pitch/yaw-norm rotation error; 5-DOF circles: centre and normal errors) and
the same metrics from ``estimators.geometry`` for the fused estimate. A log from real hardware
has no truth: its error fields are empty and ``has_truth`` is False.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from configuration.mockup import MockupConfig
from estimators.geometry import Pose, normal_angle, rotation_error_rpy_norm, translation_error
from estimators.measurement import SYSTEMS, Measurement
from estimators.target import TargetModel
from hil.evaluation.errors import measurement_error
from hil.logs.triallog import TrialLog

FUSED = "fused"
#: Per-tick outcome of a system's measurement.
STATUSES = ("accepted", "rejected", "unused", "lost", "absent")


@dataclass(frozen=True, slots=True)
class ErrorStats:
    """Median and 95th percentile of errors (NaN when there are none)."""

    count: int
    median: float
    p95: float

    @staticmethod
    def of(values: np.ndarray) -> ErrorStats:
        finite = values[np.isfinite(values)]
        if finite.size == 0:
            return ErrorStats(0, math.nan, math.nan)
        return ErrorStats(
            int(finite.size), float(np.median(finite)), float(np.percentile(finite, 95))
        )


@dataclass(frozen=True, slots=True)
class SystemSummary:
    """One system (or the fused estimate) over the trial.

    Rates are over the ticks where the system ran (``ticks``). ``fused_better`` is the
    fraction of the ticks with both errors where the fused position error was smaller.
    """

    name: str
    ticks: int
    valid: int
    accepted: int
    rejected: int
    lost: int
    five_dof: bool
    position_m: ErrorStats
    attitude_rad: ErrorStats
    fused_better_position: float = math.nan
    fused_better_attitude: float = math.nan

    @property
    def valid_rate(self) -> float:
        return self.valid / self.ticks if self.ticks else math.nan

    @property
    def accepted_rate(self) -> float:
        return self.accepted / self.ticks if self.ticks else math.nan


@dataclass(frozen=True, slots=True)
class StandoffState:
    """The last stand-off tick: where the camera really was (from truth) and the fused
    estimate's error there; truth fields are NaN without ground truth."""

    t: float
    range_m: float  # from the estimate
    true_depth_m: float  # z of the ring centre in C
    true_lateral_m: float  # ring centre off the optical axis
    true_misalignment_rad: float  # optical axis vs the ring's normal
    fused_position_error_m: float
    fused_attitude_error_rad: float


@dataclass(frozen=True)
class TrialAnalysis:
    """Per-tick series (arrays over ticks) and the summary of one trial log."""

    path: str
    header: dict[str, Any]
    recovered: bool
    complete: bool
    t: np.ndarray
    tick: np.ndarray
    phases: tuple[str, ...]
    range_m: np.ndarray
    true_depth_m: np.ndarray | None
    systems: tuple[str, ...]
    status: dict[str, np.ndarray]
    five_dof: frozenset[str]
    has_truth: bool
    position_error_m: dict[str, np.ndarray]
    attitude_error_rad: dict[str, np.ndarray]
    linear_speed: np.ndarray
    angular_speed: np.ndarray
    track_velocity: np.ndarray
    stop: np.ndarray
    events: list[dict[str, Any]]
    outcome: str
    abort_reason: str | None
    summaries: tuple[SystemSummary, ...]
    fused: SystemSummary | None
    fused_below_all: tuple[float, float, int]  # position fraction, attitude fraction, ticks
    standoff: StandoffState | None
    notes: list[str] = field(default_factory=list)
    #: The same on 1 s medians: per 1 s window, the fused median error against every system's
    #: median (position fraction, attitude fraction, windows).
    fused_below_all_1s: tuple[float, float, int] = (math.nan, math.nan, 0)

    @property
    def duration_s(self) -> float:
        finite = self.t[np.isfinite(self.t)]
        return float(finite[-1] - finite[0]) if finite.size else 0.0


def phase_spans(t: np.ndarray, phases: Sequence[str]) -> list[tuple[str, float, float]]:
    """Consecutive runs of one phase as (phase, start, end) times; a run ends where the next
    begins (the last at its last tick)."""
    spans: list[tuple[str, float, float]] = []
    for i, phase in enumerate(phases):
        if not spans or spans[-1][0] != phase:
            if spans:
                spans[-1] = (spans[-1][0], spans[-1][1], float(t[i]))
            spans.append((phase, float(t[i]), float(t[i])))
        else:
            spans[-1] = (phase, spans[-1][1], float(t[i]))
    return spans


def target_from_header(header: dict[str, Any]) -> TargetModel | None:
    """The target geometry of the mock-up embedded in the log's configuration
    (``config.mockup``, a ``MockupConfig`` dump), or None when it is not there."""
    mockup = (header.get("config") or {}).get("mockup")
    if not isinstance(mockup, dict):
        return None
    try:
        return MockupConfig.model_validate(mockup).target_model()
    except ValueError:
        return None


def _pose(value: Any) -> Pose | None:
    if value is None:
        return None
    try:
        return Pose.from_matrix(np.asarray(value, dtype=float), orthonormalize=True)
    except (ValueError, TypeError):
        return None


def _number(value: Any) -> float:
    return (
        float(value) if isinstance(value, int | float) and not isinstance(value, bool) else math.nan
    )


def _ordered_systems(seen: Iterable[str]) -> tuple[str, ...]:
    seen = list(dict.fromkeys(seen))
    return tuple([s for s in SYSTEMS if s in seen] + [s for s in seen if s not in SYSTEMS])


def analyse(log: TrialLog) -> TrialAnalysis:
    """Read every tick and event of ``log`` and compute the series and summary."""
    ticks = list(log.ticks())
    events = list(log.events())
    notes: list[str] = []
    target = target_from_header(log.header)
    systems = _ordered_systems(
        m.get("system", "?") for tick in ticks for m in tick.get("measurements") or []
    )
    n = len(ticks)
    status = {s: np.full(n, "absent", dtype=object) for s in systems}
    names = (*systems, FUSED)
    position = {name: np.full(n, math.nan) for name in names}
    attitude = {name: np.full(n, math.nan) for name in names}
    five_dof: set[str] = set()
    has_truth = any(tick.get("truth") for tick in ticks)
    unreadable = 0
    skipped_5dof = 0
    for i, tick in enumerate(ticks):
        estimate = tick.get("estimate") or {}
        accepted = set(estimate.get("accepted") or [])
        rejected = {r.get("system") for r in estimate.get("rejected") or [] if isinstance(r, dict)}
        X_CT_true = _pose((tick.get("truth") or {}).get("X_CT"))
        for record in tick.get("measurements") or []:
            system = record.get("system", "?")
            if record.get("status") == "lost":
                status[system][i] = "lost"
                continue
            status[system][i] = (
                "accepted" if system in accepted else "rejected" if system in rejected else "unused"
            )
            if record.get("X_CT") is None and record.get("center_C") is not None:
                five_dof.add(system)
            if X_CT_true is None:
                continue
            if target is None and record.get("circle") is not None:
                skipped_5dof += 1
                record = {**record, "circle": None, "center_C": None, "normal_C": None}
                if record.get("X_CT") is None:
                    continue
            try:
                error = measurement_error(Measurement.from_dict(record), X_CT_true, target)
            except (ValueError, KeyError, TypeError):
                unreadable += 1
                continue
            position[system][i] = error.position_m
            attitude[system][i] = error.attitude_rad
        X_CT_fused = _pose(estimate.get("X_CT"))
        if X_CT_true is not None and X_CT_fused is not None:
            position[FUSED][i] = translation_error(X_CT_true, X_CT_fused)
            attitude[FUSED][i] = rotation_error_rpy_norm(X_CT_true, X_CT_fused)
    if not has_truth:
        notes.append(
            "No ground truth in this log (real hardware): error plots and statistics skipped."
        )
    if skipped_5dof:
        notes.append(
            f"{skipped_5dof} circle (5-DOF) measurements not judged: the log's configuration "
            "holds no mock-up geometry (config.mockup)."
        )
    if unreadable:
        notes.append(f"{unreadable} measurements could not be read back and were not judged.")
    if log.recovered:
        notes.append(
            f"The log has no footer (its writer was killed): read up to the last flush; {log.stopped}."
        )
    elif not log.complete:
        notes.append("The log was not closed by its writer (a recovered copy).")

    t = np.array([_number(tick.get("t")) for tick in ticks])
    phases = tuple(str(tick.get("phase", "?")) for tick in ticks)
    commands = [tick.get("command") or {} for tick in ticks]
    V = np.array(
        [
            np.asarray(c.get("V_BE"), dtype=float)
            if isinstance(c.get("V_BE"), list) and len(c["V_BE"]) == 6 and None not in c["V_BE"]
            else np.full(6, math.nan)
            for c in commands
        ]
    ).reshape(n, 6)
    truths = [_pose((tick.get("truth") or {}).get("X_CT")) for tick in ticks]
    true_depth = (
        np.array([X.p[2] if X is not None else math.nan for X in truths]) if has_truth else None
    )

    summaries = tuple(
        _summary(s, status[s], s in five_dof, position, attitude, has_truth) for s in systems
    )
    fused = _fused_summary(ticks, position, attitude) if n else None
    outcome, abort_reason = _outcome(phases, events, commands, log.complete)
    analysis = TrialAnalysis(
        path=str(log.path),
        header=log.header,
        recovered=log.recovered,
        complete=log.complete,
        t=t,
        tick=np.array([_number(tick.get("tick")) for tick in ticks]),
        phases=phases,
        range_m=np.array([_number(tick.get("range_m")) for tick in ticks]),
        true_depth_m=true_depth,
        systems=systems,
        status=status,
        five_dof=frozenset(five_dof),
        has_truth=has_truth,
        position_error_m=position if has_truth else {},
        attitude_error_rad=attitude if has_truth else {},
        linear_speed=np.linalg.norm(V[:, :3], axis=1),
        angular_speed=np.linalg.norm(V[:, 3:], axis=1),
        track_velocity=np.array(
            [_number((tick.get("track") or {}).get("velocity")) for tick in ticks]
        ),
        stop=np.array([bool(c.get("stop")) for c in commands], dtype=bool),
        events=events,
        outcome=outcome,
        abort_reason=abort_reason,
        summaries=summaries,
        fused=fused,
        fused_below_all_1s=_fused_below_all_windowed(t, systems, position, attitude)
        if has_truth
        else (math.nan, math.nan, 0),
        fused_below_all=_fused_below_all(systems, position, attitude)
        if has_truth
        else (math.nan, math.nan, 0),
        standoff=_standoff(ticks, truths, position, attitude),
        notes=notes,
    )
    return analysis


def _summary(
    system: str,
    status: np.ndarray,
    five_dof: bool,
    position: dict[str, np.ndarray],
    attitude: dict[str, np.ndarray],
    has_truth: bool,
) -> SystemSummary:
    ran = status != "absent"

    def better(errors: dict[str, np.ndarray]) -> float:
        both = np.isfinite(errors[system]) & np.isfinite(errors[FUSED])
        if not has_truth or not both.any():
            return math.nan
        return float(np.mean(errors[FUSED][both] < errors[system][both]))

    return SystemSummary(
        name=system,
        ticks=int(ran.sum()),
        valid=int(np.isin(status, ("accepted", "rejected", "unused")).sum()),
        accepted=int((status == "accepted").sum()),
        rejected=int((status == "rejected").sum()),
        lost=int((status == "lost").sum()),
        five_dof=five_dof,
        position_m=ErrorStats.of(position[system]),
        attitude_rad=ErrorStats.of(attitude[system]),
        fused_better_position=better(position),
        fused_better_attitude=better(attitude),
    )


def _fused_summary(
    ticks: list[dict], position: dict[str, np.ndarray], attitude: dict[str, np.ndarray]
) -> SystemSummary:
    """The fused estimate over the ticks where estimators ran or an estimate existed:
    ``valid`` ticks had a pose, ``lost`` ones none."""
    has = np.array([_pose((tick.get("estimate") or {}).get("X_CT")) is not None for tick in ticks])
    ran = has | np.array([bool(tick.get("measurements")) for tick in ticks])
    return SystemSummary(
        name=FUSED,
        ticks=int(ran.sum()),
        valid=int(has.sum()),
        accepted=int(has.sum()),
        rejected=0,
        lost=int((ran & ~has).sum()),
        five_dof=False,
        position_m=ErrorStats.of(position[FUSED]),
        attitude_rad=ErrorStats.of(attitude[FUSED]),
    )


def _fused_below_all(
    systems: Sequence[str], position: dict[str, np.ndarray], attitude: dict[str, np.ndarray]
) -> tuple[float, float, int]:
    """Fraction of the ticks with a fused error and at least one system error where the fused
    error is below every system's at that tick (position, attitude), and how many ticks."""
    if not systems:
        return math.nan, math.nan, 0

    def fraction(errors: dict[str, np.ndarray]) -> tuple[float, int]:
        best = np.fmin.reduce([errors[s] for s in systems])  # NaN only where all are NaN
        compared = np.isfinite(best) & np.isfinite(errors[FUSED])
        if not compared.any():
            return math.nan, 0
        return float(np.mean(errors[FUSED][compared] < best[compared])), int(compared.sum())

    p, count = fraction(position)
    a, _ = fraction(attitude)
    return p, a, count


def _fused_below_all_windowed(
    t: np.ndarray,
    systems: Sequence[str],
    position: dict[str, np.ndarray],
    attitude: dict[str, np.ndarray],
    window_s: float = 1.0,
    min_samples: int = 3,
) -> tuple[float, float, int]:
    """Per ``window_s`` window: is the fused estimate's median error below the median error of
    every system with at least ``min_samples`` estimates in the window? (A single estimator's
    error crosses zero now and then; medians compare accuracy, not luck.)"""
    if not systems or len(t) == 0:
        return math.nan, math.nan, 0
    edges = np.arange(t[0], t[-1] + window_s, window_s)
    index = np.digitize(t, edges)

    def fraction(errors: dict[str, np.ndarray]) -> tuple[float, int]:
        wins = []
        for w in np.unique(index):
            inside = index == w
            fused = errors[FUSED][inside]
            fused = fused[np.isfinite(fused)]
            others = []
            for s in systems:
                e = errors[s][inside]
                e = e[np.isfinite(e)]
                if len(e) >= min_samples:
                    others.append(np.median(e))
            if len(fused) >= min_samples and others:
                wins.append(np.median(fused) < min(others))
        return (float(np.mean(wins)), len(wins)) if wins else (math.nan, 0)

    p, count = fraction(position)
    a, _ = fraction(attitude)
    return p, a, count


def _outcome(
    phases: Sequence[str], events: list[dict], commands: list[dict], complete: bool
) -> tuple[str, str | None]:
    abort_events = [e for e in events if e.get("kind") == "abort"]
    if "abort" in phases or abort_events:
        if abort_events:
            return "aborted", str(abort_events[0].get("message", ""))
        first = phases.index("abort")
        reason = commands[first].get("reason") or None
        faults = [e for e in events if e.get("kind") == "fault"]
        return "aborted", reason or (str(faults[0].get("message")) if faults else None)
    if phases and phases[-1] == "done":
        return "completed", None
    if not complete:
        return (
            f"cut off in phase {phases[-1] if phases else 'none'} (the writer did not close the log)",
            None,
        )
    return f"ended in phase {phases[-1] if phases else 'none'}", None


def _standoff(
    ticks: list[dict],
    truths: list[Pose | None],
    position: dict[str, np.ndarray],
    attitude: dict[str, np.ndarray],
) -> StandoffState | None:
    indices = [i for i, tick in enumerate(ticks) if tick.get("phase") == "standoff"]
    if not indices:
        return None
    i = indices[-1]
    X_CT = truths[i]
    nan = math.nan
    return StandoffState(
        t=_number(ticks[i].get("t")),
        range_m=_number(ticks[i].get("range_m")),
        true_depth_m=X_CT.p[2] if X_CT is not None else nan,
        true_lateral_m=float(np.hypot(*X_CT.p[:2])) if X_CT is not None else nan,
        true_misalignment_rad=normal_angle(-X_CT.R[:, 2], np.array([0.0, 0.0, 1.0]))
        if X_CT is not None
        else nan,
        fused_position_error_m=position[FUSED][i],
        fused_attitude_error_rad=attitude[FUSED][i],
    )
