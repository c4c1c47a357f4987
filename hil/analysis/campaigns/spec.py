"""A campaign expanded into self-contained trials: each ``TrialSpec`` holds everything its
trial needs (kind, parameters, seed) and a key derived from them, so a finished trial's result
file is found again by the same file and seeds, and a changed setting runs anew.

Kinds and what their axes and settings name:

* ``frames`` — the open-loop test matrix (``hil.evaluation.matrix``): any ``MatrixSpec``
  field; ``system``, ``noise``, ``distance_m`` and ``maneuver`` are the singular axes of
  ``systems``, ``noises``, ``distances_m`` and ``maneuvers``. One trial is one (distance,
  maneuver, mock-up of ``mockups``, other axes, seed) case group, rendered once for all its
  systems and noise levels (``fused`` is a fourth system); its cells are (system, noise, …).
* ``path`` — the open-loop approach path (``hil.evaluation.approach_path.run_approach``): its
  keyword arguments; one trial per (system, noise, …, seed).
* ``approach`` — closed-loop simulated approaches (``hil.runtime.compose.run_trial``):
  ``config`` names the simulation config, every other key is a dotted config field
  (``noise`` stands for ``noise.preset``); one trial per (axes, seed), its cells one per
  estimator and the fused estimate, read back from the trial's log.
"""

from __future__ import annotations

import dataclasses
import hashlib
import inspect
import itertools
import json
import re
from dataclasses import dataclass
from typing import Any

from configuration.campaign import CampaignConfig, CampaignPart
from hil.evaluation.approach_path import run_approach
from hil.evaluation.matrix import MatrixSpec
from hil.evaluation.scenarios import MANEUVERS, REFERENCE_DISTANCES_M

#: Bumped when a kind's result changes meaning: older result files then run anew.
RESULT_VERSION = 1

#: frames: singular axis → the MatrixSpec field holding the values of a case group.
FRAMES_AXES = {
    "system": "systems",
    "noise": "noises",
    "distance_m": "distances_m",
    "maneuver": "maneuvers",
}
#: frames: axes whose values share one trial (one rendering serves every system and noise).
FRAMES_INNER = ("system", "noise")
#: approach: short axis names for config fields.
APPROACH_ALIASES = {"noise": "noise.preset"}


class CampaignError(ValueError):
    """A campaign that cannot run as written (the message names the part and the field)."""


@dataclass(frozen=True, slots=True)
class TrialSpec:
    """One self-contained trial: ``params`` (JSON-able, the kind's inputs), ``seed``, and
    ``cells`` — the cell keys of the rows it yields besides ``system`` (for ``frames``
    ``system`` and ``noise`` come from each row)."""

    part: str
    kind: str
    params: dict[str, Any]
    seed: int
    cell: dict[str, Any]

    @property
    def key(self) -> str:
        """``<part>/<readable>-<hash>``: the same inputs give the same key on any machine."""
        canonical = json.dumps(
            {"v": RESULT_VERSION, "kind": self.kind, "params": self.params, "seed": self.seed},
            sort_keys=True,
            separators=(",", ":"),
        )
        digest = hashlib.sha256(canonical.encode()).hexdigest()[:10]
        words = [_slug(v) for v in self.cell.values()] + [f"s{self.seed}"]
        return f"{self.part}/{'-'.join(words)}-{digest}"

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @staticmethod
    def from_dict(data: dict[str, Any]) -> TrialSpec:
        return TrialSpec(data["part"], data["kind"], data["params"], data["seed"], data["cell"])


def _slug(value: Any) -> str:
    text = ",".join(map(str, value)) if isinstance(value, list) else str(value)
    return re.sub(r"[^A-Za-z0-9.,_]+", "_", text)[:40]


def expand(config: CampaignConfig) -> list[TrialSpec]:
    """Every trial of the campaign, parts in file order, axes in file order. Raises
    ``CampaignError`` naming the part and the axis or setting it cannot use."""
    trials: list[TrialSpec] = []
    for part in config.parts:
        expander = {"frames": _frames, "path": _path, "approach": _approach}[part.kind]
        trials.extend(expander(part))
    keys = [t.key for t in trials]
    if len(set(keys)) != len(keys):
        raise CampaignError("two trials of the campaign are identical (an axis repeats a setting)")
    return trials


def _combinations(axes: dict[str, list[Any]]) -> list[dict[str, Any]]:
    names = list(axes)
    return [dict(zip(names, values, strict=True)) for values in itertools.product(*axes.values())]


