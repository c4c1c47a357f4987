"""What a trial log says about the trial: errors against ground truth, what fusion made of each
estimator result, phases, commands, the control loop's timing, the vision pipeline's figures
and a summary — computed from the log alone (``hil.logs.triallog.TrialLog``, typed records of
``hil.logs.records``).

Two streams, two time bases. Each estimator result (a ``VisionRecord``) is judged against the
truth of the instant its frame was captured (``truth_X_CT``): the camera moves at up to
0.25 m/s, so judging it against the truth of the tick that received it, 150 ms later, would
add centimetres that are not the estimator's. The fused estimate is judged at each control
tick (a ``TickRecord``) against the tick's truth. Where the two are compared, a result stands
at its capture time and the fused estimate at the tick nearest that time.

Errors use ``hil.evaluation.errors.measurement_error`` for the results (6-DOF: translation and
the reference's roll/pitch/yaw-norm rotation error; 5-DOF circles: centre and normal errors)
and the same metrics from ``estimators.geometry`` for the fused estimate. A log from real
hardware has no truth: its error fields are NaN and ``has_truth`` is False.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from configuration.mockup import MockupConfig
from estimators.geometry import normal_angle
from estimators.measurement import SYSTEMS
from estimators.target import TargetModel
from hil.evaluation.errors import measurement_error
from hil.logs.records import TickRecord, VisionRecord
from hil.logs.triallog import TrialLog

FUSED = "fused"
#: What fusion made of an estimator result (``VisionRecord.outcome``).
OUTCOMES = ("accepted", "rejected", "not_measured", "stale")


@dataclass(frozen=True, slots=True)
class Spread:
    """Count, median, 95th and 99th percentiles and maximum of the finite values (NaN when
    there are none)."""

    count: int
    median: float
    p95: float
    p99: float
    max: float

    @staticmethod
    def of(values: Iterable[float]) -> Spread:
        array = np.asarray(values if isinstance(values, np.ndarray) else list(values), float)
        finite = array[np.isfinite(array)]
        if finite.size == 0:
            return Spread(0, math.nan, math.nan, math.nan, math.nan)
        p50, p95, p99 = np.percentile(finite, [50, 95, 99])
        return Spread(int(finite.size), float(p50), float(p95), float(p99), float(finite.max()))


@dataclass(frozen=True)
class SystemSeries:
    """One estimator's results over the trial, in capture order: capture time and the time it
    was handed to fusion (s), whether the estimator measured (``valid``: not lost), outcome,
    errors against the truth at capture (NaN when lost or without truth), latency capture →
    fusion and processing time (ms), and the frame."""

    name: str
    seq: np.ndarray
    capture_t: np.ndarray
    t: np.ndarray
    valid: np.ndarray
    outcome: np.ndarray
    position_error_m: np.ndarray
    attitude_error_rad: np.ndarray
    latency_ms: np.ndarray
    processing_ms: np.ndarray
    five_dof: bool


@dataclass(frozen=True, slots=True)
class SystemSummary:
    """One system (or the fused estimate) over the trial.

    For a system: ``results`` it handed over, ``valid`` ones (measured, not lost), what
    fusion made of them (``not_measured``: it took no measurement from the result, normally a
    lost one), error statistics, latency capture → fusion over the results that reached fusion
    (not stale), processing time, and ``fused_better_*``: the fraction of its judged results
    where the fused estimate, at the tick nearest the capture, had the smaller error. For
    ``fused``:
    ``results`` = ticks since the first result reached fusion, ``valid`` = those with a pose,
    ``not_measured`` = those without."""

    name: str
    results: int
    valid: int
    accepted: int
    rejected: int
    not_measured: int
    stale: int
    five_dof: bool
    position_m: Spread
    attitude_rad: Spread
    latency_ms: Spread
    processing_ms: Spread
    fused_better_position: float = math.nan
    fused_better_attitude: float = math.nan

    @property
    def valid_rate(self) -> float:
        return self.valid / self.results if self.results else math.nan

    @property
    def accepted_rate(self) -> float:
        return self.accepted / self.results if self.results else math.nan


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


@dataclass(frozen=True, slots=True)
class TimingSummary:
    """The control loop's wall-clock timing (``TickRecord.timing``): the nominal period (from
    the outcome event, else the configuration; NaN when neither says), the measured period
    and tick work (ms), and the ticks that missed their deadline."""

    nominal_period_ms: float
    period_ms: Spread
    work_ms: Spread
    late_ms: Spread
    deadline_misses: int
    #: The longest tick's work and the control thread's CPU time over it (ms; NaN when the log
    #: has no CPU time): equal when the thread ran throughout, far apart when it waited.
    longest_work_ms: float = math.nan
    longest_cpu_ms: float = math.nan


@dataclass(frozen=True, slots=True)
class VisionSummary:
    """The vision pipeline: frame counts from the last tick's counters, results discarded as
    stale (counter and records), and the latency capture → fusion over every result that
    reached fusion."""

    frames_received: int
    frames_processed: int
    frames_dropped: int
    results_stale: int
    stale_records: int
    latency_ms: Spread


@dataclass(frozen=True)
class TrialAnalysis:
    """Per-tick series (arrays over ticks), per-system series (over each system's results),
    and the summary of one trial log."""

    path: str
    header: dict[str, Any]
    recovered: bool
    complete: bool
    #: Parts of the file do not read (the rest was read): ``incomplete`` says which.
    corrupt: bool
    #: Why the log does not hold the whole trial (None when its writer closed it).
    incomplete: str | None
    # over ticks
    t: np.ndarray
    tick: np.ndarray
    phases: tuple[str, ...]
    range_m: np.ndarray
    true_depth_m: np.ndarray | None
    fused_position_error_m: np.ndarray
    fused_attitude_error_rad: np.ndarray
    linear_speed: np.ndarray
    angular_speed: np.ndarray
    track_velocity: np.ndarray  # commanded
    track_velocity_measured: np.ndarray
    stop: np.ndarray
    period_ms: np.ndarray
    work_ms: np.ndarray
    cpu_ms: np.ndarray  # NaN where the log has none
    deadline_miss: np.ndarray
    # over each system's results
    systems: tuple[str, ...]
    series: dict[str, SystemSeries]
    has_truth: bool
    events: list[dict[str, Any]]
    outcome: str
    abort_reason: str | None
    #: The end-of-trial ``outcome`` event's data (empty when the log has none: a crash).
    outcome_data: dict[str, Any]
    success: bool
    summaries: tuple[SystemSummary, ...]
    fused: SystemSummary | None
    #: Per frame with a fused error at its capture and at least one judged result: the
    #: fraction where the fused error was below every system's (position, attitude), frames.
    fused_below_all: tuple[float, float, int]
    #: The same on 1 s medians: per 1 s window, the fused median error (ticks in the window)
    #: against every system's median (results captured in the window).
    fused_below_all_1s: tuple[float, float, int]
    standoff: StandoffState | None
    timing: TimingSummary
    vision: VisionSummary
    notes: list[str] = field(default_factory=list)

    @property
    def five_dof(self) -> frozenset[str]:
        return frozenset(name for name, s in self.series.items() if s.five_dof)

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


def nominal_period_s(header: dict[str, Any], outcome_data: dict[str, Any]) -> float:
    """The nominal control period: the outcome event's ``control_period_s``, else from the
    configuration's ``approach.servo.control_rate_hz``; NaN when neither says."""
    period = outcome_data.get("control_period_s")
    if _is_number(period) and period > 0:
        return float(period)
    config = header.get("config") or {}
    rate = ((config.get("approach") or {}).get("servo") or {}).get("control_rate_hz")
    return 1.0 / rate if _is_number(rate) and rate > 0 else math.nan


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _ordered_systems(seen: Iterable[str]) -> tuple[str, ...]:
    seen = list(dict.fromkeys(seen))
    return tuple([s for s in SYSTEMS if s in seen] + [s for s in seen if s not in SYSTEMS])


def analyse(log: TrialLog) -> TrialAnalysis:
    """Read every record and event of ``log`` and compute the series and summary."""
    ticks = list(log.ticks())
    results = list(log.vision())
    events = list(log.events())
    notes: list[str] = []
    target = target_from_header(log.header)
    has_truth = any(r.truth_X_CT is not None for r in results) or any(
        tick.truth is not None for tick in ticks
    )
    systems = _ordered_systems(r.system for r in results)
    series, judged = {}, _Judged()
    for system in systems:
        mine = sorted((r for r in results if r.system == system), key=lambda r: r.capture_t)
        series[system] = _system_series(system, mine, target, judged)

    t = np.array([tick.t for tick in ticks], dtype=float)
    fused_p, fused_a = _fused_errors(ticks)
    period = max(float(np.median(np.diff(t))), 1e-9) if len(t) > 1 else math.inf
    outcome_event = next((e for e in reversed(events) if e.get("kind") == "outcome"), None)
    outcome_data = dict((outcome_event or {}).get("data") or {})
    phases = tuple(str(tick.phase) for tick in ticks)
    outcome, abort_reason = _outcome(phases, events, ticks, log.complete, outcome_data)
    nearest = {name: _nearest(t, s.capture_t, tolerance=period) for name, s in series.items()}

    if not has_truth:
        notes.append(
            "No ground truth in this log (real hardware): error plots and statistics skipped."
        )
    if judged.skipped_5dof:
        notes.append(
            f"{judged.skipped_5dof} circle (5-DOF) measurements not judged: the log's "
            "configuration holds no mock-up geometry (config.mockup)."
        )
    if judged.unreadable:
        notes.append(f"{judged.unreadable} measurements could not be judged.")
    if log.problems:
        notes.append(
            f"{len(log.problems)} records skipped: they do not read back as records "
            f"(first: {log.problems[0]})."
        )
    incomplete = _incompleteness(log, ticks)
    if incomplete:
        notes.append(incomplete)

    V = np.array(
        [
            tick.command.V_BE if np.shape(tick.command.V_BE) == (6,) else [math.nan] * 6
            for tick in ticks
        ],
        dtype=float,
    ).reshape(len(ticks), 6)
    true_depth = (
        np.array([tick.truth.X_CT.p[2] if tick.truth else math.nan for tick in ticks])
        if has_truth
        else None
    )
    timing = _timing(ticks, nominal_period_s(log.header, outcome_data))
    summaries = tuple(
        _summary(s, fused_p, fused_a, nearest[s.name], has_truth) for s in series.values()
    )
    first_result_t = min((r.t for r in results), default=math.inf)
    return TrialAnalysis(
        path=str(log.path),
        header=log.header,
        recovered=log.recovered,
        complete=log.complete,
        corrupt=log.corrupt,
        incomplete=incomplete,
        t=t,
        tick=np.array([tick.tick for tick in ticks], dtype=float),
        phases=phases,
        range_m=np.array([_nan_if_none(tick.range_m) for tick in ticks], dtype=float),
        true_depth_m=true_depth,
        fused_position_error_m=fused_p,
        fused_attitude_error_rad=fused_a,
        linear_speed=np.linalg.norm(V[:, :3], axis=1),
        angular_speed=np.linalg.norm(V[:, 3:], axis=1),
        track_velocity=np.array([tick.command.track_velocity for tick in ticks], dtype=float),
        track_velocity_measured=np.array(
            [tick.track.velocity if tick.track else math.nan for tick in ticks], dtype=float
        ),
        stop=np.array([bool(tick.command.stop) for tick in ticks], dtype=bool),
        period_ms=np.array([_nan_if_none(tick.timing.period_ms) for tick in ticks], dtype=float),
        work_ms=np.array([tick.timing.work_ms for tick in ticks], dtype=float),
        cpu_ms=np.array([_nan_if_none(tick.timing.cpu_ms) for tick in ticks], dtype=float),
        deadline_miss=np.array([bool(tick.timing.deadline_miss) for tick in ticks], dtype=bool),
        systems=systems,
        series=series,
        has_truth=has_truth,
        events=events,
        outcome=outcome,
        abort_reason=abort_reason,
        outcome_data=outcome_data,
        success=outcome_event is not None and outcome_event.get("message") == "success",
        summaries=summaries,
        fused=_fused_summary(ticks, fused_p, fused_a, first_result_t) if ticks else None,
        fused_below_all=_fused_below_all(series, nearest, fused_p, fused_a)
        if has_truth
        else (math.nan, math.nan, 0),
        fused_below_all_1s=_fused_below_all_windowed(t, series, fused_p, fused_a)
        if has_truth
        else (math.nan, math.nan, 0),
        standoff=_standoff(ticks, fused_p, fused_a),
        timing=timing,
        vision=_vision(ticks, results),
        notes=notes,
    )


def _incompleteness(log: TrialLog, ticks: list[TickRecord]) -> str | None:
    """Why the log does not hold the whole trial, and how much of it was read: a corrupt file
    (parts that do not read, the rest read) is told apart from a writer that was killed or
    could not write (a cut-off tail); None for a log its writer closed."""
    said = []
    if log.corrupt:
        said.append(f"The log is corrupt: {log.damage()}.")
    if log.recovered:
        last = f"t = {ticks[-1].t:.2f} s" if ticks else "no tick"
        said.append(
            "The log has no footer (its writer was killed, or could not write: a full disk): "
            f"read up to the last flush ({last}, {len(ticks)} ticks); {log.stopped}."
        )
    elif not log.complete and not log.corrupt:
        said.append("The log was not closed by its writer (a recovered copy).")
    return " ".join(said) or None


def _nan_if_none(value: float | None) -> float:
    return math.nan if value is None else value


@dataclass
class _Judged:
    """What could not be judged against truth, for the notes."""

    skipped_5dof: int = 0
    unreadable: int = 0


def _system_series(
    system: str, results: list[VisionRecord], target: TargetModel | None, judged: _Judged
) -> SystemSeries:
    n = len(results)
    position, attitude = np.full(n, math.nan), np.full(n, math.nan)
    five_dof = False
    for i, r in enumerate(results):
        m = r.measurement
        if not m.valid:
            continue
        five_dof |= m.X_CT is None and m.center_C is not None
        if r.truth_X_CT is None:
            continue
        if target is None and m.X_CT is None:
            judged.skipped_5dof += 1
            continue
        try:
            error = measurement_error(m, r.truth_X_CT, target)
        except (ValueError, KeyError, TypeError):
            judged.unreadable += 1
            continue
        position[i], attitude[i] = error.position_m, error.attitude_rad
    return SystemSeries(
        name=system,
        seq=np.array([r.seq for r in results], dtype=int),
        capture_t=np.array([r.capture_t for r in results], dtype=float),
        t=np.array([r.t for r in results], dtype=float),
        valid=np.array([r.measurement.valid for r in results], dtype=bool),
        outcome=np.array([r.outcome for r in results], dtype=object),
        position_error_m=position,
        attitude_error_rad=attitude,
        latency_ms=np.array([r.latency_ms for r in results], dtype=float),
        processing_ms=np.array([r.processing_ms for r in results], dtype=float),
        five_dof=five_dof,
    )


def _fused_errors(ticks: list[TickRecord]) -> tuple[np.ndarray, np.ndarray]:
    """Position and attitude error of the fused estimate at each tick against its truth:
    ``estimators.geometry.translation_error`` and ``rotation_error_rpy_norm``, computed for all
    ticks at once (a trial at 125 Hz has thousands)."""
    n = len(ticks)
    position, attitude = np.full(n, math.nan), np.full(n, math.nan)
    pairs = [
        (i, tick.truth.X_CT, tick.estimate.X_CT)
        for i, tick in enumerate(ticks)
        if tick.truth is not None and tick.estimate.X_CT is not None
    ]
    if not pairs:
        return position, attitude
    index = np.array([i for i, _, _ in pairs])
    R_true = np.array([X.R for _, X, _ in pairs])
    R_est = np.array([X.R for _, _, X in pairs])
    p_true = np.array([X.p for _, X, _ in pairs])
    p_est = np.array([X.p for _, _, X in pairs])
    finite = np.isfinite(R_est).all(axis=(1, 2)) & np.isfinite(p_est).all(axis=1)
    position[index] = np.linalg.norm(p_true - p_est, axis=1)
    R_error = np.einsum("nij,nkj->nik", R_true[finite], R_est[finite])  # R_true · R_estᵀ
    if len(R_error):
        rpy = Rotation.from_matrix(R_error).as_euler("xyz")
        attitude[index[finite]] = np.linalg.norm(rpy, axis=1)
    return position, attitude


def _nearest(t: np.ndarray, times: np.ndarray, *, tolerance: float) -> np.ndarray:
    """Index of the tick nearest each of ``times``; -1 where none is within ``tolerance``."""
    if len(t) == 0 or len(times) == 0:
        return np.full(len(times), -1, dtype=int)
    right = np.clip(np.searchsorted(t, times), 0, len(t) - 1)
    left = np.clip(right - 1, 0, len(t) - 1)
    index = np.where(np.abs(t[left] - times) <= np.abs(t[right] - times), left, right)
    return np.where(np.abs(t[index] - times) <= tolerance, index, -1)


def _at(values: np.ndarray, index: np.ndarray) -> np.ndarray:
    """``values[index]``, NaN where ``index`` is -1."""
    out = np.full(len(index), math.nan)
    found = index >= 0
    out[found] = values[index[found]]
    return out


def _summary(
    s: SystemSeries,
    fused_p: np.ndarray,
    fused_a: np.ndarray,
    nearest: np.ndarray,
    has_truth: bool,
) -> SystemSummary:
    def better(errors: np.ndarray, fused: np.ndarray) -> float:
        at_capture = _at(fused, nearest)
        both = np.isfinite(errors) & np.isfinite(at_capture)
        if not has_truth or not both.any():
            return math.nan
        return float(np.mean(at_capture[both] < errors[both]))

    fused_in_time = s.outcome != "stale"
    return SystemSummary(
        name=s.name,
        results=len(s.outcome),
        valid=int(s.valid.sum()),
        accepted=int((s.outcome == "accepted").sum()),
        rejected=int((s.outcome == "rejected").sum()),
        not_measured=int((s.outcome == "not_measured").sum()),
        stale=int((s.outcome == "stale").sum()),
        five_dof=s.five_dof,
        position_m=Spread.of(s.position_error_m),
        attitude_rad=Spread.of(s.attitude_error_rad),
        latency_ms=Spread.of(s.latency_ms[fused_in_time]),
        processing_ms=Spread.of(s.processing_ms),
        fused_better_position=better(s.position_error_m, fused_p),
        fused_better_attitude=better(s.attitude_error_rad, fused_a),
    )


def _fused_summary(
    ticks: list[TickRecord], fused_p: np.ndarray, fused_a: np.ndarray, first_result_t: float
) -> SystemSummary:
    has = np.array([tick.estimate.X_CT is not None for tick in ticks])
    since = np.array([tick.t >= first_result_t for tick in ticks]) | has
    nothing = Spread.of(())
    return SystemSummary(
        name=FUSED,
        results=int(since.sum()),
        valid=int(has.sum()),
        accepted=int(has.sum()),
        rejected=0,
        not_measured=int((since & ~has).sum()),
        stale=0,
        five_dof=False,
        position_m=Spread.of(fused_p),
        attitude_rad=Spread.of(fused_a),
        latency_ms=nothing,
        processing_ms=nothing,
    )


def _fused_below_all(
    series: dict[str, SystemSeries],
    nearest: dict[str, np.ndarray],
    fused_p: np.ndarray,
    fused_a: np.ndarray,
) -> tuple[float, float, int]:
    """Per frame (every system's result of one frame shares its capture time): is the fused
    error at the tick nearest the capture below every judged result of that frame?"""
    if not series:
        return math.nan, math.nan, 0
    frames: dict[int, list] = {}  # seq → [fused p, fused a, best p, best a]
    for name, s in series.items():
        fp, fa = _at(fused_p, nearest[name]), _at(fused_a, nearest[name])
        for i, seq in enumerate(s.seq):
            row = frames.setdefault(int(seq), [fp[i], fa[i], math.inf, math.inf])
            row[2] = np.fmin(row[2], s.position_error_m[i])
            row[3] = np.fmin(row[3], s.attitude_error_rad[i])
    rows = np.array(list(frames.values()), dtype=float).reshape(-1, 4)
    rows[~np.isfinite(rows)] = math.nan  # a frame with no judged result: inf → NaN

    def fraction(fused: np.ndarray, best: np.ndarray) -> tuple[float, int]:
        compared = np.isfinite(fused) & np.isfinite(best)
        if not compared.any():
            return math.nan, 0
        return float(np.mean(fused[compared] < best[compared])), int(compared.sum())

    p, count = fraction(rows[:, 0], rows[:, 2])
    a, _ = fraction(rows[:, 1], rows[:, 3])
    return p, a, count


def _fused_below_all_windowed(
    t: np.ndarray,
    series: dict[str, SystemSeries],
    fused_p: np.ndarray,
    fused_a: np.ndarray,
    window_s: float = 1.0,
    min_samples: int = 3,
) -> tuple[float, float, int]:
    """Per ``window_s`` window: is the fused estimate's median error (over the window's ticks)
    below the median error of every system with at least ``min_samples`` results captured in
    the window? (A single estimator's error crosses zero now and then; medians compare
    accuracy, not luck.)"""
    if not series or len(t) == 0:
        return math.nan, math.nan, 0
    edges = np.arange(t[0], t[-1] + window_s, window_s)

    def fraction(fused: np.ndarray, errors: dict[str, np.ndarray]) -> tuple[float, int]:
        tick_window = np.digitize(t, edges)
        wins = []
        for w in np.unique(tick_window):
            inside = fused[tick_window == w]
            inside = inside[np.isfinite(inside)]
            others = []
            for name, s in series.items():
                e = errors[name][np.digitize(s.capture_t, edges) == w]
                e = e[np.isfinite(e)]
                if len(e) >= min_samples:
                    others.append(np.median(e))
            if len(inside) >= min_samples and others:
                wins.append(np.median(inside) < min(others))
        return (float(np.mean(wins)), len(wins)) if wins else (math.nan, 0)

    p, count = fraction(fused_p, {n: s.position_error_m for n, s in series.items()})
    a, _ = fraction(fused_a, {n: s.attitude_error_rad for n, s in series.items()})
    return p, a, count


def _outcome(
    phases: Sequence[str],
    events: list[dict],
    ticks: list[TickRecord],
    complete: bool,
    outcome_data: dict[str, Any],
) -> tuple[str, str | None]:
    """(how the trial ended, why it aborted): the abort reason is the first ``abort`` event's,
    else the outcome event's, else the stop reason of the first abort tick or the first
    fault."""
    abort_events = [e for e in events if e.get("kind") == "abort"]
    if "abort" in phases or abort_events:
        if abort_events:
            return "aborted", str(abort_events[0].get("message", ""))
        if outcome_data.get("abort_reason"):
            return "aborted", str(outcome_data["abort_reason"])
        reason = ticks[phases.index("abort")].command.reason or None
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
    ticks: list[TickRecord], fused_p: np.ndarray, fused_a: np.ndarray
) -> StandoffState | None:
    indices = [i for i, tick in enumerate(ticks) if tick.phase == "standoff"]
    if not indices:
        return None
    i = indices[-1]
    X_CT = ticks[i].truth.X_CT if ticks[i].truth is not None else None
    nan = math.nan
    return StandoffState(
        t=ticks[i].t,
        range_m=_nan_if_none(ticks[i].range_m),
        true_depth_m=X_CT.p[2] if X_CT is not None else nan,
        true_lateral_m=float(np.hypot(*X_CT.p[:2])) if X_CT is not None else nan,
        true_misalignment_rad=normal_angle(-X_CT.R[:, 2], np.array([0.0, 0.0, 1.0]))
        if X_CT is not None
        else nan,
        fused_position_error_m=fused_p[i],
        fused_attitude_error_rad=fused_a[i],
    )


