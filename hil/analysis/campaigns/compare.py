"""``satgrasp compare A B``: two trials (MCAP logs) or two campaigns (directories), before /
after a change or simulated vs replayed — aligned tables of the differences with significance
where it applies, and overlaid plots.

Significance: the two-sided Mann–Whitney U test (Mann & Whitney 1947; no normality assumed;
``scipy.stats.mannwhitneyu``) of B's errors against A's. For campaigns it compares the cell's
per-trial mean errors when both sides have at least ``MIN_TRIALS`` trials (trials are
independent); otherwise the answers themselves, which are correlated from frame to frame in a
trial, so their p-value is optimistic — the table says which was used. For two trials it
compares the answers of each system (the same caveat). ``significant`` is p < 0.05.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from scipy.stats import mannwhitneyu

from hil.analysis.campaigns.stats import Series

MIN_TRIALS = 3
ALPHA = 0.05


@dataclass(frozen=True, slots=True)
class Difference:
    """One aligned quantity: its label, A's and B's value, and the test (p, what it used)."""

    label: str
    quantity: str
    a: float
    b: float
    p: float = math.nan
    basis: str = ""

    @property
    def ratio(self) -> float:
        return self.b / self.a if self.a and math.isfinite(self.a) else math.nan


def mann_whitney(a: Sequence[float], b: Sequence[float]) -> float:
    """Two-sided p-value, NaN when either side has fewer than two finite values."""
    a = [v for v in a if math.isfinite(v)]
    b = [v for v in b if math.isfinite(v)]
    if len(a) < 2 or len(b) < 2:
        return math.nan
    if np.allclose(a, a[0]) and np.allclose(b, b[0]) and math.isclose(a[0], b[0]):
        return 1.0
    return float(mannwhitneyu(a, b, alternative="two-sided").pvalue)


# --- campaigns -------------------------------------------------------------------------------


def _cells(campaign_dir: Path) -> dict[tuple, list[Series]]:
    """Cell label → its series, one per trial, from the result files (campaign-order free:
    sorted by trial key)."""
    cells: dict[tuple, list[Series]] = {}
    files = sorted((Path(campaign_dir) / "trials").glob("*/*.json"))
    if not files:
        raise ValueError(f"{campaign_dir} holds no trial results (trials/*/*.json)")
    for path in files:
        data = json.loads(path.read_text(encoding="utf-8"))
        for row in data["rows"]:
            label = (data["trial"]["part"], *(f"{k}={v}" for k, v in row["cell"].items()))
            cells.setdefault(label, []).append(Series.from_dict(row["series"]))
    return cells


def _valid(series: Series, name: str, scale: float) -> np.ndarray:
    values = np.asarray(getattr(series, name), float)[np.asarray(series.valid, bool)]
    return scale * values[np.isfinite(values)]


def compare_campaigns(a_dir: Path, b_dir: Path) -> list[Difference]:
    a_cells, b_cells = _cells(a_dir), _cells(b_dir)
    differences = []
    for label in [k for k in a_cells if k in b_cells]:
        for name, quantity, scale in (
            ("position_m", "translation mean (mm)", 1000.0),
            ("attitude_rad", "rotation mean (°)", math.degrees(1.0)),
        ):
            a, b = a_cells[label], b_cells[label]
            a_trials = [float(v.mean()) for v in (_valid(s, name, scale) for s in a) if len(v)]
            b_trials = [float(v.mean()) for v in (_valid(s, name, scale) for s in b) if len(v)]
            a_all = np.concatenate([_valid(s, name, scale) for s in a])
            b_all = np.concatenate([_valid(s, name, scale) for s in b])
            if min(len(a_trials), len(b_trials)) >= MIN_TRIALS:
                p, basis = mann_whitney(a_trials, b_trials), f"trial means ({len(a)}/{len(b)})"
            else:
                p, basis = mann_whitney(a_all, b_all), f"answers ({len(a_all)}/{len(b_all)})"
            mean_a = float(a_all.mean()) if len(a_all) else math.nan
            mean_b = float(b_all.mean()) if len(b_all) else math.nan
            differences.append(Difference(" ".join(label), quantity, mean_a, mean_b, p, basis))
        lost_a = sum(len(s.valid) - sum(s.valid) for s in a_cells[label])
        lost_b = sum(len(s.valid) - sum(s.valid) for s in b_cells[label])
        differences.append(Difference(" ".join(label), "lost answers", lost_a, lost_b))
    if not differences:
        raise ValueError(f"{a_dir} and {b_dir} have no cell in common")
    return differences


# --- trials ----------------------------------------------------------------------------------


def _trial_errors(path: Path) -> tuple[dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]], dict]:
    """Per system and ``fused``: (time s, position error mm, attitude error °) of the valid,
    judged answers; and the trial's outcome figures."""
    from hil.analysis.trial_analysis import analyse
    from hil.logs.triallog import TrialLog

    analysis = analyse(TrialLog.open(path))
    errors = {}
    for name, s in analysis.series.items():
        keep = s.valid & np.isfinite(s.position_error_m)
        errors[name] = (
            s.capture_t[keep],
            1000 * s.position_error_m[keep],
            np.degrees(s.attitude_error_rad[keep]),
        )
    keep = np.isfinite(analysis.fused_position_error_m)
    errors["fused"] = (
        analysis.t[keep],
        1000 * analysis.fused_position_error_m[keep],
        np.degrees(analysis.fused_attitude_error_rad[keep]),
    )
    data = analysis.outcome_data
    outcome = {
        "success": float(analysis.success),
        "duration (s)": float(analysis.t[-1]) if len(analysis.t) else math.nan,
        "stand-off error (mm)": 1000 * float(data.get("standoff_error_m") or math.nan),
        "stand-off error (°)": math.degrees(float(data.get("standoff_error_rad") or math.nan)),
        "vision latency p95 (ms)": analysis.vision.latency_ms.p95,
        "frames dropped": float(analysis.vision.frames_dropped),
    }
    return errors, outcome


