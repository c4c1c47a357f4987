"""``satgrasp report RUN.mcap``: PNG plots and a small HTML page from one trial log, or the
same figures as one JSON object (``report_json``, for ``--json``).

Reads only the log (``hil.logs.triallog.TrialLog``), analysed by
``hil.analysis.trial_analysis``. Plots: range with the phase timeline, translation and rotation
error of every estimator result (at its capture time) and of the fused estimate (at each tick)
against ground truth (skipped, and said so, for a log without truth), the per-system outcome
raster, the commanded speeds, and the timing: control period and tick work over the trial,
and the vision latency capture → fusion per system. Matplotlib is used through its object API
on the Agg canvas (no pyplot state, no display needed).
"""

from __future__ import annotations

import html
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from hil.analysis.trial_analysis import FUSED, Spread, TrialAnalysis, analyse, phase_spans
from hil.logs.triallog import TrialLog

PHASE_COLORS = {
    "idle": "#e0e0e0",
    "acquire": "#fff2b3",
    "approach": "#cfe5ff",
    "standoff": "#c9f2c9",
    "grasp": "#ead1f5",
    "retreat": "#ffe0c2",
    "abort": "#ffb3b3",
    "done": "#d0d0d0",
}
SYSTEM_COLORS = {"corners": "#1f77b4", "lines": "#ff7f0e", "ellipses": "#2ca02c"}
OUTCOME_STYLE = {  # colour, label
    "accepted": ("#2ca02c", "accepted by fusion"),
    "rejected": ("#ff7f0e", "rejected by fusion"),
    "not_measured": ("#d62728", "lost (not measured)"),
    "stale": ("#9e9e9e", "stale (too late for fusion)"),
}
DPI = 100
DEG = math.degrees(1.0)


def _system_color(name: str, index: int) -> str:
    return SYSTEM_COLORS.get(name, f"C{(index + 3) % 10}")


def _shade_phases(ax, analysis: TrialAnalysis, *, alpha: float = 0.6) -> list[Patch]:
    """Shade the phases behind ``ax``'s data; returns legend handles of the phases seen."""
    seen: dict[str, Patch] = {}
    for phase, start, end in phase_spans(analysis.t, analysis.phases):
        color = PHASE_COLORS.get(phase, "#f0f0f0")
        ax.axvspan(start, max(end, start + 1e-3), color=color, alpha=alpha, lw=0, zorder=0)
        seen.setdefault(phase, Patch(color=color, alpha=alpha, label=phase))
    for event in analysis.events:
        if event.get("kind") in ("abort", "fault") and isinstance(event.get("t"), int | float):
            ax.axvline(event["t"], color="#d62728", lw=1.2, ls="--", zorder=3)
    return list(seen.values())


def _save(fig: Figure, path: Path) -> Path:
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=DPI)
    return path


def plot_range(analysis: TrialAnalysis, path: Path) -> Path:
    fig = Figure(figsize=(10, 3.6), layout="constrained")
    ax = fig.add_subplot()
    handles = _shade_phases(ax, analysis)
    (line,) = ax.plot(analysis.t, analysis.range_m, color="black", lw=1.5, label="range (estimate)")
    handles = [line, *handles]
    if analysis.true_depth_m is not None:
        (truth,) = ax.plot(
            analysis.t,
            analysis.true_depth_m,
            color="#7b1fa2",
            lw=1.0,
            ls="--",
            label="truth (ring-centre depth)",
        )
        handles.insert(1, truth)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("range (m)")
    ax.set_title("Range to the ring face and phases (red dashes: abort/fault events)")
    ax.grid(alpha=0.3)
    ax.legend(handles=handles, loc="upper right", fontsize=8, ncols=2)
    return _save(fig, path)


