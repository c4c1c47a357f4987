"""``satgrasp report CAMPAIGN_DIR``: a campaign's summary in the reference study's layout, its
numbers beside ours and the ratio, the fused system as a fourth; figures like the reference's;
an HTML page and a Markdown page tying them together.

Tables (frames kind): per system and noise level, one table for translation and one for
rotation, a row per maneuver and per distance our mean ± std, the reference's range (its
tables give low-noise ranges over the maneuvers per system and distance; for high noise the
few figures it states; ../shared/REFERENCE.md) and the ratio of our mean to the reference's
best (range minimum; < 1 beats its best case). The fused system is compared with the
reference's best system at that distance. An efficiency table puts each cell's mean beside
the Cramér–Rao bound's (``hil.evaluation.crb``). Path and approach parts get tables of their
own (per distance band; per system with successes).
"""

from __future__ import annotations

import csv
import html
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from hil.analysis.campaigns.stats import Series, losses
from hil.evaluation.reference import reference_ranges
from hil.evaluation.scenarios import MANEUVERS

SYSTEMS = ("corners", "lines", "ellipses", "fused")
NOISES = ("none", "low", "high")
COLORS = {"corners": "#d95f02", "lines": "#1b9e77", "ellipses": "#7570b3", "fused": "#222222"}
_CM, _DEG = 0.01, math.pi / 180.0


class CampaignReportError(ValueError):
    """A directory that holds no campaign summary (the message names it)."""


def read_summary(campaign_dir: Path) -> list[dict[str, Any]]:
    """The rows of ``summary.csv``, numbers as floats (empty cells as NaN)."""
    path = Path(campaign_dir) / "summary.csv"
    if not path.is_file():
        raise CampaignReportError(
            f"{campaign_dir} holds no summary.csv: not a campaign directory, or its campaign "
            "has not run (satgrasp campaign FILE --out DIR)"
        )
    rows = []
    with path.open(encoding="utf-8", newline="") as f:
        for row in csv.DictReader(f):
            rows.append({k: _number(v) for k, v in row.items()})
    return rows


def _number(text: str) -> Any:
    if text == "":
        return math.nan
    try:
        return float(text)
    except ValueError:
        return text


def _fmt(mean: float, std: float, scale: float, unit: str, digits: int = 2) -> str:
    if not math.isfinite(mean):
        return "–"
    return f"{scale * mean:.{digits}f} ± {scale * std:.{digits}f}{unit}"


def _range(values: tuple[float, float] | None, scale: float, unit: str) -> str:
    if values is None:
        return "–"
    low, high = values
    if low == high:
        return f"≈ {low / scale:.2g}{unit}"
    return f"{low / scale:.2g}–{high / scale:.2g}{unit}"


def ratio(ours: float, reference: tuple[float, float] | None, scale: float) -> float | None:
    """``scale · ours`` ÷ the lower end of the reference's range (None: nothing to compare)."""
    if reference is None or not math.isfinite(ours) or reference[0] <= 0:
        return None
    return scale * ours / reference[0]


def _ratio(ours: float, reference: tuple[float, float] | None, scale: float) -> str:
    value = ratio(ours, reference, scale)
    return "–" if value is None else f"{value:.2f}"


def best_reference(distance_m: float, noise: str, which: int) -> tuple[float, float] | None:
    """The reference's best system at a distance (lowest range minimum) for translation
    (``which`` 0) or rotation (1): what the fused system is held against."""
    candidates = [reference_ranges(s, distance_m, noise)[which] for s in SYSTEMS[:3]]
    candidates = [c for c in candidates if c is not None]
    return min(candidates, key=lambda c: c[0]) if candidates else None


def reference_for(system: str, distance_m: float, noise: str, which: int):
    """The reference's range a system's cell is held against: its own, or for the fused system
    the reference's best system there."""
    if system == "fused":
        return best_reference(distance_m, noise, which)
    return reference_ranges(system, distance_m, noise)[which]


# --- tables ----------------------------------------------------------------------------------