def _timing(ticks: list[TickRecord], nominal_period_s: float) -> TimingSummary:
    timing = [tick.timing for tick in ticks]
    longest = max(timing, key=lambda x: x.work_ms, default=None)
    return TimingSummary(
        nominal_period_ms=1000.0 * nominal_period_s,
        period_ms=Spread.of([_nan_if_none(x.period_ms) for x in timing]),
        work_ms=Spread.of([x.work_ms for x in timing]),
        late_ms=Spread.of([x.late_ms for x in timing]),
        deadline_misses=sum(bool(x.deadline_miss) for x in timing),
        longest_work_ms=math.nan if longest is None else longest.work_ms,
        longest_cpu_ms=math.nan if longest is None else _nan_if_none(longest.cpu_ms),
    )


def _vision(ticks: list[TickRecord], results: list[VisionRecord]) -> VisionSummary:
    counters = ticks[-1].vision if ticks else None
    reached = [r.latency_ms for r in results if r.outcome != "stale"]
    return VisionSummary(
        frames_received=counters.frames_received if counters else 0,
        frames_processed=counters.frames_processed if counters else 0,
        frames_dropped=counters.frames_dropped if counters else 0,
        results_stale=counters.results_stale if counters else 0,
        stale_records=sum(r.outcome == "stale" for r in results),
        latency_ms=Spread.of(reached),
    )