def plot_errors(analysis: TrialAnalysis, path: Path) -> Path:
    fig = Figure(figsize=(10, 6.4), layout="constrained")
    ax_p, ax_a = fig.subplots(2, 1, sharex=True)
    for ax, fused, attribute, scale, unit in (
        (ax_p, analysis.fused_position_error_m, "position_error_m", 1000.0, "translation (mm)"),
        (ax_a, analysis.fused_attitude_error_rad, "attitude_error_rad", DEG, "rotation (deg)"),
    ):
        _shade_phases(ax, analysis, alpha=0.35)
        positive = bool((np.isfinite(fused) & (fused > 0)).any())
        for i, system in enumerate(analysis.systems):
            s = analysis.series[system]
            values = getattr(s, attribute) * scale
            positive |= bool((np.isfinite(values) & (values > 0)).any())
            color = _system_color(system, i)
            label = system + (" (circle centre / normal)" if s.five_dof else "")
            used = s.outcome == "accepted"
            ax.plot(s.capture_t[used], values[used], ".", ms=3, color=color, label=label)
            for outcome, marker in (("rejected", "x"), ("stale", "+")):
                mask = s.outcome == outcome
                if mask.any():
                    ax.plot(
                        s.capture_t[mask],
                        values[mask],
                        marker,
                        ms=5,
                        color=color,
                        label=f"{system} {outcome}",
                    )
        ax.plot(analysis.t, fused * scale, "-", color="black", lw=1.6, label="fused")
        if positive:
            ax.set_yscale("log")
        ax.set_ylabel(unit)
        ax.grid(alpha=0.3, which="both")
    ax_p.set_title("Errors against ground truth: results at capture, the fused estimate per tick")
    ax_p.legend(loc="upper right", fontsize=8, ncols=3)
    ax_a.set_xlabel("time (s)")
    return _save(fig, path)


def plot_results(analysis: TrialAnalysis, path: Path) -> Path:
    fig = Figure(figsize=(10, 1.2 + 0.6 * max(1, len(analysis.systems))), layout="constrained")
    ax = fig.add_subplot()
    _shade_phases(ax, analysis, alpha=0.35)
    for row, system in enumerate(analysis.systems):
        s = analysis.series[system]
        for name, (color, label) in OUTCOME_STYLE.items():
            mask = s.outcome == name
            if mask.any():
                ax.plot(
                    s.capture_t[mask],
                    np.full(mask.sum(), row),
                    "|",
                    ms=14,
                    mew=1.5,
                    color=color,
                    label=label,
                )
    ax.set_yticks(range(len(analysis.systems)), analysis.systems)
    ax.set_ylim(-0.6, len(analysis.systems) - 0.4)
    ax.invert_yaxis()
    ax.set_xlabel("capture time (s)")
    ax.set_title("Estimator results and what fusion made of them")
    handles, labels = ax.get_legend_handles_labels()
    unique = dict(zip(labels, handles, strict=True))
    ax.legend(unique.values(), unique.keys(), loc="upper right", fontsize=8, ncols=4)
    return _save(fig, path)


def plot_command(analysis: TrialAnalysis, path: Path) -> Path:
    fig = Figure(figsize=(10, 4.4), layout="constrained")
    ax_v, ax_w = fig.subplots(2, 1, sharex=True)
    for ax in (ax_v, ax_w):
        _shade_phases(ax, analysis, alpha=0.35)
        if analysis.stop.any():
            ax.plot(
                analysis.t[analysis.stop],
                np.zeros(int(analysis.stop.sum())),
                "s",
                ms=3,
                color="#d62728",
                label="stop commanded",
            )
        ax.grid(alpha=0.3)
    ax_v.plot(analysis.t, analysis.linear_speed, color="black", label="arm ‖v‖ commanded")
    if np.isfinite(analysis.track_velocity).any():
        ax_v.plot(
            analysis.t, analysis.track_velocity, color="#1f77b4", label="track velocity commanded"
        )
    if np.isfinite(analysis.track_velocity_measured).any():
        ax_v.plot(
            analysis.t,
            analysis.track_velocity_measured,
            color="#1f77b4",
            ls=":",
            label="track velocity measured",
        )
    ax_v.set_ylabel("m/s")
    ax_v.legend(loc="upper right", fontsize=8)
    ax_v.set_title("Commands")
    ax_w.plot(
        analysis.t, np.degrees(analysis.angular_speed), color="black", label="arm ‖ω‖ commanded"
    )
    ax_w.set_ylabel("deg/s")
    ax_w.set_xlabel("time (s)")
    ax_w.legend(loc="upper right", fontsize=8)
    return _save(fig, path)