def ratio_summary(rows: Sequence[dict[str, Any]]) -> str:
    """Markdown: per system and noise, over the matrix cells the reference has a figure for,
    the median and range of our mean error ÷ the lower end of the reference's range (the
    ratio column of the reference tables, gathered)."""
    frames = [r for r in rows if r["kind"] == "frames"]
    lines = []
    for system in SYSTEMS:
        for noise in NOISES:
            cells = [r for r in frames if r["system"] == system and r["noise"] == noise]
            columns, count = [], 0
            for which, (column, scale) in enumerate(
                (("translation_mean_m", 1.0), ("rotation_mean_deg", _DEG))
            ):
                ratios = []
                for r in cells:
                    ref = reference_for(system, r["distance_m"], noise, which)
                    value = ratio(r[column], ref, scale)
                    if value is not None:
                        ratios.append(value)
                count = max(count, len(ratios))
                columns.append(
                    f"{np.median(ratios):.3f} ({min(ratios):.3f}–{max(ratios):.3f})"
                    if ratios
                    else "–"
                )
            if count:
                lines.append(f"| {system} | {noise} | {count} | {columns[0]} | {columns[1]} |")
    if not lines:
        return ""
    head = [
        "Our mean error ÷ the lower end of the reference's range, over the cells it gives a "
        "figure for (below 1: better than the reference; fused: against its best system).\n",
        "| system | noise | cells | translation ratio, median (range) | rotation ratio, "
        "median (range) |",
        "|---|---|---|---|---|",
    ]
    return "\n".join(head + lines) + "\n"


def reference_tables(rows: Sequence[dict[str, Any]]) -> str:
    """Markdown: per system and noise, translation and rotation tables in the reference's
    layout (a row per maneuver, per distance ours | reference | ratio)."""
    frames = [r for r in rows if r["kind"] == "frames"]
    if not frames:
        return ""
    distances = sorted({r["distance_m"] for r in frames}, reverse=True)
    maneuvers = [m.name for m in MANEUVERS if any(r["maneuver"] == m.name for r in frames)]
    index = {(r["system"], r["noise"], r["distance_m"], r["maneuver"]): r for r in frames}
    out = []
    for system in [s for s in SYSTEMS if any(r["system"] == s for r in frames)]:
        for noise in [n for n in NOISES if any(r["noise"] == n for r in frames)]:
            for which, (label, column, scale, unit) in enumerate(
                (
                    ("translation error", "translation", 100.0, " cm"),
                    ("rotation error", "rotation", 1.0, "°"),
                )
            ):
                suffix = "m" if which == 0 else "deg"
                fused = " (reference: its best system)" if system == "fused" else ""
                out.append(f"#### {system}, noise {noise}: {label}{fused}\n")
                head = "| maneuver | " + " | ".join(
                    f"{d:g} m ours | {d:g} m reference | ratio" for d in distances
                )
                out += [head + " |", "|---" * (1 + 3 * len(distances)) + "|"]
                for maneuver in maneuvers:
                    cells = [maneuver]
                    for d in distances:
                        r = index.get((system, noise, d, maneuver))
                        ref = reference_for(system, d, noise, which)
                        ref_scale = _CM if which == 0 else _DEG
                        mean = r[f"{column}_mean_{suffix}"] if r else math.nan
                        std = r[f"{column}_std_{suffix}"] if r else math.nan
                        lost = f" ({int(r['lost'])} lost)" if r and r["lost"] else ""
                        ours = _fmt(mean, std, scale, unit, 3) + lost
                        ratio_scale = 1.0 if which == 0 else _DEG
                        cells += [
                            ours,
                            _range(ref, ref_scale, unit.strip() if which else " cm"),
                            _ratio(mean, ref, ratio_scale),
                        ]
                    out.append("| " + " | ".join(cells) + " |")
                out.append("")
    return "\n".join(out)


