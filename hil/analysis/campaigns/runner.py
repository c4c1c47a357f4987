"""Run a campaign: expand it into trials, run those without a result on an executor, and
summarise every result into ``OUT/summary.csv`` and ``OUT/summary.parquet``.

* **Resumable**: a trial counts only once its result file exists (``trials.execute`` renames
  it into place when the trial is done); running the campaign again runs the others only.
* **Parallel**: ``local`` runs ``workers`` trials at once in processes of this machine (in this
  process when ``workers`` is 1); ``dask`` submits them to a Dask distributed scheduler
  (``scheduler`` address, or a ``LocalCluster`` of ``workers`` processes on 127.0.0.1), the
  optional extra ``satgrasp[cluster]``. A remote cluster's workers must see ``out_dir``.
* **Deterministic**: a trial is a function of its inputs and seed, and the summary pools
  results in the campaign's trial order, never in the order they finished — so the same file
  and seeds give a byte-identical ``summary.csv`` on any executor. What depends on the machine
  (processing and wall times, deadline misses) goes to ``timing.csv`` and ``trials.csv``.
"""

from __future__ import annotations

import csv
import io
import math
import multiprocessing
import os
import time
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from configuration.campaign import CampaignConfig
from hil.analysis.campaigns.spec import TrialSpec, expand
from hil.analysis.campaigns.stats import CellStats, Series, cell_stats
from hil.analysis.campaigns.trials import execute, read_result, write_atomic

#: (finished trial key, its wall seconds, trials done, trials to run)
Progress = Callable[[str, float, int, int], None]

STATS_COLUMNS = tuple(CellStats.__dataclass_fields__)
#: Columns of the approach kind's trial outcomes (empty for the open-loop kinds).
OUTCOME_COLUMNS = ("successes", "standoff_error_max_m", "standoff_error_max_deg")
BOUND_COLUMNS = (
    "bound_translation_mean_m",
    "bound_rotation_mean_deg",
    "efficiency_translation",
    "efficiency_rotation",
)


@dataclass(frozen=True, slots=True)
class CampaignRun:
    """What a run did: trials in the campaign, run now, found finished; its output files."""

    trials: int
    ran: int
    skipped: int
    wall_s: float
    summary_csv: Path
    summary_parquet: Path | None


def run_campaign(
    config: CampaignConfig,
    out_dir: Path,
    *,
    workers: int = 1,
    executor: str = "local",
    scheduler: str | None = None,
    progress: Progress | None = None,
    source: str | None = None,
) -> CampaignRun:
    """Run every trial of ``config`` that has no result in ``out_dir`` yet, then summarise.
    ``source``: the campaign file's text, kept as ``OUT/campaign.yaml``."""
    if executor not in ("local", "dask"):
        raise ValueError(f"--executor must be local or dask; got {executor!r}")
    if workers < 1:
        raise ValueError(f"--workers must be at least 1; got {workers}")
    started = time.perf_counter()
    trials = expand(config)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if source is not None:
        write_atomic(out_dir / "campaign.yaml", source)
    pending = [t for t in trials if read_result(out_dir, t) is None]
    if pending:
        run = _run_dask if executor == "dask" else _run_local
        run(pending, out_dir, workers, scheduler, progress)
    csv_path, parquet_path = write_summary(trials, out_dir)
    return CampaignRun(
        len(trials),
        len(pending),
        len(trials) - len(pending),
        time.perf_counter() - started,
        csv_path,
        parquet_path,
    )


# --- executors -------------------------------------------------------------------------------


def _run_local(
    trials: Sequence[TrialSpec],
    out_dir: Path,
    workers: int,
    scheduler: str | None,
    progress: Progress | None,
) -> None:
    if scheduler is not None:
        raise ValueError("--scheduler needs --executor dask")
    total = len(trials)
    if workers == 1:
        for done, trial in enumerate(trials, 1):
            key, seconds = execute(trial.to_dict(), str(out_dir))
            if progress:
                progress(key, seconds, done, total)
        return
    # spawn: the parent holds threads (progress display) and pybullet state that a fork copies
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=workers, mp_context=context) as pool:
        futures = {pool.submit(execute, t.to_dict(), str(out_dir)) for t in trials}
        done = 0
        try:
            while futures:
                finished, futures = wait(futures, return_when=FIRST_COMPLETED)
                for future in finished:
                    key, seconds = future.result()
                    done += 1
                    if progress:
                        progress(key, seconds, done, total)
        except BaseException:
            for future in futures:
                future.cancel()
            raise