def plot_timing(analysis: TrialAnalysis, path: Path) -> Path:
    """Control period and tick work over the trial (deadline misses marked), and the latency
    capture → fusion of every result per system, at the time it reached fusion."""
    fig = Figure(figsize=(10, 6.0), layout="constrained")
    ax_c, ax_v = fig.subplots(2, 1, sharex=True)
    for ax in (ax_c, ax_v):
        _shade_phases(ax, analysis, alpha=0.35)
        ax.grid(alpha=0.3)
    nominal = analysis.timing.nominal_period_ms
    ax_c.plot(analysis.t, analysis.period_ms, color="black", lw=0.8, label="period")
    ax_c.plot(analysis.t, analysis.work_ms, color="#1f77b4", lw=0.8, label="tick work")
    simulated = analysis.outcome_data.get("clock") == "sim"
    if not simulated and np.isfinite(analysis.cpu_ms).any():  # under sim the work is CPU time
        ax_c.plot(analysis.t, analysis.cpu_ms, color="#ff7f0e", lw=0.6, label="of it on the CPU")
    if math.isfinite(nominal):
        ax_c.axhline(nominal, color="#7b1fa2", ls="--", lw=1.0, label=f"nominal {nominal:g} ms")
    if analysis.deadline_miss.any():
        miss = analysis.deadline_miss
        ax_c.plot(
            analysis.t[miss],
            np.nan_to_num(analysis.period_ms[miss], nan=nominal),
            "v",
            ms=6,
            color="#d62728",
            label=f"deadline miss ({int(miss.sum())})",
        )
    ax_c.set_ylabel("ms")
    ax_c.set_ylim(bottom=0)
    ax_c.set_title(
        "Control loop: period and work of each tick "
        + ("(work: the tick's CPU time; simulated clock)" if simulated else "(wall clock)")
    )
    ax_c.legend(loc="upper right", fontsize=8, ncols=4)
    for i, system in enumerate(analysis.systems):
        s = analysis.series[system]
        fused = s.outcome != "stale"
        color = _system_color(system, i)
        ax_v.plot(s.t[fused], s.latency_ms[fused], ".", ms=3, color=color, label=system)
        if (~fused).any():
            ax_v.plot(
                s.t[~fused], s.latency_ms[~fused], "+", ms=6, color=color, label=f"{system} stale"
            )
    ax_v.set_ylabel("ms")
    ax_v.set_ylim(bottom=0)
    ax_v.set_xlabel("time (s)")
    ax_v.set_title("Vision latency: frame capture → result handed to fusion")
    if analysis.systems:
        ax_v.legend(loc="upper right", fontsize=8, ncols=3)
    return _save(fig, path)


# --- figures as JSON --------------------------------------------------------------------------