def efficiency_table(rows: Sequence[dict[str, Any]]) -> str:
    """Markdown: per system, noise and distance the range of the cells' mean errors over the
    maneuvers beside the Cramér–Rao bound's mean errors and the efficiency (mean ÷ bound)."""
    frames = [
        r for r in rows if r["kind"] == "frames" and math.isfinite(r["bound_translation_mean_m"])
    ]
    if not frames:
        return ""
    lines = [
        "| system | noise | distance | translation mean (over maneuvers) | bound | efficiency "
        "| rotation mean | bound | efficiency |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    groups: dict[tuple, list[dict]] = {}
    for r in frames:
        groups.setdefault((r["system"], r["noise"], r["distance_m"]), []).append(r)
    order = {s: i for i, s in enumerate(SYSTEMS)}
    for (system, noise, distance), group in sorted(
        groups.items(),
        key=lambda g: (
            order.get(g[0][0], 9),
            NOISES.index(g[0][1]) if g[0][1] in NOISES else 9,
            -g[0][2],
        ),
    ):
        t = [g["translation_mean_m"] for g in group]
        a = [g["rotation_mean_deg"] for g in group]
        et = [g["efficiency_translation"] for g in group]
        ea = [g["efficiency_rotation"] for g in group]
        lines.append(
            f"| {system} | {noise} | {distance:g} m | {_span(t, 1000, ' mm')} "
            f"| {1000 * group[0]['bound_translation_mean_m']:.2f} mm | {_span(et, 1, '', 1)} "
            f"| {_span(a, 1, '°')} | {group[0]['bound_rotation_mean_deg']:.3f}° | {_span(ea, 1, '', 1)} |"
        )
    return "\n".join(lines) + "\n"


def _span(values: Sequence[float], scale: float, unit: str, digits: int = 2) -> str:
    finite = [v for v in values if math.isfinite(v)]
    if not finite:
        return "–"
    low, high = scale * min(finite), scale * max(finite)
    return f"{low:.{digits}f}{unit}" if low == high else f"{low:.{digits}f}–{high:.{digits}f}{unit}"


def path_table(rows: Sequence[dict[str, Any]]) -> str:
    """Markdown: the open-loop approach path per system, noise and distance band."""
    path = [r for r in rows if r["kind"] == "path"]
    if not path:
        return ""
    lines = [
        "| system | noise | distance band | frames | valid | lost episodes (re-acquired) "
        "| translation mean ± std | rotation mean ± std | p95 |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in path:
        lines.append(
            f"| {r['system']} | {r['noise']} | {r['band']} | {int(r['samples'])} | {int(r['valid'])} "
            f"| {int(r['loss_episodes'])} ({int(r['reacquired'])}) "
            f"| {_fmt(r['translation_mean_m'], r['translation_std_m'], 1000, ' mm')} "
            f"| {_fmt(r['rotation_mean_deg'], r['rotation_std_deg'], 1, '°', 3)} "
            f"| {_fmt(r['translation_p95_m'], 0, 1000, ' mm').split(' ±')[0]} / "
            f"{_fmt(r['rotation_p95_deg'], 0, 1, '°', 3).split(' ±')[0]}° |"
        )
    return "\n".join(lines) + "\n"


def approach_table(rows: Sequence[dict[str, Any]]) -> str:
    """Markdown: the closed-loop approaches per noise (and other axes) and system."""
    approach = [r for r in rows if r["kind"] == "approach"]
    if not approach:
        return ""
    keys = [k for k in approach[0] if k in ("noise",)]
    lines = [
        "| noise | system | trials | successes | stand-off error max | results (valid) "
        "| lost episodes (re-acquired, mean time) | translation median / p95 | rotation median / p95 "
        "| latency mean / p95 |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in approach:
        success = (
            f"{int(r['successes'])}/{int(r['trials'])}" if math.isfinite(r["successes"]) else "–"
        )
        standoff = (
            f"{1000 * r['standoff_error_max_m']:.2f} mm / {r['standoff_error_max_deg']:.3f}°"
            if math.isfinite(r["standoff_error_max_m"])
            else "–"
        )
        reacquire = (
            f"{r['reacquire_time_mean_s']:.2f} s"
            if math.isfinite(r["reacquire_time_mean_s"])
            else "–"
        )
        latency = (
            f"{r['latency_mean_ms']:.0f} / {r['latency_p95_ms']:.0f} ms"
            if math.isfinite(r["latency_mean_ms"])
            else "–"
        )
        lines.append(
            f"| {' '.join(str(r[k]) for k in keys)} | {r['system']} | {int(r['trials'])} | {success} "
            f"| {standoff} | {int(r['samples'])} ({int(r['valid'])}) "
            f"| {int(r['loss_episodes'])} ({int(r['reacquired'])}, {reacquire}) "
            f"| {1000 * r['translation_median_m']:.2f} / {1000 * r['translation_p95_m']:.2f} mm "
            f"| {r['rotation_median_deg']:.3f} / {r['rotation_p95_deg']:.3f}° | {latency} |"
        )
    return "\n".join(lines) + "\n"


# --- figures ---------------------------------------------------------------------------------


def _save(figure: Figure, path: Path) -> Path:
    FigureCanvasAgg(figure)
    figure.tight_layout()
    figure.savefig(path, dpi=90)
    return path


def _frames(rows, **match) -> list[dict]:
    return [r for r in rows if r["kind"] == "frames" and all(r[k] == v for k, v in match.items())]


def _mean_over(group: list[dict], column: str) -> float:
    values = [g[column] for g in group if math.isfinite(g[column])]
    return float(np.mean(values)) if values else math.nan


def figure_error_vs_distance(rows, path: Path, noise: str = "low") -> Path | None:
    """Mean error over the maneuvers against distance per system, the reference's low-noise
    ranges as bars."""
    frames = _frames(rows, noise=noise)
    if not frames:
        return None
    figure = Figure(figsize=(10, 4))
    for k, (column, scale, label) in enumerate(
        (
            ("translation_mean_m", 100, "translation error (cm)"),
            ("rotation_mean_deg", 1, "rotation error (°)"),
        )
    ):
        ax = figure.add_subplot(1, 2, k + 1)
        for system in SYSTEMS:
            distances = sorted({r["distance_m"] for r in frames if r["system"] == system})
            if not distances:
                continue
            means = [
                scale * _mean_over(_frames(frames, system=system, distance_m=d), column)
                for d in distances
            ]
            ax.plot(distances, means, "o-", color=COLORS[system], label=f"{system} (ours)")
            shift = 0.04 * (SYSTEMS.index(system) - 1)  # the systems' bars side by side
            for d in distances:
                ref = reference_ranges(system, d, noise)[k] if system != "fused" else None
                if ref is not None:  # translation in cm, rotation in degrees
                    unit = _CM if k == 0 else _DEG
                    ax.plot(
                        [d + shift, d + shift],
                        [ref[0] / unit, ref[1] / unit],
                        color=COLORS[system],
                        lw=6,
                        alpha=0.25,
                    )
        ax.set_yscale("log")
        ax.set_xlabel("distance (m)")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    figure.axes[0].legend(fontsize=8)
    figure.suptitle(f"error vs distance, noise {noise} (bars: the reference's range)")
    return _save(figure, path)


def figure_error_vs_noise(rows, path: Path, distance_m: float = 2.0) -> Path | None:
    frames = _frames(rows, distance_m=distance_m)
    if not frames:
        return None
    figure = Figure(figsize=(10, 4))
    noises = [n for n in NOISES if any(r["noise"] == n for r in frames)]
    for k, (column, scale, label) in enumerate(
        (
            ("translation_mean_m", 100, "translation error (cm)"),
            ("rotation_mean_deg", 1, "rotation error (°)"),
        )
    ):
        ax = figure.add_subplot(1, 2, k + 1)
        for system in SYSTEMS:
            means = [
                scale * _mean_over(_frames(frames, system=system, noise=n), column) for n in noises
            ]
            ax.plot(noises, means, "o-", color=COLORS[system], label=system)
        ax.set_yscale("log")
        ax.set_xlabel("noise")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    figure.axes[0].legend(fontsize=8)
    figure.suptitle(f"error vs noise at {distance_m:g} m (mean over the maneuvers)")
    return _save(figure, path)


def figure_error_vs_maneuver(
    rows, path: Path, distance_m: float = 2.0, noise: str = "low"
) -> Path | None:
    frames = _frames(rows, distance_m=distance_m, noise=noise)
    if not frames:
        return None
    maneuvers = [m.name for m in MANEUVERS if any(r["maneuver"] == m.name for r in frames)]
    figure = Figure(figsize=(11, 4.5))
    width = 0.8 / len(SYSTEMS)
    for k, (column, std, scale, label) in enumerate(
        (
            ("translation_mean_m", "translation_std_m", 100, "translation error (cm)"),
            ("rotation_mean_deg", "rotation_std_deg", 1, "rotation error (°)"),
        )
    ):
        ax = figure.add_subplot(1, 2, k + 1)
        for i, system in enumerate(SYSTEMS):
            cells = {r["maneuver"]: r for r in _frames(frames, system=system)}
            x = np.arange(len(maneuvers)) + (i - 1.5) * width
            values = [scale * cells[m][column] if m in cells else np.nan for m in maneuvers]
            errors = [scale * cells[m][std] if m in cells else np.nan for m in maneuvers]
            ax.bar(x, values, width, yerr=errors, color=COLORS[system], label=system)
        ax.set_xticks(np.arange(len(maneuvers)), maneuvers, rotation=35, ha="right", fontsize=8)
        ax.set_yscale("log")
        ax.set_ylabel(label)
    figure.axes[0].legend(fontsize=8)
    figure.suptitle(f"error vs maneuver at {distance_m:g} m, noise {noise} (mean ± std)")
    return _save(figure, path)


def figure_systems_with_bound(rows, path: Path, noise: str = "low") -> Path | None:
    """Systems compared at a fixed noise per distance, the Cramér–Rao bound's mean as a tick."""
    frames = _frames(rows, noise=noise)
    if not frames:
        return None
    distances = sorted({r["distance_m"] for r in frames}, reverse=True)
    figure = Figure(figsize=(10, 4))
    width = 0.8 / len(SYSTEMS)
    for k, (column, bound, scale, label) in enumerate(
        (
            ("translation_mean_m", "bound_translation_mean_m", 1000, "translation error (mm)"),
            ("rotation_mean_deg", "bound_rotation_mean_deg", 1, "rotation error (°)"),
        )
    ):
        ax = figure.add_subplot(1, 2, k + 1)
        for i, system in enumerate(SYSTEMS):
            x = np.arange(len(distances)) + (i - 1.5) * width
            groups = [_frames(frames, system=system, distance_m=d) for d in distances]
            ax.bar(
                x,
                [scale * _mean_over(g, column) for g in groups],
                width,
                color=COLORS[system],
                label=system,
            )
            ax.plot(
                x, [scale * _mean_over(g, bound) for g in groups], "_", color="red", ms=14, mew=2
            )
        ax.set_xticks(np.arange(len(distances)), [f"{d:g} m" for d in distances])
        ax.set_yscale("log")
        ax.set_ylabel(label)
    figure.axes[0].legend(fontsize=8)
    figure.suptitle(f"systems at noise {noise} (mean over maneuvers; red: Cramér–Rao bound)")
    return _save(figure, path)


def figure_loss_traces(campaign_dir: Path, path: Path) -> Path | None:
    """Error against time of the trials with the most loss episodes per system (path and
    approach parts), lost stretches shaded."""
    chosen: dict[str, tuple[int, str, Series]] = {}
    for result_file in sorted((Path(campaign_dir) / "trials").glob("*/*.json")):
        data = json.loads(result_file.read_text(encoding="utf-8"))
        if data["trial"]["kind"] == "frames":
            continue
        for row in data["rows"]:
            if row["cell"].get("band", "all") != "all":
                continue
            series = Series.from_dict(row["series"])
            episodes = losses(series).episodes
            system = row["cell"]["system"]
            label = f"{data['trial']['part']} {system} seed {data['trial']['seed']}"
            if episodes and episodes > chosen.get(system, (0,))[0]:
                chosen[system] = (episodes, label, series)
    if not chosen:
        return None
    figure = Figure(figsize=(10, 2.6 * len(chosen)))
    for k, (system, (episodes, label, series)) in enumerate(sorted(chosen.items())):
        ax = figure.add_subplot(len(chosen), 1, k + 1)
        t = np.asarray(series.t)
        error = 1000 * np.asarray(series.position_m)
        ax.plot(t, error, ".", ms=2, color=COLORS.get(system, "k"))
        for i in np.flatnonzero(~np.asarray(series.valid, bool)):
            ax.axvspan(t[i] - 0.02, t[i] + 0.02, color="red", alpha=0.15, lw=0)
        ax.set_ylabel("translation error (mm)")
        ax.set_yscale("log")
        ax.set_title(f"{label}: {episodes} loss episode(s), lost answers shaded", fontsize=9)
    figure.axes[-1].set_xlabel("time (s)")
    return _save(figure, path)


# --- the page --------------------------------------------------------------------------------


def _markdown_to_html(text: str) -> str:
    """The subset our tables use: '####' headings, pipe tables, paragraphs."""
    out, table = [], []

    def flush() -> None:
        if table:
            rows = [[c.strip() for c in line.strip("|").split("|")] for line in table]
            body = [r for r in rows[1:] if not all(set(c) <= {"-"} for c in r)]
            out.append(
                "<table><tr>" + "".join(f"<th>{html.escape(c)}</th>" for c in rows[0]) + "</tr>"
            )
            out.extend(
                "<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in r) + "</tr>" for r in body
            )
            out.append("</table>")
            table.clear()

    for line in text.splitlines():
        if line.startswith("|"):
            table.append(line)
            continue
        flush()
        if line.startswith("#"):
            level = min(len(line) - len(line.lstrip("#")), 6)
            out.append(f"<h{level}>{html.escape(line.lstrip('#').strip())}</h{level}>")
        elif line.strip():
            out.append(f"<p>{html.escape(line)}</p>")
    flush()
    return "\n".join(out)


def write_campaign_report(campaign_dir: Path, out_dir: Path | None = None) -> tuple[Path, Path]:
    """Write the figures, ``report.md`` and ``index.html``; returns (index.html, report.md)."""
    from hil.analysis.report import CSS

    campaign_dir = Path(campaign_dir)
    rows = read_summary(campaign_dir)
    out = Path(out_dir) if out_dir is not None else campaign_dir / "report"
    out.mkdir(parents=True, exist_ok=True)
    figures = [
        (
            "Error vs distance per system (low noise)",
            figure_error_vs_distance(rows, out / "error_vs_distance.png"),
        ),
        ("Error vs noise at 2 m", figure_error_vs_noise(rows, out / "error_vs_noise.png")),
        (
            "Error vs maneuver at 2 m, low noise",
            figure_error_vs_maneuver(rows, out / "error_vs_maneuver.png"),
        ),
        (
            "Systems compared at low noise, with the Cramér–Rao bound",
            figure_systems_with_bound(rows, out / "systems_low_noise.png"),
        ),
        (
            "Error vs time of lost-track episodes",
            figure_loss_traces(campaign_dir, out / "loss_traces.png"),
        ),
    ]
    figures = [(caption, p) for caption, p in figures if p is not None]
    sections = [
        ("Against the reference", ratio_summary(rows)),
        ("Test matrix in the reference's layout", reference_tables(rows)),
        ("Efficiency: measured mean error ÷ the Cramér–Rao bound's", efficiency_table(rows)),
        ("Open-loop approach path", path_table(rows)),
        ("Closed-loop approaches", approach_table(rows)),
    ]
    markdown = [f"# Campaign {campaign_dir.name}\n"]
    for title, text in sections:
        if text:
            markdown += [f"## {title}\n", text]
    markdown += ["## Figures\n"] + [f"![{c}]({p.name})\n" for c, p in figures]
    md_path = out / "report.md"
    md_path.write_text("\n".join(markdown), encoding="utf-8")
    body = _markdown_to_html("\n".join(m for m in markdown if not m.startswith("![")))
    images = "\n".join(
        f'<h2>{html.escape(c)}</h2><img src="{html.escape(p.name)}" alt="{html.escape(c)}">'
        for c, p in figures
    )
    index = out / "index.html"
    index.write_text(
        '<!DOCTYPE html><html lang="en"><head><meta charset="utf-8">'
        f"<title>Campaign {html.escape(campaign_dir.name)}</title><style>{CSS}</style></head>"
        f"<body>{body}{images}</body></html>\n",
        encoding="utf-8",
    )
    return index, md_path
