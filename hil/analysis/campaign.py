"""Campaigns of simulated approaches: many seeds × noise levels, one trial log each, and a
summary read back from the logs (reports and comparisons read only logs)."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from configuration.campaign import CampaignConfig, CampaignPart
from configuration.simulation import SimulationConfig
from hil.analysis.trial_analysis import analyse
from hil.logs.triallog import TrialLog


@dataclass(frozen=True, slots=True)
class TrialSummary:
    """One trial as read back from its log."""

    seed: int
    noise: str
    log_path: str
    success: bool
    phase: str
    abort_reason: str
    duration_s: float
    standoff_error_m: float
    standoff_error_deg: float
    fused_position_median_m: float
    best_single_position_median_m: float
    fused_attitude_median_deg: float
    best_single_attitude_median_deg: float
    fused_below_all_position: float  # fraction of frames: fused (nearest tick) vs their results
    fused_below_all_attitude: float
    fused_below_all_1s_position: float  # fraction of 1 s windows, on median errors
    fused_below_all_1s_attitude: float
    deadline_misses: int = 0
    vision_latency_p95_ms: float = math.nan


def summarize_log(path: Path, seed: int, noise: str) -> TrialSummary:
    analysis = analyse(TrialLog.open(path))
    data = analysis.outcome_data
    singles = [s for s in analysis.summaries if s.position_m.count > 0]
    fused = analysis.fused

    def median(stats, scale=1.0) -> float:
        return scale * stats.median if stats is not None and stats.count > 0 else math.nan

    def number(value) -> float:
        return float(value) if isinstance(value, int | float) else math.nan

    return TrialSummary(
        seed=seed,
        noise=noise,
        log_path=str(path),
        success=analysis.success,
        phase=data.get("phase") or (analysis.phases[-1] if analysis.phases else analysis.outcome),
        abort_reason=data.get("abort_reason") or analysis.abort_reason or "",
        duration_s=float(analysis.t[-1]) if len(analysis.t) else math.nan,
        standoff_error_m=number(data.get("standoff_error_m")),
        standoff_error_deg=math.degrees(number(data.get("standoff_error_rad"))),
        fused_position_median_m=median(fused.position_m) if fused else math.nan,
        best_single_position_median_m=min(
            (median(s.position_m) for s in singles), default=math.nan
        ),
        fused_attitude_median_deg=median(fused.attitude_rad, math.degrees(1))
        if fused
        else math.nan,
        best_single_attitude_median_deg=min(
            (median(s.attitude_rad, math.degrees(1)) for s in singles), default=math.nan
        ),
        fused_below_all_position=analysis.fused_below_all[0],
        fused_below_all_attitude=analysis.fused_below_all[1],
        fused_below_all_1s_position=analysis.fused_below_all_1s[0],
        fused_below_all_1s_attitude=analysis.fused_below_all_1s[1],
        deadline_misses=analysis.timing.deadline_misses,
        vision_latency_p95_ms=analysis.vision.latency_ms.p95,
    )


def seeds_campaign(
    sim: SimulationConfig, seeds: Sequence[int], noises: Sequence[str], name: str = "seeds"
) -> CampaignConfig:
    """``satgrasp campaign --seeds``: closed-loop approaches of ``sim`` (its full resolved
    configuration), every noise level × every seed — a campaign of one ``approach`` part."""
    return CampaignConfig(
        name=name,
        parts=[
            CampaignPart(
                name="approach",
                kind="approach",
                settings={"config": sim.model_dump(mode="json")},
                axes={"noise": list(noises)},
                seeds=list(seeds),
            )
        ],
    )


def run_campaign(
    sim: SimulationConfig,
    seeds: Sequence[int],
    noises: Sequence[str],
    out_dir: Path,
    *,
    jobs: int = 1,
    progress: Callable[[str, float, int, int], None] | None = None,
) -> list[TrialSummary]:
    """Run every (noise, seed) trial through the campaign runner (resumable, ``jobs`` at a
    time) and read each trial's summary back from its log."""
    from hil.analysis.campaigns.runner import run_campaign as run
    from hil.analysis.campaigns.spec import expand
    from hil.analysis.campaigns.trials import log_path

    config = seeds_campaign(sim, seeds, noises)
    run(config, out_dir, workers=jobs, progress=progress)
    return [summarize_log(log_path(out_dir, t), t.seed, t.cell["noise"]) for t in expand(config)]


def _cm(m: float) -> str:
    return "–" if math.isnan(m) else f"{100 * m:.2f} cm"


def _mm(m: float) -> str:
    return "–" if math.isnan(m) else f"{1000 * m:.1f} mm"


def _deg(d: float) -> str:
    return "–" if math.isnan(d) else f"{d:.2f}°"


def campaign_markdown(rows: Sequence[TrialSummary]) -> str:
    """Per noise level: success rate and error statistics; then one line per trial."""
    lines = [
        "| noise | trials | success | stand-off error (max) | fused below every system: instants "
        "| fused below every system: 1 s medians |",
        "|---|---|---|---|---|---|",
    ]
    for noise in dict.fromkeys(r.noise for r in rows):
        group = [r for r in rows if r.noise == noise]
        ok = sum(r.success for r in group)
        errors_m = [r.standoff_error_m for r in group if not math.isnan(r.standoff_error_m)]
        errors_deg = [r.standoff_error_deg for r in group if not math.isnan(r.standoff_error_deg)]
        below_p = np.nanmean([r.fused_below_all_position for r in group])
        below_a = np.nanmean([r.fused_below_all_attitude for r in group])
        below_p1 = np.nanmean([r.fused_below_all_1s_position for r in group])
        below_a1 = np.nanmean([r.fused_below_all_1s_attitude for r in group])
        lines.append(
            f"| {noise} | {len(group)} | {ok}/{len(group)} ({100 * ok / len(group):.0f} %) "
            f"| {_mm(max(errors_m, default=math.nan))} / {_deg(max(errors_deg, default=math.nan))} "
            f"| position {100 * below_p:.0f} %, attitude {100 * below_a:.0f} % "
            f"| position {100 * below_p1:.0f} %, attitude {100 * below_a1:.0f} % |"
        )
    lines += [
        "",
        "| noise | seed | outcome | duration | stand-off error | fused median error | best single median error "
        "| vision latency p95 | deadline misses | log |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        outcome = "success" if r.success else f"{r.phase}: {r.abort_reason}"[:60]
        latency = (
            "–" if math.isnan(r.vision_latency_p95_ms) else f"{r.vision_latency_p95_ms:.0f} ms"
        )
        lines.append(
            f"| {r.noise} | {r.seed} | {outcome} | {r.duration_s:.1f} s "
            f"| {_mm(r.standoff_error_m)} / {_deg(r.standoff_error_deg)} "
            f"| {_mm(r.fused_position_median_m)} / {_deg(r.fused_attitude_median_deg)} "
            f"| {_mm(r.best_single_position_median_m)} / {_deg(r.best_single_attitude_median_deg)} "
            f"| {latency} | {r.deadline_misses} | {Path(r.log_path).name} |"
        )
    return "\n".join(lines) + "\n"