def _number(value: Any, scale: float = 1.0) -> float | None:
    """A finite number scaled, else None (JSON null)."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        return None
    return value * scale


def _spread(s: Spread, *keys: str) -> dict[str, float | None]:
    values = {"p50": s.median, "p95": s.p95, "p99": s.p99, "max": s.max}
    return {key: _number(values[key]) for key in keys}


def _errors(position: Spread, attitude: Spread) -> dict[str, Any]:
    return {
        "position_error_mm": {
            "median": _number(position.median, 1000.0),
            "p95": _number(position.p95, 1000.0),
        },
        "attitude_error_deg": {
            "median": _number(attitude.median, DEG),
            "p95": _number(attitude.p95, DEG),
        },
    }


def report_json(analysis: TrialAnalysis) -> dict[str, Any]:
    """The trial's figures as JSON data (docs/trial_logs.md lists the keys); NaN as null."""
    timing, vision, data = analysis.timing, analysis.vision, analysis.outcome_data
    systems = {}
    for s in analysis.summaries:
        systems[s.name] = {
            "results": s.results,
            "accepted": s.accepted,
            "rejected": s.rejected,
            "not_measured": s.not_measured,
            "stale": s.stale,
            "latency_ms": _spread(s.latency_ms, "p50", "p95"),
            "processing_ms": _spread(s.processing_ms, "p50", "p95"),
            **(_errors(s.position_m, s.attitude_rad) if analysis.has_truth else {}),
        }
    fused = analysis.fused
    return {
        "log": analysis.path,
        "complete": analysis.complete,
        "corrupt": analysis.corrupt,
        "incomplete": analysis.incomplete,
        "success": analysis.success,
        "outcome": analysis.outcome,
        "phase": analysis.phases[-1] if analysis.phases else None,
        "abort_reason": analysis.abort_reason,
        "duration_s": _number(analysis.duration_s),
        "clock": data.get("clock"),
        "seed": analysis.header.get("seed"),
        "ticks": len(analysis.t),
        "control_period_ms": {
            "nominal": _number(timing.nominal_period_ms),
            **_spread(timing.period_ms, "p50", "p99", "max"),
        },
        "tick_work_ms": _spread(timing.work_ms, "p50", "p99", "max"),
        "longest_tick_ms": {
            "work": _number(timing.longest_work_ms),
            "cpu": _number(timing.longest_cpu_ms),
        },
        "deadline_misses": timing.deadline_misses,
        "frames": {
            "received": vision.frames_received,
            "processed": vision.frames_processed,
            "dropped": vision.frames_dropped,
        },
        "results_stale": vision.results_stale,
        "vision_latency_ms": _spread(vision.latency_ms, "p50", "p95", "max"),
        "standoff_error_mm": _number(data.get("standoff_error_m"), 1000.0),
        "standoff_error_deg": _number(data.get("standoff_error_rad"), DEG),
        "systems": systems,
        "fused": None
        if fused is None
        else {
            "ticks": fused.results,
            "with_estimate": fused.valid,
            **(_errors(fused.position_m, fused.attitude_rad) if analysis.has_truth else {}),
        },
        "notes": list(analysis.notes),
    }


# --- HTML -------------------------------------------------------------------------------------


def _fmt(value: float | None, scale: float = 1.0, digits: int = 1, unit: str = "") -> str:
    if value is None or not math.isfinite(value):
        return "–"
    return f"{value * scale:.{digits}f}{unit}"


def _pct(value: float) -> str:
    return "–" if not math.isfinite(value) else f"{100 * value:.0f} %"