def _run_dask(
    trials: Sequence[TrialSpec],
    out_dir: Path,
    workers: int,
    scheduler: str | None,
    progress: Progress | None,
) -> None:
    try:
        from distributed import Client, LocalCluster, as_completed
    except ImportError:
        raise ValueError(
            "--executor dask needs the optional extra: pip install 'satgrasp[cluster]'"
        ) from None
    import logging

    cluster = None
    if scheduler is None:
        cluster = LocalCluster(
            n_workers=workers,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=None,
            silence_logs=logging.ERROR,
        )
    try:
        with Client(cluster if cluster is not None else scheduler) as client:
            futures = [
                client.submit(execute, t.to_dict(), str(out_dir.resolve()), key=t.key, pure=False)
                for t in trials
            ]
            for done, future in enumerate(as_completed(futures), 1):
                key, seconds = future.result()
                if progress:
                    progress(key, seconds, done, len(trials))
    finally:
        if cluster is not None:
            cluster.close()


# --- summary ---------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class CellRow:
    """One summary row: the part, its kind, the cell's keys and its statistics."""

    part: str
    kind: str
    cell: dict[str, Any]
    stats: CellStats
    outcomes: dict[str, Any]
    bound: tuple[float, float] | None  # mean translation (m), rotation (deg) at the bound


def collect(trials: Sequence[TrialSpec], out_dir: Path) -> tuple[list[CellRow], list[dict]]:
    """Cells in the order they first appear in the campaign, each pooled over its trials in
    campaign order; and one dict per trial (its key, cell, seed and outcomes). Trials without
    a result are left out (a summary of a campaign still running)."""
    from hil.evaluation.crb import mean_error_bound

    cells: dict[tuple, tuple[TrialSpec, dict, list[Series], list[dict]]] = {}
    per_trial = []
    for trial in trials:
        result = read_result(out_dir, trial)
        if result is None:
            continue
        per_trial.append(
            {"key": trial.key, "part": trial.part, "seed": trial.seed, **trial.cell}
            | result["extra"]
            | {k: v for k, v in result["timing"].items() if not isinstance(v, list)}
        )
        for row in result["rows"]:
            key = (trial.part, _freeze(row["cell"]))
            entry = cells.setdefault(key, (trial, row["cell"], [], []))
            entry[2].append(Series.from_dict(row["series"]))
            if result["extra"]:
                entry[3].append(result["extra"])
    rows = []
    for (part, _), (trial, cell, series, extras) in cells.items():
        bound = None
        if trial.kind == "frames":
            bound = mean_error_bound(
                cell["system"],
                cell["noise"],
                float(trial.params["distance_m"]),
                camera=trial.params.get("camera", "reference"),
                mockup=trial.params.get("mockup", "default"),
            )
        rows.append(CellRow(part, trial.kind, cell, cell_stats(series), _outcomes(extras), bound))
    return rows, per_trial


def _freeze(value: Any) -> Any:
    if isinstance(value, dict):
        return tuple((k, _freeze(v)) for k, v in value.items())
    if isinstance(value, list):
        return tuple(_freeze(v) for v in value)
    return value


def _outcomes(extras: list[dict]) -> dict[str, Any]:
    if not extras:
        return {}

    def worst(name: str) -> float:
        values = [e[name] for e in extras if isinstance(e.get(name), int | float)]
        return max(values) if values else math.nan

    return {
        "successes": sum(bool(e.get("success")) for e in extras),
        "standoff_error_max_m": worst("standoff_error_m"),
        "standoff_error_max_deg": worst("standoff_error_deg"),
    }


