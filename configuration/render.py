"""How the simulated camera renders: lighting, image noise, anti-aliasing, clip planes.

Every model is frozen and rejects unknown keys.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from configuration.base import PositiveM, Strict, Unit


class Lighting(Strict):
    """Ambient + a sun-like directional light (Lambertian)."""

    ambient: Unit = 0.45
    diffuse: Unit = 0.55
    specular: Unit = 0.0
    #: Direction from the target toward the sun, in T (normalised on use).
    sun_direction_T: tuple[float, float, float] = (-0.25, 0.35, 1.0)
    shadows: bool = False


#: Issue 13's harsh light: a low sun from the side, as on orbit or under a facility's sun lamp.
HARSH_LIGHTING = Lighting(
    ambient=0.08, diffuse=0.92, specular=0.5, sun_direction_T=(0.9, -0.3, 0.35), shadows=True
)


class NoiseConfig(Strict):
    """Image noise. ``preset`` gives the reference study's additive Gaussian levels
    (variance 0 / 0.05 / 0.1 on [0,1] intensities, clipped); ``sensor`` adds shot and read
    noise from a photon-transfer model instead."""

    preset: Literal["none", "low", "high", "sensor"] = "none"
    variance: Annotated[float, Field(ge=0.0, le=1.0)] | None = None
    full_well_e: Annotated[float, Field(gt=0.0)] = 10000.0
    read_noise_e: Annotated[float, Field(ge=0.0)] = 8.0
    motion_blur: bool = False
    exposure_s: Annotated[float, Field(ge=0.0, le=1.0)] = 0.008

    @property
    def gaussian_variance(self) -> float:
        """Variance of the additive Gaussian noise on [0, 1] intensities (0 for ``sensor``)."""
        if self.variance is not None:
            return self.variance
        return {"none": 0.0, "low": 0.05, "high": 0.1, "sensor": 0.0}[self.preset]


class RenderConfig(Strict):
    #: ``pybullet``: TinyRenderer. ``raster``: ``sim_backends.raster``, the same image in a
    #: tenth of the time, without shadows or specular light. ``auto``: raster wherever it draws
    #: the same image (configured or OBJ mock-ups under light without either), else pybullet.
    engine: Literal["auto", "pybullet", "raster"] = "auto"
    lighting: Lighting = Lighting()
    supersample: Annotated[int, Field(ge=1, le=4)] = 1
    near_m: PositiveM = 0.05
    far_m: PositiveM = 30.0