def _table(rows: list[list[str]], header: list[str] | None = None) -> str:
    out = ["<table>"]
    if header:
        out.append("<tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in header) + "</tr>")
    for row in rows:
        out.append("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in row) + "</tr>")
    out.append("</table>")
    return "\n".join(out)


def _log_state(analysis: TrialAnalysis) -> str:
    state = (
        "recovered: no footer (writer killed, or could not write)"
        if analysis.recovered
        else "complete"
        if analysis.complete
        else "not closed by its writer"
    )
    return f"corrupt, {state}" if analysis.corrupt else state


def summary_rows(analysis: TrialAnalysis) -> list[list[str]]:
    """The trial summary as (label, value) rows."""
    h = analysis.header
    figures = report_json(analysis)
    rows = [
        ["outcome", analysis.outcome],
        ["success", "yes" if analysis.success else "no"],
        ["abort reason", analysis.abort_reason or "–"],
        ["duration", f"{analysis.duration_s:.2f} s"],
        ["ticks", str(len(analysis.t))],
        ["log", _log_state(analysis)],
        ["clock", str(figures["clock"] or "–")],
        ["satgrasp", str(h.get("satgrasp_version", "?"))],
        ["started (UTC)", str(h.get("start_time_utc", "?"))],
        ["host", str(h.get("host", "?"))],
        ["seed", str(h.get("seed"))],
        ["notes", str(h.get("notes", ""))],
    ]
    s = analysis.standoff
    if s is not None:
        rows.append(
            ["stand-off range (estimate, last stand-off tick)", _fmt(s.range_m, 1, 3, " m")]
        )
        if analysis.has_truth:
            rows += [
                [
                    "stand-off true depth / lateral offset",
                    f"{_fmt(s.true_depth_m, 1, 3, ' m')} / {_fmt(s.true_lateral_m, 1000, 1, ' mm')}",
                ],
                [
                    "stand-off true misalignment (optical axis vs ring normal)",
                    _fmt(s.true_misalignment_rad, DEG, 2, "°"),
                ],
                [
                    "stand-off fused camera-pose error",
                    f"{_fmt(s.fused_position_error_m, 1000, 2, ' mm')} / {_fmt(s.fused_attitude_error_rad, DEG, 3, '°')}",
                ],
            ]
    else:
        rows.append(["stand-off", "not reached"])
    rows.append(
        [
            "stand-off true error when reached (outcome)",
            f"{_fmt(figures['standoff_error_mm'], 1, 2, ' mm')} / "
            f"{_fmt(figures['standoff_error_deg'], 1, 3, '°')}",
        ]
    )
    if analysis.has_truth:
        p, a, n = analysis.fused_below_all
        rows.append(
            [
                "fused error (nearest tick) below every estimator's result of the same frame",
                f"translation {_pct(p)}, rotation {_pct(a)} of {n} frames",
            ]
        )
        p, a, n = analysis.fused_below_all_1s
        rows.append(
            [
                "fused median error below every estimator's median, per 1 s window",
                f"translation {_pct(p)}, rotation {_pct(a)} of {n} windows",
            ]
        )
    return rows


def timing_rows(analysis: TrialAnalysis) -> list[list[str]]:
    """The control loop's and the vision pipeline's figures: those of ``report_json``."""
    f = report_json(analysis)
    period, work, latency = f["control_period_ms"], f["tick_work_ms"], f["vision_latency_ms"]
    frames = f["frames"]
    return [
        [
            "control period nominal / p50 / p99 / max",
            f"{_fmt(period['nominal'], 1, 2)} / {_fmt(period['p50'], 1, 2)} / "
            f"{_fmt(period['p99'], 1, 2)} / {_fmt(period['max'], 1, 2)} ms",
        ],
        [
            "tick work p50 / p99 / max",
            f"{_fmt(work['p50'], 1, 2)} / {_fmt(work['p99'], 1, 2)} / {_fmt(work['max'], 1, 2)} ms",
        ],
        [
            "longest tick: work / the control thread on the CPU",
            f"{_fmt(f['longest_tick_ms']['work'], 1, 2)} / "
            f"{_fmt(f['longest_tick_ms']['cpu'], 1, 2)} ms",
        ],
        ["deadline misses", str(f["deadline_misses"])],
        [
            "frames received / processed / dropped",
            f"{frames['received']} / {frames['processed']} / {frames['dropped']}",
        ],
        ["results discarded as stale", str(f["results_stale"])],
        [
            "vision latency capture → fusion p50 / p95 / max",
            f"{_fmt(latency['p50'])} / {_fmt(latency['p95'])} / {_fmt(latency['max'])} ms",
        ],
    ]


def system_rows(analysis: TrialAnalysis) -> tuple[list[str], list[list[str]]]:
    """Header and rows of the per-system table (error columns only with ground truth)."""
    header = [
        "system",
        "kind",
        "results",
        "valid",
        "accepted",
        "rejected",
        "lost",
        "stale",
        "latency p50 / p95 (ms)",
        "processing p50 / p95 (ms)",
    ]
    if analysis.has_truth:
        header += [
            "translation error median / p95 (mm)",
            "rotation error median / p95 (deg)",
            "fused better (translation / rotation)",
        ]
    rows = []
    summaries = list(analysis.summaries) + ([analysis.fused] if analysis.fused else [])
    for s in summaries:
        fused = s.name == FUSED
        kind = "5-DOF circle" if s.five_dof else "fused" if fused else "6-DOF"
        row = [
            s.name,
            kind,
            str(s.results),
            _pct(s.valid_rate),
            "–" if fused else _pct(s.accepted_rate),
            "–" if fused else str(s.rejected),
            str(s.not_measured),
            "–" if fused else str(s.stale),
            "–" if fused else f"{_fmt(s.latency_ms.median)} / {_fmt(s.latency_ms.p95)}",
            "–" if fused else f"{_fmt(s.processing_ms.median)} / {_fmt(s.processing_ms.p95)}",
        ]
        if analysis.has_truth:
            row += [
                f"{_fmt(s.position_m.median, 1000, 2)} / {_fmt(s.position_m.p95, 1000, 2)}",
                f"{_fmt(s.attitude_rad.median, DEG, 3)} / {_fmt(s.attitude_rad.p95, DEG, 3)}",
                "–"
                if fused
                else f"{_pct(s.fused_better_position)} / {_pct(s.fused_better_attitude)}",
            ]
        rows.append(row)
    return header, rows


CSS = """
body { font-family: sans-serif; margin: 2em; max-width: 1100px; color: #222; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em; font-size: 0.9em; }
td, th { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: left; }
th { background: #f3f3f3; }
img { max-width: 100%; border: 1px solid #ddd; margin-bottom: 1em; }
.note { background: #fff8e1; padding: 0.5em 1em; border-left: 4px solid #ffb300; }
"""


def make_report(log_path: str | os.PathLike[str], out_dir: str | os.PathLike[str]) -> Path:
    """Write the plots and ``index.html`` for the trial log ``log_path`` into ``out_dir``
    (created if needed); returns the path of ``index.html``. Raises ``FileNotFoundError`` or
    ``hil.logs.triallog.TrialLogError`` for a file that is not a readable trial log."""
    return write_report(analyse(TrialLog.open(log_path)), out_dir)


def write_report(analysis: TrialAnalysis, out_dir: str | os.PathLike[str]) -> Path:
    """Write the plots and ``index.html`` of an analysed log into ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    plots: list[tuple[str, Path]] = []
    if len(analysis.t):
        plots.append(("Range and phases", plot_range(analysis, out / "range.png")))
        if analysis.has_truth:
            plots.append(("Errors against ground truth", plot_errors(analysis, out / "errors.png")))
        if analysis.systems:
            plots.append(("Estimator results", plot_results(analysis, out / "results.png")))
        plots.append(("Commands", plot_command(analysis, out / "command.png")))
        plots.append(("Timing", plot_timing(analysis, out / "timing.png")))
    index = out / "index.html"
    index.write_text(render_html(analysis, plots), encoding="utf-8")
    return index


def render_html(analysis: TrialAnalysis, plots: list[tuple[str, Path]]) -> str:
    title = f"Trial report: {Path(analysis.path).name}"
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{html.escape(title)}</title><style>{CSS}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
    ]
    notes = list(analysis.notes) or []
    if not len(analysis.t):
        notes.append("The log holds no ticks.")
    parts += [f'<p class="note">{html.escape(n)}</p>' for n in notes]
    parts += ["<h2>Summary</h2>", _table(summary_rows(analysis))]
    parts += ["<h2>Timing and vision pipeline</h2>", _table(timing_rows(analysis))]
    if analysis.systems:
        header, rows = system_rows(analysis)
        parts += ["<h2>Estimators and fusion</h2>", _table(rows, header)]
        if analysis.five_dof:
            parts.append(
                "<p>For 5-DOF circle measurements the errors are those of the circle's centre "
                "and normal (roll about the normal is not measured).</p>"
            )
    for caption, path in plots:
        parts += [
            f"<h2>{html.escape(caption)}</h2>",
            f'<img src="{html.escape(path.name)}" alt="{html.escape(caption)}">',
        ]
    if analysis.events:
        rows = [
            [f"{e.get('t', 0):.2f}", e.get("kind", ""), e.get("message", "")]
            for e in analysis.events[:300]
        ]
        parts += ["<h2>Events</h2>", _table(rows, ["t (s)", "kind", "message"])]
        if len(analysis.events) > 300:
            parts.append(f"<p>… and {len(analysis.events) - 300} more events.</p>")
    parts.append("</body></html>")
    return "\n".join(parts) + "\n"
