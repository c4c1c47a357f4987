"""``satgrasp report RUN.mcap``: PNG plots and a small HTML page from one trial log.

Reads only the log (``hil.logs.triallog.TrialLog``), analysed by ``hil.analysis.trial_analysis``. Plots:
range with the phase timeline, translation and rotation error of every estimator and of the
fused estimate against ground truth (skipped, and said so, for a log without truth), the
per-system accepted/rejected/lost raster and the commanded speeds. Matplotlib is used through
its object API on the Agg canvas (no pyplot state, no display needed).
"""

from __future__ import annotations

import html
import math
import os
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from hil.analysis.trial_analysis import FUSED, TrialAnalysis, analyse, phase_spans
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
STATUS_STYLE = {  # colour, label
    "accepted": ("#2ca02c", "accepted by fusion"),
    "rejected": ("#ff7f0e", "rejected by fusion"),
    "unused": ("#9e9e9e", "valid, not fused"),
    "lost": ("#d62728", "lost"),
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
    for ax, errors, scale, unit in (
        (ax_p, analysis.position_error_m, 1000.0, "translation error (mm)"),
        (ax_a, analysis.attitude_error_rad, math.degrees(1.0), "rotation error (deg)"),
    ):
        _shade_phases(ax, analysis, alpha=0.35)
        for i, system in enumerate(analysis.systems):
            values = errors[system] * scale
            status = analysis.status[system]
            color = _system_color(system, i)
            label = system + (" (circle centre / normal)" if system in analysis.five_dof else "")
            used = status != "rejected"
            ax.plot(analysis.t[used], values[used], ".", ms=3, color=color, label=label)
            if (~used).any():
                ax.plot(
                    analysis.t[~used],
                    values[~used],
                    "x",
                    ms=5,
                    color=color,
                    label=f"{system} rejected",
                )
        ax.plot(analysis.t, errors[FUSED] * scale, "-", color="black", lw=1.6, label="fused")
        if any((np.isfinite(v) & (v > 0)).any() for v in errors.values()):
            ax.set_yscale("log")
        ax.set_ylabel(unit)
        ax.grid(alpha=0.3, which="both")
    ax_p.set_title("Errors against ground truth: each estimator and the fused estimate")
    ax_p.legend(loc="upper right", fontsize=8, ncols=3)
    ax_a.set_xlabel("time (s)")
    return _save(fig, path)


def plot_measurements(analysis: TrialAnalysis, path: Path) -> Path:
    fig = Figure(figsize=(10, 1.2 + 0.6 * max(1, len(analysis.systems))), layout="constrained")
    ax = fig.add_subplot()
    _shade_phases(ax, analysis, alpha=0.35)
    for row, system in enumerate(analysis.systems):
        status = analysis.status[system]
        for name, (color, label) in STATUS_STYLE.items():
            mask = status == name
            if mask.any():
                ax.plot(
                    analysis.t[mask],
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
    ax.set_xlabel("time (s)")
    ax.set_title("Measurements per tick")
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
        ax_v.plot(analysis.t, analysis.track_velocity, color="#1f77b4", label="track velocity")
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


# --- HTML -------------------------------------------------------------------------------------


def _fmt(value: float, scale: float = 1.0, digits: int = 1, unit: str = "") -> str:
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


def summary_rows(analysis: TrialAnalysis) -> list[list[str]]:
    """The trial summary as (label, value) rows."""
    h = analysis.header
    rows = [
        ["outcome", analysis.outcome],
        ["abort reason", analysis.abort_reason or "–"],
        ["duration", f"{analysis.duration_s:.2f} s"],
        ["ticks", str(len(analysis.t))],
        [
            "log",
            "recovered (writer killed)"
            if analysis.recovered
            else "complete"
            if analysis.complete
            else "not closed by its writer",
        ],
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
    if analysis.has_truth:
        p, a, n = analysis.fused_below_all
        rows.append(
            [
                "fused error below every single estimator at the same tick",
                f"translation {_pct(p)}, rotation {_pct(a)} of {n} ticks",
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


def system_rows(analysis: TrialAnalysis) -> tuple[list[str], list[list[str]]]:
    """Header and rows of the per-system table (error columns only with ground truth)."""
    header = ["system", "kind", "ticks", "valid", "accepted", "rejected", "lost"]
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
            str(s.ticks),
            _pct(s.valid_rate),
            "–" if fused else _pct(s.accepted_rate),
            "–" if fused else str(s.rejected),
            str(s.lost),
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
    log = TrialLog.open(log_path)
    analysis = analyse(log)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    plots: list[tuple[str, Path]] = []
    if len(analysis.t):
        plots.append(("Range and phases", plot_range(analysis, out / "range.png")))
        if analysis.has_truth:
            plots.append(("Errors against ground truth", plot_errors(analysis, out / "errors.png")))
        if analysis.systems:
            plots.append(("Measurements", plot_measurements(analysis, out / "measurements.png")))
        plots.append(("Commands", plot_command(analysis, out / "command.png")))
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
