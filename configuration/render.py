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
    #: Scale each frame, before its noise, so that the mock-up's brightest pixels come near
    #: full scale (``sim_backends.sensor.auto_exposure_gain``): a camera's auto-exposure
    #: metering the target, as a user sets an OAK's exposure region on the mock-up. Off: the
    #: rendered intensities as the light makes them, however dim.
    auto_exposure: bool = False

    @property
    def gaussian_variance(self) -> float:
        """Variance of the additive Gaussian noise on [0, 1] intensities (0 for ``sensor``)."""
        if self.variance is not None:
            return self.variance
        return {"none": 0.0, "low": 0.05, "high": 0.1, "sensor": 0.0}[self.preset]


#: Below this variance of the additive noise (σ ≈ 0.1 of full scale) a point-sampled image's
#: staircase edges show: each image row puts an edge up to half a pixel off, where a camera's
#: pixels, integrating light over their area, put it where it is. The study's noise (σ 0.22 and
#: 0.32) hides that error; a camera's own noise (``sensor``, σ ≈ 0.01) does not, and the panel
#: systems then refuse frames whose edges disagree with the model by χ²/dof 8–13.
ALIASING_HIDDEN_VARIANCE = 0.01


class RenderConfig(Strict):
    #: ``pybullet``: TinyRenderer. ``raster``: ``sim_backends.raster``, the same image in a
    #: tenth of the time, without shadows or specular light. ``auto``: raster wherever it draws
    #: the same image (configured or OBJ mock-ups under light without either), else pybullet.
    engine: Literal["auto", "pybullet", "raster"] = "auto"
    lighting: Lighting = Lighting()
    #: Anti-aliasing: each pixel the mean of supersample² samples. ``auto``: 4 (and 4
    #: ``passes``) under noise below ``ALIASING_HIDDEN_VARIANCE`` (``sensor``, ``none``), else 1
    #: (``for_noise``).
    supersample: Annotated[int, Field(ge=1, le=4)] | Literal["auto"] = 1
    #: Renders averaged per frame, their samples shifted along the diagonal by 1/passes of a
    #: sample: an edge along the pixel rows or columns (a camera square on to the panel) is
    #: placed to 1/(supersample·passes) px instead of 1/supersample, at passes × the cost.
    #: ``supersample: auto`` sets 4 where it sets 4 × 4 samples.
    passes: Annotated[int, Field(ge=1, le=4)] = 1
    near_m: PositiveM = 0.05
    far_m: PositiveM = 30.0

    def for_noise(self, noise: NoiseConfig) -> RenderConfig:
        """This config with an ``auto`` supersample resolved for frames under ``noise``."""
        if self.supersample != "auto":
            return self
        hidden = noise.preset != "sensor" and noise.gaussian_variance >= ALIASING_HIDDEN_VARIANCE
        if hidden:
            return self.model_copy(update={"supersample": 1})
        return self.model_copy(update={"supersample": 4, "passes": 4})
