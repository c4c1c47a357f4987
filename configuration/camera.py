"""Camera profiles (``configs/cameras/``): resolution and intrinsics, from a FOV or explicit.

Every model is frozen and rejects unknown keys.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import Field, model_validator

from configuration.base import PositiveM, Strict
from configuration.files import load_config
from estimators.frame import CameraInfo
from estimators.geometry import check_distortion, intrinsics_from_fov


class CameraConfig(Strict):
    """A camera profile: resolution and either a horizontal FOV or explicit intrinsics."""

    name: str
    width: Annotated[int, Field(ge=16, le=8192)]
    height: Annotated[int, Field(ge=16, le=8192)]
    hfov_deg: Annotated[float, Field(gt=1.0, lt=179.0)] | None = None
    fx: PositiveM | None = None
    fy: PositiveM | None = None
    cx: float | None = None
    cy: float | None = None
    distortion: list[float] = Field(default_factory=list)
    channels: Literal[1, 3] = 1
    fps: Annotated[float, Field(gt=0.0)] = 30.0

    @model_validator(mode="after")
    def _intrinsics_given_once(self) -> CameraConfig:
        explicit = [self.fx, self.fy, self.cx, self.cy]
        if self.hfov_deg is None and any(v is None for v in explicit):
            raise ValueError("give either hfov_deg or all of fx, fy, cx, cy")
        if self.hfov_deg is not None and any(v is not None for v in explicit):
            raise ValueError("give either hfov_deg or fx/fy/cx/cy, not both")
        check_distortion(np.array(self.distortion))
        return self

    def camera_info(self) -> CameraInfo:
        if self.hfov_deg is not None:
            K = intrinsics_from_fov(self.width, self.height, self.hfov_deg)
        else:
            K = np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])
        return CameraInfo(
            width=self.width,
            height=self.height,
            K=K,
            dist=np.array(self.distortion, dtype=float),
            model=self.name,
            channels=self.channels,
        )


def load_camera(name_or_path: str | Path) -> CameraConfig:
    return load_config(name_or_path, CameraConfig, "cameras")
