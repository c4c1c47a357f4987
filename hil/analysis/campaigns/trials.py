"""Run one trial of a campaign and write its result file — the whole job of a worker, on any
executor: ``execute(trial, out_dir)`` needs nothing but its arguments and the file system.

The result file (``OUT/trials/<key>.json``) is written to a temporary name and renamed into
place, so it exists only for a finished trial: an interrupted one leaves no result (and at
most a stale temporary file or trial log, replaced when it runs again) and is never counted.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import json
import math
import os
import time
from pathlib import Path
from typing import Any

from hil.analysis.campaigns.spec import RESULT_VERSION, TrialSpec
from hil.analysis.campaigns.stats import Series

#: Distance bands (m, descending edges) of the path kind's per-band cells.
PATH_BANDS_M = (2.5, 2.0, 1.5, 1.0, 0.75, 0.49)
#: Frame rate the open-loop kinds stamp their frames with (``hil.evaluation``'s 30 fps).
OPEN_LOOP_FPS = 30.0


def result_path(out_dir: Path, trial: TrialSpec) -> Path:
    return Path(out_dir) / "trials" / f"{trial.key}.json"


def log_path(out_dir: Path, trial: TrialSpec) -> Path:
    return Path(out_dir) / "logs" / f"{trial.key}.mcap"


def read_result(out_dir: Path, trial: TrialSpec) -> dict[str, Any] | None:
    """The trial's result if a complete one for exactly these inputs exists, else None."""
    path = result_path(out_dir, trial)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if data.get("version") != RESULT_VERSION or data.get("trial") != trial.to_dict():
        return None
    return data


def execute(trial_data: dict[str, Any], out_dir: str) -> tuple[str, float]:
    """Run the trial (``TrialSpec.to_dict()``), write its result; (key, wall seconds)."""
    _single_threaded()
    trial = TrialSpec.from_dict(trial_data)
    started, started_cpu = time.perf_counter(), time.process_time()
    runner = {"frames": _frames, "path": _path, "approach": _approach}[trial.kind]
    rows, extra, timing = runner(trial, Path(out_dir))
    seconds = time.perf_counter() - started
    timing["cpu_s"] = time.process_time() - started_cpu
    result = {
        "version": RESULT_VERSION,
        "trial": trial.to_dict(),
        "rows": rows,
        "extra": extra,
        "timing": {**timing, "wall_s": seconds},  # machine-dependent: never in summary.csv
    }
    write_atomic(result_path(Path(out_dir), trial), json.dumps(result, allow_nan=False))
    return trial.key, seconds