def compare_trials(a_path: Path, b_path: Path) -> tuple[list[Difference], dict, dict]:
    a, a_outcome = _trial_errors(a_path)
    b, b_outcome = _trial_errors(b_path)
    differences = [Difference("trial", k, a_outcome[k], b_outcome[k]) for k in a_outcome]
    for system in [s for s in a if s in b]:
        for index, quantity in ((1, "translation median (mm)"), (2, "rotation median (°)")):
            va, vb = a[system][index], b[system][index]
            differences.append(
                Difference(
                    system,
                    quantity,
                    float(np.median(va)) if len(va) else math.nan,
                    float(np.median(vb)) if len(vb) else math.nan,
                    mann_whitney(va, vb),
                    f"answers ({len(va)}/{len(vb)})",
                )
            )
    return differences, a, b


# --- output ----------------------------------------------------------------------------------


def markdown(differences: Sequence[Difference], a_name: str, b_name: str) -> str:
    lines = [
        f"A = {a_name}, B = {b_name}; p: two-sided Mann–Whitney U, significant when p < {ALPHA}",
        "",
        "| cell | quantity | A | B | B − A | B ÷ A | p | significant | test on |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for d in differences:
        p = "–" if math.isnan(d.p) else f"{d.p:.3g}"
        significant = "–" if math.isnan(d.p) else ("yes" if d.p < ALPHA else "no")
        ratio = "–" if math.isnan(d.ratio) else f"{d.ratio:.3f}"
        lines.append(
            f"| {d.label} | {d.quantity} | {d.a:.4g} | {d.b:.4g} | {d.b - d.a:+.4g} | {ratio} "
            f"| {p} | {significant} | {d.basis or '–'} |"
        )
    return "\n".join(lines) + "\n"


def plot_campaigns(differences: Sequence[Difference], path: Path) -> Path:
    """B against A per cell (log-log), the diagonal drawn: a point below it is better in B."""
    figure = Figure(figsize=(10, 4.5))
    for k, quantity in enumerate(("translation mean (mm)", "rotation mean (°)")):
        ax = figure.add_subplot(1, 2, k + 1)
        rows = [d for d in differences if d.quantity == quantity and d.a > 0 and d.b > 0]
        significant = [d for d in rows if d.p < ALPHA]
        ax.loglog([d.a for d in rows], [d.b for d in rows], "o", ms=4, alpha=0.6, label="cell")
        ax.loglog(
            [d.a for d in significant], [d.b for d in significant], "o", mfc="none", mec="red",
            ms=8, label=f"p < {ALPHA}",
        )  # fmt: skip
        if rows:
            low = min(min(d.a, d.b) for d in rows)
            high = max(max(d.a, d.b) for d in rows)
            ax.plot([low, high], [low, high], "k--", lw=1)
        ax.set_xlabel(f"A: {quantity}")
        ax.set_ylabel(f"B: {quantity}")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    FigureCanvasAgg(figure)
    figure.tight_layout()
    figure.savefig(path, dpi=90)
    return path


def plot_trials(a: dict, b: dict, path: Path, a_name: str, b_name: str) -> Path:
    """Errors against time of every system and the fused estimate, A and B overlaid."""
    systems = [s for s in a if s in b]
    figure = Figure(figsize=(10, 2.4 * len(systems)))
    for k, system in enumerate(systems):
        ax = figure.add_subplot(len(systems), 1, k + 1)
        for data, name, color in ((a, a_name, "#1f77b4"), (b, b_name, "#d62728")):
            t, position, _ = data[system]
            ax.plot(t, position, ".", ms=2, color=color, label=name, alpha=0.7)
        ax.set_yscale("log")
        ax.set_ylabel("translation error (mm)")
        ax.set_title(system, fontsize=9)
        ax.legend(fontsize=7, markerscale=4)
    figure.axes[-1].set_xlabel("trial time (s)")
    FigureCanvasAgg(figure)
    figure.tight_layout()
    figure.savefig(path, dpi=90)
    return path