def _frames(part: CampaignPart) -> list[TrialSpec]:
    fields = {f.name for f in dataclasses.fields(MatrixSpec)} - {"seed"}
    known = set(FRAMES_AXES) | fields
    for where, names in (("axes", part.axes), ("settings", part.settings)):
        for name in names:
            if name not in known or (name in FRAMES_AXES.values() and where == "axes"):
                raise CampaignError(
                    f"part {part.name!r}: {where}.{name}: not a frames setting; use "
                    f"{', '.join(sorted(set(FRAMES_AXES) | fields - set(FRAMES_AXES.values())))}"
                )
    settings = {FRAMES_AXES.get(k, k): v for k, v in part.settings.items()}
    lists = {
        "systems": part.axes.get("system", settings.pop("systems", None)),
        "noises": part.axes.get("noise", settings.pop("noises", ["none", "low", "high"])),
        "distances_m": part.axes.get(
            "distance_m", settings.pop("distances_m", list(REFERENCE_DISTANCES_M))
        ),
        "maneuvers": part.axes.get(
            "maneuver", settings.pop("maneuvers", [m.name for m in MANEUVERS])
        ),
    }
    if not lists["systems"]:
        raise CampaignError(f"part {part.name!r}: name the systems (axes.system)")
    known_maneuvers = {m.name for m in MANEUVERS}
    for maneuver in lists["maneuvers"]:
        if maneuver not in known_maneuvers:
            raise CampaignError(
                f"part {part.name!r}: unknown maneuver {maneuver!r}; known: "
                f"{', '.join(m.name for m in MANEUVERS)}"
            )
    outer = {k: v for k, v in part.axes.items() if k not in FRAMES_INNER}
    outer.setdefault("distance_m", lists["distances_m"])
    outer.setdefault("maneuver", lists["maneuvers"])
    if settings.get("mockups"):  # a trial per mock-up; the list stays: it fixes each one's noise
        outer.setdefault("mockup", list(settings["mockups"]))
    trials = []
    for combination in _combinations(outer):
        params = {**settings, **lists}
        params.update({k: v for k, v in combination.items() if k not in FRAMES_AXES})
        params["distance_m"] = float(combination["distance_m"])
        params["maneuver"] = combination["maneuver"]
        params["distances_m"] = [float(d) for d in params["distances_m"]]
        for seed in part.seed_list:
            trials.append(TrialSpec(part.name, "frames", params, seed, dict(combination)))
    return trials


def _path(part: CampaignPart) -> list[TrialSpec]:
    accepted = set(inspect.signature(run_approach).parameters) - {"seed", "path"}
    for where, names in (("axes", part.axes), ("settings", part.settings)):
        for name in names:
            if name not in accepted:
                raise CampaignError(
                    f"part {part.name!r}: {where}.{name}: not a path setting; use "
                    f"{', '.join(sorted(accepted))}"
                )
    if "system" not in part.axes and "system" not in part.settings:
        raise CampaignError(f"part {part.name!r}: name the system (axes.system)")
    if "fused" in part.axes.get("system", []):
        raise CampaignError(f"part {part.name!r}: the path kind runs single systems, not 'fused'")
    trials = []
    for combination in _combinations(part.axes):
        params = {**part.settings, **combination}
        for seed in part.seed_list:
            trials.append(TrialSpec(part.name, "path", params, seed, dict(combination)))
    return trials


def _approach(part: CampaignPart) -> list[TrialSpec]:
    from configuration.simulation import with_settings

    settings = {APPROACH_ALIASES.get(k, k): v for k, v in part.settings.items()}
    base = settings.pop("config", "sim")
    axes = {APPROACH_ALIASES.get(k, k): v for k, v in part.axes.items()}
    try:
        config = base_simulation(base)
    except ValueError as exc:
        raise CampaignError(f"part {part.name!r}: settings.config: {exc}") from None
    trials = []
    for combination in _combinations(axes):
        overrides = {**settings, **combination}
        try:  # validate now, not in the middle of the campaign
            with_settings(config, dotted(overrides))
        except ValueError as exc:
            raise CampaignError(f"part {part.name!r}: {exc}") from None
        params = {"config": base, "set": overrides}
        cell = {_short(k): v for k, v in combination.items()}
        for seed in part.seed_list:
            trials.append(TrialSpec(part.name, "approach", params, seed, cell))
    return trials


def base_simulation(base: Any):
    """The simulation config an approach part starts from: a built-in name or YAML path, or a
    whole resolved config as a mapping (``satgrasp campaign --seeds``)."""
    from configuration.simulation import SimulationConfig, load_simulation

    if isinstance(base, dict):
        try:
            return SimulationConfig.model_validate(base)
        except Exception as exc:  # pydantic's ValidationError is a ValueError
            raise ValueError(f"the config mapping does not validate: {exc}") from None
    return load_simulation(str(base))


def _short(name: str) -> str:
    for short, full in APPROACH_ALIASES.items():
        if name == full:
            return short
    return name


def dotted(overrides: dict[str, Any]) -> list[str]:
    """``{"noise.preset": "low"}`` → ``["noise.preset=low"]`` (values as YAML flow text)."""
    return [f"{k}={json.dumps(v)}" for k, v in overrides.items()]