def write_atomic(path: Path, text: str | bytes) -> None:
    """Write ``path`` through a temporary file in the same directory and ``os.replace``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as f:
        f.write(text.encode("utf-8") if isinstance(text, str) else text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _single_threaded() -> None:
    """One core per trial: the trials themselves are the parallelism."""
    import cv2

    cv2.setNumThreads(1)
    for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(name, "1")


def _row(cell: dict[str, Any], series: Series) -> dict[str, Any]:
    return {"cell": cell, "series": series.to_dict()}


def _judged_series(frames: list[Any], system: str, fps: float, blank=lambda r: False) -> Series:
    from hil.evaluation.targets import judged_errors

    t, valid, position, attitude = [], [], [], []
    for r in frames:
        if blank(r):
            continue
        ok = r.status != "lost"
        errors = judged_errors(system, r.error) if ok else (math.nan, math.nan)
        t.append(r.index / fps)
        valid.append(ok)
        position.append(float(errors[0]))
        attitude.append(float(errors[1]))
    return Series(tuple(t), tuple(valid), tuple(position), tuple(attitude))


# --- frames: one (distance, maneuver) case group of the matrix ------------------------------


def matrix_spec(params: dict[str, Any], seed: int):
    """The ``MatrixSpec`` of a frames trial (its lists keep the campaign's order, so a case's
    noise is that of ``satgrasp matrix`` with the same seed)."""
    from hil.evaluation.matrix import MatrixSpec

    fields = {f.name for f in dataclasses.fields(MatrixSpec)}
    values = {k: v for k, v in params.items() if k in fields}
    for name in ("systems", "noises", "distances_m", "maneuvers", "blank_frames", "mockups"):
        if name in values:
            values[name] = tuple(values[name])
    return MatrixSpec(**values, seed=seed)


def _no_nan(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _no_nan(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_no_nan(v) for v in value]
    return value


def frame_results_to_json(results: list[Any]) -> list[dict[str, Any]]:
    """The matrix's ``FrameResult``s as JSON (NaN as null), for ``satgrasp matrix``'s tables."""
    return [_no_nan(dataclasses.asdict(r)) for r in results]


def frame_results_from_json(data: list[dict[str, Any]]) -> list[Any]:
    from hil.evaluation.errors import MeasurementError
    from hil.evaluation.matrix import FrameResult

    def number(v: Any) -> Any:
        if isinstance(v, list):  # a vector (MeasurementError.offset_C)
            return tuple(number(x) for x in v)
        return math.nan if v is None else v

    return [
        FrameResult(
            **{k: number(v) for k, v in row.items() if k != "error"},
            error=MeasurementError(**{k: number(v) for k, v in row["error"].items()}),
        )
        for row in data
    ]


def _frames(trial: TrialSpec, out_dir: Path):
    from hil.evaluation.matrix import run_case_group

    spec = matrix_spec(trial.params, trial.seed)
    results = run_case_group(
        spec, trial.params["distance_m"], trial.params["maneuver"], spec.mockup
    )
    rows, timing = [], {}
    for system in spec.systems:
        for noise in spec.noises:
            frames = [
                r
                for r in results
                if r.system == system and r.noise == noise and r.mode == "tracking"
            ]
            series = _judged_series(frames, system, OPEN_LOOP_FPS, blank=lambda r: r.blank)
            rows.append(_row({**trial.cell, "system": system, "noise": noise}, series))
            timing[f"{system}/{noise}/processing_ms"] = [r.time_ms for r in frames]
    # every frame's full result (NEES, wrong locks, acquisition rows) for the matrix's tables;
    # machine-dependent processing times included, so it stays out of summary.csv
    return rows, {}, {**timing, "frame_results": frame_results_to_json(results)}


# --- path: one system along the open-loop approach path --------------------------------------


def _path(trial: TrialSpec, out_dir: Path):
    from hil.evaluation.approach_path import run_approach

    params = dict(trial.params)
    system = params["system"]
    results = run_approach(**params, seed=trial.seed)
    cell = {**trial.cell, "system": system}
    if "noise" not in cell:
        cell["noise"] = params.get("noise", "low")
    rows = [_row({**cell, "band": "all"}, _judged_series(results, system, OPEN_LOOP_FPS))]
    for hi, lo in itertools.pairwise(PATH_BANDS_M):
        band = [r for r in results if lo < r.distance_m <= hi]
        if band:
            series = _judged_series(band, system, OPEN_LOOP_FPS)
            rows.append(_row({**cell, "band": f"{hi:.2f}-{lo:.2f} m"}, series))
    timing = {"processing_ms": [r.time_ms for r in results]}
    return rows, {}, timing


# --- approach: one closed-loop simulated approach --------------------------------------------


def simulation_config(params: dict[str, Any]):
    from configuration.simulation import with_settings
    from hil.analysis.campaigns.spec import base_simulation, dotted

    return with_settings(base_simulation(params["config"]), dotted(params["set"]))


def _approach(trial: TrialSpec, out_dir: Path):
    from hil.analysis.campaign import summarize_log
    from hil.analysis.trial_analysis import analyse
    from hil.logs.triallog import TrialLog
    from hil.runtime.compose import run_trial

    config = simulation_config(trial.params)
    path = log_path(out_dir, trial)
    path.parent.mkdir(parents=True, exist_ok=True)
    with contextlib.suppress(FileNotFoundError):
        path.unlink()  # an interrupted run's log: this run replaces it
    run_trial(config, seed=trial.seed, log_path=path)
    analysis = analyse(TrialLog.open(path))
    rows = []
    for name, s in analysis.series.items():
        series = Series(
            tuple(map(float, s.capture_t)),
            tuple(map(bool, s.valid)),
            tuple(map(float, s.position_error_m)),
            tuple(map(float, s.attitude_error_rad)),
            tuple(map(float, s.latency_ms)),
        )
        rows.append(_row({**trial.cell, "system": name}, series))
    position = analysis.fused_position_error_m
    fused = Series(
        tuple(map(float, analysis.t)),
        tuple(bool(math.isfinite(v)) for v in position),
        tuple(map(float, position)),
        tuple(map(float, analysis.fused_attitude_error_rad)),
        (),
    )
    rows.append(_row({**trial.cell, "system": "fused"}, fused))
    summary = summarize_log(path, trial.seed, config.noise.preset)
    extra = {
        k: v
        for k, v in dataclasses.asdict(summary).items()
        if k not in ("log_path", "deadline_misses", "seed", "noise")
    }
    extra = {
        k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in extra.items()
    }
    extra["log"] = str(path.relative_to(out_dir))
    return rows, extra, {"deadline_misses": summary.deadline_misses}