def summary_table(rows: Sequence[CellRow]) -> tuple[list[str], list[list[Any]]]:
    """(columns, values): part, kind, every cell key (in first-appearance order), the cell
    statistics, the approach outcomes and the bound with the efficiency (measured ÷ bound)."""
    keys: list[str] = []
    for row in rows:
        keys += [k for k in row.cell if k not in keys]
    columns = ["part", "kind", *keys, *STATS_COLUMNS, *OUTCOME_COLUMNS, *BOUND_COLUMNS]
    values = []
    for row in rows:
        stats = asdict(row.stats)
        bound = row.bound or (math.nan, math.nan)
        efficiency = (
            _ratio(stats["translation_mean_m"], bound[0]),
            _ratio(stats["rotation_mean_deg"], bound[1]),
        )
        values.append(
            [row.part, row.kind]
            + [row.cell.get(k) for k in keys]
            + [stats[c] for c in STATS_COLUMNS]
            + [row.outcomes.get(c) for c in OUTCOME_COLUMNS]
            + [*bound, *efficiency]
        )
    return columns, values


def _ratio(measured: float, bound: float) -> float:
    if not (math.isfinite(measured) and math.isfinite(bound)) or bound <= 0:
        return math.nan
    return measured / bound


def _cell_text(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float):
        return "" if math.isnan(value) else repr(value)  # shortest exact: same float, same text
    if isinstance(value, list):
        return ",".join(map(str, value))
    return str(value)


def csv_text(columns: Sequence[str], values: Sequence[Sequence[Any]]) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(columns)
    for row in values:
        writer.writerow([_cell_text(v) for v in row])
    return buffer.getvalue()


def write_summary(trials: Sequence[TrialSpec], out_dir: Path) -> tuple[Path, Path | None]:
    """``summary.csv``, ``summary.parquet`` (when pyarrow is installed), ``trials.csv`` and
    ``timing.csv`` from the results in ``out_dir``; each written whole to a temporary file and
    renamed (a killed Parquet writer leaves an unreadable file)."""
    rows, per_trial = collect(trials, out_dir)
    columns, values = summary_table(rows)
    csv_path = out_dir / "summary.csv"
    write_atomic(csv_path, csv_text(columns, values))
    trial_columns: list[str] = []
    for t in per_trial:
        trial_columns += [k for k in t if k not in trial_columns]
    write_atomic(
        out_dir / "trials.csv",
        csv_text(trial_columns, [[t.get(c) for c in trial_columns] for t in per_trial]),
    )
    write_atomic(out_dir / "timing.csv", _timing_csv(trials, out_dir))
    return csv_path, _write_parquet(out_dir / "summary.parquet", columns, values)


def _timing_csv(trials: Sequence[TrialSpec], out_dir: Path) -> str:
    """Per trial: wall seconds and median processing time per system (machine-dependent)."""
    values = []
    for trial in trials:
        result = read_result(out_dir, trial)
        if result is None:
            continue
        timing = result["timing"]
        medians = {
            k: float(np.median(v))
            for k, v in timing.items()
            if k.endswith("processing_ms") and isinstance(v, list) and len(v)
        }
        for name, median in medians.items() or [("", math.nan)]:
            values.append([trial.key, timing.get("wall_s"), timing.get("cpu_s"), name, median])
    return csv_text(("trial", "wall_s", "cpu_s", "series", "processing_median_ms"), values)


def _write_parquet(path: Path, columns: Sequence[str], values: Sequence[Sequence[Any]]):
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        return None
    arrays = {}
    for i, name in enumerate(columns):
        column = [row[i] for row in values]
        present = [v for v in column if v is not None]
        if present and all(isinstance(v, int | float) and not isinstance(v, bool) for v in present):
            arrays[name] = pa.array([math.nan if v is None else float(v) for v in column])
        else:
            arrays[name] = pa.array([None if v is None else _cell_text(v) for v in column])
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    pq.write_table(pa.table(arrays), tmp)
    os.replace(tmp, path)
    return path
