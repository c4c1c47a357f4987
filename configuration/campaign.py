"""A campaign file (``configs/campaigns/*.yaml``): parts of one of three kinds, each with fixed
settings, axes to sweep and seeds.

```yaml
name: smoke
parts:
  - name: matrix
    kind: frames                 # open-loop frames (the reference's test matrix)
    settings: {frames: 4}
    axes: {system: [corners, fused], noise: [low], distance_m: [2.0], maneuver: [none]}
    seeds: [0]
  - name: approach
    kind: approach               # closed-loop approaches (settings: config + dotted keys)
    settings: {config: sim, max_duration_s: 3}
    axes: {noise: [low, high]}
    seeds: {first: 1, count: 2}
```

Which settings and axes a kind takes is checked when the campaign is expanded into trials
(``hil.analysis.campaigns.spec``); here only the shape. Every model is frozen and rejects
unknown keys.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field, field_validator, model_validator

from configuration.base import Strict
from configuration.files import load_config

Scalar = str | int | float | bool | None
#: A value an axis or a setting takes: a scalar or a list of scalars (e.g. ``systems``).
Value = Scalar | list[Scalar]


class SeedRange(Strict):
    """Seeds ``first`` … ``first + count − 1``."""

    first: Annotated[int, Field(ge=0)] = 0
    count: Annotated[int, Field(ge=1, le=100_000)] = 1


class CampaignPart(Strict):
    """One kind of trial swept over ``axes`` (every combination of their values is a cell),
    ``seeds`` trials per cell (for ``frames``: a seed is a noise realisation of the case)."""

    name: Annotated[str, Field(pattern=r"^[A-Za-z0-9_-]+$")]
    kind: Literal["frames", "path", "approach"]
    #: (``approach``: ``config`` may also be a whole resolved simulation config, as a mapping)
    settings: dict[str, Value | dict[str, Any]] = Field(default_factory=dict)
    axes: dict[str, list[Value]] = Field(default_factory=dict)
    seeds: list[Annotated[int, Field(ge=0)]] | SeedRange = Field(default_factory=lambda: [0])

    @field_validator("axes")
    @classmethod
    def _axes_not_empty(cls, axes: dict[str, list[Value]]) -> dict[str, list[Value]]:
        for name, values in axes.items():
            if not values:
                raise ValueError(f"axis {name!r} has no values")
            if len({repr(v) for v in values}) != len(values):
                raise ValueError(f"axis {name!r} repeats a value")
        return axes

    @property
    def seed_list(self) -> list[int]:
        if isinstance(self.seeds, SeedRange):
            return list(range(self.seeds.first, self.seeds.first + self.seeds.count))
        return list(self.seeds)


class CampaignConfig(Strict):
    name: Annotated[str, Field(pattern=r"^[A-Za-z0-9_.-]+$")]
    description: str = ""
    parts: list[CampaignPart]

    @model_validator(mode="after")
    def _unique_parts(self) -> CampaignConfig:
        if not self.parts:
            raise ValueError("parts: name at least one part")
        names = [p.name for p in self.parts]
        if len(set(names)) != len(names):
            raise ValueError("parts: each part needs a name of its own")
        return self


def load_campaign_config(name_or_path: str | Path) -> CampaignConfig:
    """A built-in campaign (``smoke``, ``reference``) or a YAML file; ``ConfigError`` naming
    the file, the field and its line otherwise."""
    return load_config(name_or_path, CampaignConfig, "campaigns")


def plain(value: Any) -> Any:
    """An axis or setting value as it goes into a trial's key (lists stay lists)."""
    return list(value) if isinstance(value, tuple) else value
