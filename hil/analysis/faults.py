"""The fault-injection suite (``satgrasp faults``): one short simulated trial per fault, each
judged on how the loop reacted.

Every trial is the configured simulation with a small camera (``cameras/small.yaml``) and the
ground-truth estimator (``sim_backends.oracle``) where vision is not the point, and one fault
injected ``AFTER_S`` seconds into the approach. From the trial's tick records (collected in
process, so a trial whose log fails is judged too) and its log:

* the fault's *effect*: the first instant the loop could observe it — a device fault at the
  next tick; a corrupt or frozen frame when it arrives (capture + latency); NaN estimates when
  the first such result comes back; a camera that stopped when its newest frame grows older
  than ``max_frame_age_s`` (that rule's threshold); a tumbling mock-up when the fused estimate's
  rate first exceeds ``max_target_rate_deg_s``; a full disk at the next write;
* the *stop*: the first tick after the injection that commanded a stop, or the loop stopping
  the devices outside a tick (the way a trial ends when its log cannot be written);
* the *reaction*: whole control periods from the first tick that could see the effect to that
  stop (0: the very same tick; negative: another rule had stopped the arm before, e.g. fusion
  losing a target that turns away from its model). A row passes when the reaction is at most one period, the log
  opens, and the reason is named (in the log; for a full disk, which cannot take it, in the
  trial's outcome).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from configuration.simulation import FAULT_KINDS, SimulationConfig, with_overrides
from hil.logs.records import TickRecord
from hil.logs.triallog import TrialLog
from hil.runtime.compose import Trial, TrialResult
from sim_backends.oracle import ORACLE_SYSTEM

#: When each fault is injected: this long into the approach phase (s).
AFTER_S = 1.0
#: How long a fault trial may run (simulated s): the approach starts ≈ 0.5 s in; the tumbling
#: mock-up is held for target_rate_abort_s (3 s) before the abort.
TRIAL_S = 8.0

#: What the loop's stop or abort reason must say for each fault.
REASONS = {
    "camera_dropout": "no usable frame",
    "frozen_camera": "frozen camera",
    "corrupt_frame": "corrupt frame",
    "nan_estimate": "non-finite",
    "protective_stop": "protective stop",
    "emergency_stop": "emergency stop",
    "link_drop": "arm state unavailable",
    "modbus_silent": "track state unavailable",
    "track_fault": "drive fault",
    "tumbling_target": "target rotating at",
    "disk_full": "log",
}
#: Faults the loop observes at its next tick (device states, the log's writes).
_AT_NEXT_TICK = {
    "protective_stop",
    "emergency_stop",
    "link_drop",
    "modbus_silent",
    "track_fault",
    "disk_full",
}


@dataclass(frozen=True, slots=True)
class FaultRow:
    """How one fault trial went (times in s since the trial's start)."""

    kind: str
    injected_t: float | None
    effect_t: float | None
    stop_t: float | None
    reaction_ticks: int | None
    final: str
    log_readable: str
    reason: str
    passed: bool
    log_path: Path


def fault_config(base: SimulationConfig, kind: str) -> SimulationConfig:
    """``base`` made into a short fault trial of ``kind``."""
    vision = base.vision.model_dump(mode="json") | {"log_frames_every_s": 0.0}
    return with_overrides(
        base,
        camera="small",
        systems=[ORACLE_SYSTEM],
        noise={"preset": "none"},
        vision=vision,
        max_duration_s=TRIAL_S,
        faults=[{"kind": kind, "phase": "approach", "after_s": AFTER_S}],
    )


def run_fault(base: SimulationConfig, kind: str, *, seed: int, out_dir: Path) -> FaultRow:
    """Run the trial of fault ``kind`` and judge it."""
    config = fault_config(base, kind)
    out_dir.mkdir(parents=True, exist_ok=True)
    log_path = out_dir / f"fault_{kind}_seed{seed}_{time.strftime('%Y%m%d-%H%M%S')}.mcap"
    ticks: list[TickRecord] = []
    with Trial(config, seed=seed, log_path=log_path, on_tick=ticks.append) as trial:
        stops = _record_stops(trial)
        result = trial.run()
        assert trial.injector is not None
        injected = trial.injector.injected
        faulty_frames = [
            arrival - trial.loop.t0 for _, _, arrival in trial.world.camera.faulty_frames
        ]
        period = trial.loop.period_s
    return judge(
        kind, config, ticks, result, injected[0].t if injected else None, faulty_frames, period,
        stops,
    )  # fmt: skip


def _record_stops(trial: Trial) -> list[float]:
    """Times (s since the start) at which the loop stops the devices itself."""
    stops: list[float] = []
    loop, stop_devices = trial.loop, trial.loop.stop_devices

    def recorded(t: float, *args, **kwargs):
        stops.append(t - loop.t0)
        return stop_devices(t, *args, **kwargs)

    loop.stop_devices = recorded  # type: ignore[method-assign]
    return stops


def judge(
    kind: str,
    config: SimulationConfig,
    ticks: Sequence[TickRecord],
    result: TrialResult,
    injected_t: float | None,
    faulty_arrivals: Sequence[float],
    period: float,
    device_stops: Sequence[float] = (),
) -> FaultRow:
    log, readable = _open(result.log_path, len(ticks))
    if injected_t is None:
        return FaultRow(
            kind, None, None, None, None, _final(result, ticks), readable, "not injected", False,
            result.log_path,
        )  # fmt: skip
    effect_t = _effect(kind, config, ticks, log, injected_t, faulty_arrivals)
    after = [t for t in ticks if t.t > injected_t + 1e-9]
    stop_times = [t.t for t in after if t.command.stop]
    # The loop may also stop the devices at once, between ticks (the injection's own instant).
    stop_times += [s for s in device_stops if s >= injected_t - 1e-9]
    stop_t = min(stop_times) if stop_times else None
    reaction = None
    if stop_t is not None and effect_t is not None:
        # The first tick that could see it (or, after the last tick, the next one's time).
        seeing = next((t.t for t in after if t.t >= effect_t - 1e-9), None)
        if seeing is None:
            seeing = ticks[-1].t + period if ticks else None
        if seeing is not None and stop_t < effect_t - 1e-9:  # stopped before, by another rule
            reaction = -round((seeing - stop_t) / period)
        elif seeing is not None:
            reaction = max(0, round((stop_t - seeing) / period))
    reason = _reason(kind, log, injected_t, result)
    passed = (
        reaction is not None
        and reaction <= 1
        and readable.startswith("yes")
        and not reason.startswith("no")
    )
    return FaultRow(
        kind, injected_t, effect_t, stop_t, reaction, _final(result, ticks), readable, reason,
        passed, result.log_path,
    )  # fmt: skip


def _open(path: Path, ticks_run: int) -> tuple[TrialLog | None, str]:
    try:
        log = TrialLog.open(path)
        logged = log.tick_count
    except Exception as exc:  # the column reports it; the suite goes on
        return None, f"no: {exc}"
    if logged < ticks_run:
        return log, f"yes, {logged} of {ticks_run} ticks"
    return log, f"yes, {logged} ticks"


def _effect(
    kind: str,
    config: SimulationConfig,
    ticks: Sequence[TickRecord],
    log: TrialLog | None,
    injected_t: float,
    faulty_arrivals: Sequence[float],
) -> float | None:
    """The first instant the loop could observe the fault (s since the start)."""
    if kind in _AT_NEXT_TICK:
        return injected_t
    if kind in ("frozen_camera", "corrupt_frame"):
        return faulty_arrivals[0] if faulty_arrivals else None
    if kind == "camera_dropout":
        newest = [t.vision.newest_frame_t for t in ticks if t.vision.newest_frame_t is not None]
        return max(newest) + config.approach.supervisor.max_frame_age_s if newest else None
    if kind == "nan_estimate":
        if log is None:
            return None
        late = [r.t for r in log.vision() if r.capture_t >= injected_t - 1e-9]
        return min(late) if late else None
    if kind == "tumbling_target":
        limit = math.radians(config.approach.supervisor.max_target_rate_deg_s)
        for tick in ticks:
            V = tick.estimate.V_MT
            if tick.t > injected_t and V is not None and np.linalg.norm(V[:3]) > limit:
                return tick.t
        return None
    raise ValueError(f"unknown fault kind {kind!r}")


def _reason(kind: str, log: TrialLog | None, injected_t: float, result: TrialResult) -> str:
    """The logged reason naming the fault, or why there is none."""
    expected = REASONS[kind]
    if log is not None:
        for event in log.events():
            named = event["kind"] in ("fault", "abort") and expected in event["message"]
            if named and event["t"] >= injected_t - 1e-9:
                return event["message"]
    outcome = result.outcome.abort_reason
    if kind == "disk_full" and expected in outcome:
        return f"(the log is full) outcome: {outcome}"
    return f"no (outcome: {outcome or result.outcome.phase})"


def _final(result: TrialResult, ticks: Sequence[TickRecord]) -> str:
    o = result.outcome
    if o.abort_reason.startswith("trial exceeded") and len(ticks) > 1:
        return f"{ticks[-2].phase} at the {TRIAL_S:.0f} s limit"
    return f"{o.phase}" + (f": {o.abort_reason}" if o.abort_reason else "")


def run_suite(
    base: SimulationConfig,
    kinds: Sequence[str] = FAULT_KINDS,
    *,
    seed: int = 2,
    out_dir: Path = Path("runs/faults"),
    progress: Callable[[FaultRow], None] | None = None,
) -> list[FaultRow]:
    """One fault trial per kind, in order."""
    rows = []
    for kind in kinds:
        row = run_fault(base, kind, seed=seed, out_dir=out_dir)
        rows.append(row)
        if progress is not None:
            progress(row)
    return rows


def _s(value: float | None) -> str:
    return "–" if value is None else f"{value:.3f}"


def table(rows: Sequence[FaultRow], period_s: float) -> str:
    """The suite's result as a Markdown table."""
    lines = [
        "| fault | injected (s) | first effect (s) | stop (s) | reaction (ticks) | final state "
        "| log readable | reason logged | pass |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        reaction = "no stop" if r.reaction_ticks is None else str(r.reaction_ticks)
        reason = r.reason.replace("|", "/")
        lines.append(
            f"| {r.kind} | {_s(r.injected_t)} | {_s(r.effect_t)} | {_s(r.stop_t)} | {reaction} "
            f"| {r.final.replace('|', '/')} | {r.log_readable} | {reason} "
            f"| {'yes' if r.passed else '**no**'} |"
        )
    lines.append("")
    lines.append(
        f"Reaction: whole control periods ({1000 * period_s:.0f} ms) from the first tick that "
        "could see the fault's effect to the first stop; 0 = the same tick, negative = "
        "stopped before by another rule."
    )
    return "\n".join(lines)
