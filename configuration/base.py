"""Shared building blocks of the configuration models: strict frozen models and the units
of their fields (metres, unit reflectances, positions).

Every model is frozen and rejects unknown keys.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field

PositiveM = Annotated[float, Field(gt=0.0)]


Unit = Annotated[float, Field(ge=0.0, le=1.0)]


RGB = tuple[Unit, Unit, Unit]


XY = tuple[float, float]


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


XYZ = tuple[float, float, float]


Vec3 = tuple[float, float, float]


Vec6 = tuple[float, float, float, float, float, float]


Positive = Annotated[float, Field(gt=0.0)]  # a positive quantity in the unit its name gives
