"""``satgrasp matrix`` as a campaign of one ``frames`` part: the same trials, executor and
result files as ``satgrasp campaign``; the matrix's tables are made from the frames' full
results the trials keep."""

from __future__ import annotations

import dataclasses
import tempfile
from collections.abc import Callable
from pathlib import Path

from configuration.campaign import CampaignConfig, CampaignPart
from configuration.mockup import load_mockup
from hil.analysis.campaigns.runner import run_campaign
from hil.analysis.campaigns.spec import expand
from hil.analysis.campaigns.trials import frame_results_from_json, read_result
from hil.evaluation.matrix import FrameResult, MatrixSpec

#: MatrixSpec's lists → the frames kind's axes.
_AXES = {
    "systems": "system",
    "noises": "noise",
    "distances_m": "distance_m",
    "maneuvers": "maneuver",
}


def matrix_campaign(spec: MatrixSpec) -> CampaignConfig:
    """The campaign of one frames part that runs exactly ``spec``."""
    settings = {}
    for field in dataclasses.fields(MatrixSpec):
        value = getattr(spec, field.name)
        if field.name in _AXES or field.name == "seed" or value == field.default:
            continue
        if field.default_factory is not dataclasses.MISSING and value == field.default_factory():
            continue
        settings[field.name] = list(value) if isinstance(value, tuple) else value
    axes = {axis: list(getattr(spec, name)) for name, axis in _AXES.items()}
    part = CampaignPart(
        name="matrix", kind="frames", settings=settings, axes=axes, seeds=[spec.seed]
    )
    return CampaignConfig(name="matrix", parts=[part])


def run_matrix_campaign(
    spec: MatrixSpec,
    *,
    workers: int = 1,
    out_dir: Path | None = None,
    progress: Callable[[str, float, int, int], None] | None = None,
) -> list[FrameResult]:
    """Run ``spec`` through the campaign runner (in ``out_dir``, resumable; a temporary
    directory by default) and return every frame's result in campaign order."""
    for name in spec.mockup_names:
        load_mockup(name)  # a bad name fails here, once, before any trial runs
    config = matrix_campaign(spec)
    with tempfile.TemporaryDirectory(prefix="satgrasp-matrix-") as scratch:
        folder = Path(out_dir) if out_dir is not None else Path(scratch)
        run_campaign(config, folder, workers=workers, progress=progress)
        results: list[FrameResult] = []
        for trial in expand(config):
            result = read_result(folder, trial)
            if result is None or "frame_results" not in result["timing"]:
                raise ValueError(f"{trial.key}: no frame results (an older result file?)")
            results += frame_results_from_json(result["timing"]["frame_results"])
    return results
