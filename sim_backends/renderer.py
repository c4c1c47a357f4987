"""Render the mock-up through a camera model with exact intrinsics: pybullet's TinyRenderer, or
``sim_backends.raster``, which draws the same image ten times faster (``make_renderer`` picks).

Rendered pixels agree with ``estimators.geometry.project`` (tests measure ≤ 0.3 px; typically
< 0.1 px). How:

* Projection matrix from K. TinyRenderer samples integer viewport coordinates and flips rows;
  the matrix below (measured in ../shared/LIBRARY-FACTS.md) absorbs that, so any K — fx ≠ fy,
  off-centre principal point — renders in OpenCV's pixel convention (centres at integers).
* Supersampling by s: render at s× with K_s = [s·fx, s·cx + (s−1)/2; …] and average s×s blocks
  (``cv2.INTER_AREA``), whose centres then fall on the 1× pixel grid. This is the anti-aliasing.
* Lens distortion: render an ideal pinhole image large enough to cover the distorted field, then
  ``cv2.remap`` every output pixel from its undistorted position.
* Background (nothing hit) is space black.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from configuration.render import Lighting, RenderConfig
from estimators.frame import CameraInfo
from estimators.geometry import Pose, undistort_pixels
from sim_backends.bullet import pybullet
from sim_backends.raster import compile_kernel, rasterize
from sim_backends.scene import MockupScene


@dataclass(frozen=True, slots=True, eq=False)
class Rendering:
    """A noise-free rendered image and its ground truth.

    ``image``: float32 in [0, 1], HxW (mono camera) or HxWx3 (BGR, OpenCV's channel order).
    ``depth_m``: float32 HxW distance along the optical axis (inf where nothing was hit).
    """

    image: np.ndarray
    depth_m: np.ndarray
    X_WC: Pose
    X_CT: Pose


def pybullet_projection(
    K: np.ndarray, width: int, height: int, near: float, far: float
) -> list[float]:
    """pybullet (OpenGL) projection matrix, column-major, reproducing OpenCV intrinsics K."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    M = np.zeros((4, 4))
    M[0, 0] = 2.0 * fx / width
    M[0, 1] = -2.0 * K[0, 1] / width
    M[0, 2] = 1.0 - 2.0 * cx / width
    M[1, 1] = 2.0 * fy / height
    M[1, 2] = 2.0 * (cy + 1.0) / height - 1.0
    M[2, 2] = -(far + near) / (far - near)
    M[2, 3] = -2.0 * far * near / (far - near)
    M[3, 2] = -1.0
    return M.T.reshape(-1).tolist()


def pybullet_view(X_WC: Pose) -> list[float]:
    """pybullet view matrix (column-major) for an OpenCV optical frame C at ``X_WC``.

    OpenGL's camera looks down −z with y up: X_GC = diag(1, −1, −1), so V = X_GW = X_GC · X_CW.
    """
    V = np.diag([1.0, -1.0, -1.0, 1.0]) @ X_WC.inverse().matrix
    return V.T.reshape(-1).tolist()


@dataclass(frozen=True, slots=True, eq=False)
class _RenderPlan:
    """How one camera is rendered: the pybullet image size and K, and the steps after it."""

    supersample: int
    width: int  # pinhole image, before supersampling
    height: int
    K_pinhole: np.ndarray
    map_x: np.ndarray | None  # remap from the pinhole image to the distorted output
    map_y: np.ndarray | None
    passes: int = 1

    @property
    def render_size(self) -> tuple[int, int]:
        return self.width * self.supersample, self.height * self.supersample

    @property
    def K_render(self) -> np.ndarray:
        s = self.supersample
        K = self.K_pinhole.copy()
        K[0, :] *= s
        K[1, :] *= s
        K[0, 2] += (s - 1) / 2.0
        K[1, 2] += (s - 1) / 2.0
        return K

    @property
    def K_passes(self) -> list[np.ndarray]:
        """``K_render`` of each pass: the samples shifted along the diagonal by fractions of a
        sample, centred on no shift. A regular grid of s × s samples puts an edge that runs
        along the pixel rows or columns only to 1/s px, the same in every row (a camera
        square on to a panel); n passes put it to 1/(s·n) px."""
        Ks = []
        for k in range(self.passes):
            K = self.K_render
            shift = (k - (self.passes - 1) / 2.0) / self.passes
            K[0, 2] += shift
            K[1, 2] += shift
            Ks.append(K)
        return Ks


def plan_render(info: CameraInfo, supersample: int | str, passes: int = 1) -> _RenderPlan:
    """Choose the pinhole render covering ``info``'s (possibly distorted) field of view."""
    if not isinstance(supersample, int):
        raise ValueError(
            f"render.supersample {supersample!r}: resolve it for the noise first "
            "(RenderConfig.for_noise)"
        )
    if not info.has_distortion:
        return _RenderPlan(supersample, info.width, info.height, info.K.copy(), None, None, passes)
    W, H = info.width, info.height
    # Undistorted positions of every output pixel (done once per camera).
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    xy = undistort_pixels(np.column_stack([u.ravel(), v.ravel()]), info.K, info.dist)
    fx, fy, skew = info.K[0, 0], info.K[1, 1], info.K[0, 1]
    margin = 2.0
    x_min, y_min = xy.min(axis=0)
    x_max, y_max = xy.max(axis=0)
    cx = -fx * x_min - skew * y_min + margin
    cy = -fy * y_min + margin
    width = math.ceil(fx * (x_max - x_min) + abs(skew) * (y_max - y_min) + 2 * margin) + 1
    height = math.ceil(fy * (y_max - y_min) + 2 * margin) + 1
    K_pinhole = np.array([[fx, skew, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    map_x = (fx * xy[:, 0] + skew * xy[:, 1] + cx).reshape(H, W).astype(np.float32)
    map_y = (fy * xy[:, 1] + cy).reshape(H, W).astype(np.float32)
    return _RenderPlan(supersample, width, height, K_pinhole, map_x, map_y, passes)


class PybulletRenderer:
    """Renders a ``MockupScene`` as seen by a camera with intrinsics ``info`` (TinyRenderer)."""

    def __init__(self, scene: MockupScene, info: CameraInfo, config: RenderConfig | None = None):
        self.scene = scene
        self.info = info
        self.config = config or RenderConfig()
        self._plan = plan_render(info, self.config.supersample, self.config.passes)
        w, h = self._plan.render_size
        self._projections = [
            pybullet_projection(K, w, h, self.config.near_m, self.config.far_m)
            for K in self._plan.K_passes
        ]

    def render(self, X_WC: Pose, *, lighting: Lighting | None = None) -> Rendering:
        """Noise-free image of the scene from camera pose ``X_WC``."""
        lighting = lighting or self.config.lighting
        w, h = self._plan.render_size
        sun_W = self.scene.X_WT.R @ np.asarray(lighting.sun_direction_T, dtype=float)
        sun_W /= np.linalg.norm(sun_W)
        near, far = self.config.near_m, self.config.far_m
        view, light = pybullet_view(X_WC), sun_W.tolist()

        def draw(projection: list[float]) -> tuple[np.ndarray, np.ndarray]:
            _, _, rgba, depth_buffer, _ = pybullet.getCameraImage(
                w,
                h,
                viewMatrix=view,
                projectionMatrix=projection,
                renderer=pybullet.ER_TINY_RENDERER,
                flags=pybullet.ER_NO_SEGMENTATION_MASK,
                lightDirection=light,
                lightColor=[1.0, 1.0, 1.0],
                lightAmbientCoeff=lighting.ambient,
                lightDiffuseCoeff=lighting.diffuse,
                lightSpecularCoeff=lighting.specular,
                shadow=int(lighting.shadows),
                physicsClientId=self.scene.client,
            )
            rgb = np.asarray(rgba, dtype=np.uint8).reshape(h, w, 4)[:, :, :3]
            depth_buffer = np.asarray(depth_buffer, dtype=np.float32).reshape(h, w)
            depth = (far * near / (far - (far - near) * depth_buffer)).astype(np.float32)
            depth[depth_buffer >= 1.0 - 1e-7] = np.inf  # nothing hit
            return rgb, depth

        rgb, depth = _merge_passes([draw(p) for p in self._projections])
        return _develop(self._plan, self.info, rgb, depth, X_WC, self.scene.X_WT)


class RasterRenderer:
    """Renders a ``MockupScene`` with ``sim_backends.raster``: TinyRenderer's image for a tenth
    of its time (no shadows, no specular light)."""

    def __init__(self, scene: MockupScene, info: CameraInfo, config: RenderConfig | None = None):
        if scene.mesh is None:
            raise ValueError(
                "render.engine: raster draws configured and OBJ mock-ups, not URDF models; "
                "use engine pybullet"
            )
        self.scene = scene
        self.info = info
        self.config = config or RenderConfig()
        self._check(self.config.lighting)
        self._plan = plan_render(info, self.config.supersample, self.config.passes)
        self._K_passes = self._plan.K_passes
        compile_kernel()  # now, not at the first frame (a cold numba cache takes seconds)

    @staticmethod
    def draws(lighting: Lighting) -> bool:
        """Whether this renderer draws ``lighting`` as TinyRenderer would (no shadows, no
        specular light)."""
        return not lighting.shadows and lighting.specular == 0.0

    @staticmethod
    def _check(lighting: Lighting) -> None:
        if not RasterRenderer.draws(lighting):
            raise ValueError(
                "render.engine: raster draws no shadows or specular light "
                f"(lighting.shadows={lighting.shadows}, lighting.specular={lighting.specular}); "
                "use engine pybullet or auto"
            )

    def render(self, X_WC: Pose, *, lighting: Lighting | None = None) -> Rendering:
        """Noise-free image of the scene from camera pose ``X_WC``."""
        lighting = lighting or self.config.lighting
        self._check(lighting)
        mesh = self.scene.mesh
        assert mesh is not None
        X_CT = X_WC.inverse() @ self.scene.X_WT
        sun_T = np.asarray(lighting.sun_direction_T, dtype=float)
        w, h = self._plan.render_size
        vertices_C = mesh.vertices_T @ X_CT.R.T + X_CT.p
        normals_C = mesh.normals_T @ X_CT.R.T
        sun_C = X_CT.R @ (sun_T / np.linalg.norm(sun_T))

        def draw(K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            rgb = np.zeros((h, w, 3), dtype=np.uint8)
            depth = np.full((h, w), np.inf, dtype=np.float32)
            rasterize(
                vertices_C,
                normals_C,
                mesh.triangles,
                mesh.colors_8bit,
                K,
                self.config.near_m,
                sun_C,
                lighting.ambient,
                lighting.diffuse,
                rgb,
                depth,
            )
            depth[depth > self.config.far_m] = np.inf  # beyond the far plane, as pybullet clips
            return rgb, depth

        rgb, depth = _merge_passes([draw(K) for K in self._K_passes])
        return _develop(self._plan, self.info, rgb, depth, X_WC, self.scene.X_WT)


Renderer = PybulletRenderer | RasterRenderer


def make_renderer(
    scene: MockupScene, info: CameraInfo, config: RenderConfig | None = None
) -> Renderer:
    """The renderer ``config.engine`` names; ``auto`` takes the raster one wherever it draws
    the same image (a configured or OBJ mock-up, no shadows, no specular light)."""
    config = config or RenderConfig()
    engine = config.engine
    if engine == "auto":
        drawable = scene.mesh is not None and RasterRenderer.draws(config.lighting)
        engine = "raster" if drawable else "pybullet"
    if engine == "raster":
        return RasterRenderer(scene, info, config)
    return PybulletRenderer(scene, info, config)


def _merge_passes(
    passes: list[tuple[np.ndarray, np.ndarray]],
) -> tuple[np.ndarray, np.ndarray]:
    """One render from its passes' 8-bit RGB and depth: the mean colour, each pass black where
    it hit nothing, and the nearest depth (inf only where no pass hit anything)."""
    if len(passes) == 1:
        return passes[0]
    total = np.zeros(passes[0][0].shape, dtype=np.float32)
    nearest = np.full(passes[0][1].shape, np.inf, dtype=np.float32)
    for rgb, depth in passes:
        hit = (depth < np.inf).view(np.uint8)
        cv2.accumulate(rgb, total, mask=hit)
        np.minimum(nearest, depth, out=nearest)
    total *= 1.0 / len(passes)
    return total, nearest


def _develop(
    plan: _RenderPlan,
    info: CameraInfo,
    rgb: np.ndarray,
    depth: np.ndarray,
    X_WC: Pose,
    X_WT: Pose,
) -> Rendering:
    """From a renderer's RGB (0–255, 8-bit or the mean of passes) and metric depth (inf where
    nothing was hit) to the camera's image: its channels, anti-aliased by averaging
    supersamples, distorted as its lens does."""
    background = np.isinf(depth)
    if info.channels == 1:
        image = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
    else:
        image = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR).astype(np.float32)
    image *= 1.0 / 255.0
    image[background] = 0.0
    if plan.supersample > 1:
        size = (plan.width, plan.height)
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        depth = cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST)
    if plan.map_x is not None:
        # Outside the pinhole render: black, and nothing hit.
        image = cv2.remap(image, plan.map_x, plan.map_y, cv2.INTER_LINEAR, borderValue=0.0)
        depth = cv2.remap(
            depth, plan.map_x, plan.map_y, cv2.INTER_NEAREST, borderValue=float("inf")
        )
    np.clip(image, 0.0, 1.0, out=image)
    X_CT = X_WC.inverse() @ X_WT
    return Rendering(image=image, depth_m=depth, X_WC=X_WC, X_CT=X_CT)
