"""A plain OpenCV pose pipeline per system, of the kind a user would write instead of satgrasp:
the comparator ``satgrasp bench`` times beside the estimators (issue 12). Not an estimator.

Every pipeline takes the frame, the camera (K, distortion), the target model and a prior pose
``prior_X_CT`` (the same prior the estimators get) and returns an ``OpenCVEstimate``:

* **corners**: Gaussian blur, ``cv2.goodFeaturesToTrack`` (Shi–Tomasi minimum eigenvalue [1])
  over the frame, kept in discs around the model's point features (the corners system's: panel
  corners, bolt and fastener discs) projected under the prior, ``cv2.cornerSubPix``, each
  feature labelled by the nearest detection, ``cv2.solvePnP`` (ITERATIVE: Levenberg–Marquardt
  on the reprojection error) started from the prior.
* **lines**: Gaussian blur, ``cv2.Canny`` [2], ``cv2.HoughLinesP`` (progressive probabilistic
  Hough [3]); per panel edge projected under the prior the segment whose ends lie nearest it,
  then ``cv2.fitLine`` (Huber) on the edge pixels along that segment, refitted once on those
  along the first fit; the four lines intersected into corners;
  ``cv2.solvePnPGeneric`` with IPPE (Collins & Bartoli [4]), the solution nearer the prior.
* **ellipses**: Gaussian blur, ``cv2.Canny``, ``cv2.findContours`` (Suzuki–Abe border
  following [5]), the contours along the outer ring projected under the prior,
  ``cv2.fitEllipseAMS`` (approximate mean square [6]) and the circle's two poses from the
  ellipse's cone by the standard closed form (Shiu & Ahmad [7]; Chen et al. [8]), the one whose
  normal is nearer the prior's.

Detection runs on the whole frame, as a plain pipeline does; the prior only selects and labels
what was detected (within ``gate_px`` of its projection). A distorted camera's image is remapped to its pinhole view once per frame
(``cv2.initUndistortRectifyMap`` computed once per camera) for lines and ellipses, whose
geometry (straight lines, conics) only holds there; corners are detected in the raw image and
``solvePnP`` is given the distortion. OpenCV runs on one thread when the caller says so
(``cv2.setNumThreads(1)``).

[1] J. Shi, C. Tomasi, "Good features to track", CVPR 1994.
[2] J. Canny, "A computational approach to edge detection", PAMI 8(6), 1986.
[3] J. Matas, C. Galambos, J. Kittler, "Robust detection of lines using the progressive
    probabilistic Hough transform", CVIU 78(1), 2000.
[4] T. Collins, A. Bartoli, "Infinitesimal plane-based pose estimation", IJCV 109(3), 2014.
[5] S. Suzuki, K. Abe, "Topological structural analysis of digitized binary images by border
    following", CVGIP 30(1), 1985.
[6] G. Taubin, "Estimation of planar curves, surfaces and nonplanar space curves defined by
    implicit equations", PAMI 13(11), 1991 (the approximate mean square distance).
[7] Y. C. Shiu, S. Ahmad, "3D location of circular and spherical features by monocular
    model-based vision", IEEE SMC 1989.
[8] Q. Chen, H. Wu, T. Wada, "Camera calibration with two arbitrary coplanar circles",
    ECCV 2004, section 3.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from estimators.conics import conic_from_parameters
from estimators.frame import CameraInfo, Frame
from estimators.geometry import Pose, normal_angle, rotation_error_rpy_norm, translation_error
from estimators.target import Circle3D, TargetModel

#: The systems the comparator has a pipeline for.
OPENCV_SYSTEMS = ("corners", "lines", "ellipses")
#: Gaussian blur before edges: the rendered frames carry noise of σ 13 (low) to 26 (high) grey
#: levels; σ 2.5 px with Canny 40 / 100 keeps ~94 % of the true edges and ~0.1 % of the noise
#: (measured on a 3 m reference frame). Corners are detected on a lighter blur.
EDGE_BLUR_SIGMA_PX = 2.5
CORNER_BLUR_SIGMA_PX = 1.5
CANNY_LOW, CANNY_HIGH = 40, 100
#: Search radius around a projected feature: what 2 cm (twice the 1 cm prior error) displaces
#: a point at the feature's depth, plus 4 px.
GATE_M = 0.02
GATE_MIN_PX = 4.0
#: Outer-ring contour gate, as a fraction of the ring's band (outer − inner radius) in pixels.
RING_GATE_FRACTION = 0.3
ELLIPSE_SAMPLES = 90
#: Shi–Tomasi corners kept (strongest first) per point feature searched for.
MAX_CORNERS_PER_FEATURE = 10


@dataclass(frozen=True, slots=True, eq=False)
class OpenCVEstimate:
    """What an OpenCV pipeline found: a pose ``X_CT`` (corners, lines) or the circle
    ``circle``'s centre ``center_C`` (m) and unit normal ``normal_C`` in C (ellipses);
    ``reason`` says why nothing was found (empty when something was)."""

    system: str
    reason: str = ""
    X_CT: Pose | None = None
    circle: str | None = None
    center_C: np.ndarray | None = None
    normal_C: np.ndarray | None = None

    @property
    def valid(self) -> bool:
        return not self.reason


@dataclass(frozen=True, slots=True, eq=False)
class PinholeView:
    """A camera and the maps that remap its image to the pinhole camera with the same K
    (None when it has no distortion)."""

    info: CameraInfo
    map_x: np.ndarray | None
    map_y: np.ndarray | None

    @staticmethod
    def of(info: CameraInfo) -> PinholeView:
        if not info.has_distortion:
            return PinholeView(info, None, None)
        map_x, map_y = cv2.initUndistortRectifyMap(
            info.K, info.dist, None, info.K, (info.width, info.height), cv2.CV_16SC2
        )
        return PinholeView(info, map_x, map_y)

    def undistorted(self, gray: np.ndarray) -> np.ndarray:
        """The image as the pinhole camera with the same K would have taken it."""
        if self.map_x is None:
            return gray
        return cv2.remap(gray, self.map_x, self.map_y, cv2.INTER_LINEAR)


#: A region of interest: x0, y0, x1, y1 (pixels, end exclusive).
Roi = tuple[int, int, int, int]


def region_around(points_px: np.ndarray, margin_px: float, info: CameraInfo) -> Roi | None:
    """The bounding box of ``points_px`` grown by ``margin_px``, clipped to the image; None
    when (nearly) nothing of it is in the image."""
    lo = np.floor(points_px.min(axis=0) - margin_px).astype(int)
    hi = np.ceil(points_px.max(axis=0) + margin_px).astype(int) + 1
    x0, y0 = max(lo[0], 0), max(lo[1], 0)
    x1, y1 = min(hi[0], info.width), min(hi[1], info.height)
    if x1 - x0 < 8 or y1 - y0 < 8:
        return None
    return int(x0), int(y0), int(x1), int(y1)


def gate_px(info: CameraInfo, depth_m: float) -> float:
    """The search radius (px) around a feature projected under the prior at ``depth_m``."""
    return GATE_MIN_PX + GATE_M * info.K[0, 0] / max(depth_m, 1e-3)


def to_gray(image: np.ndarray) -> np.ndarray:
    """uint8 grey image from a BGR or grey frame."""
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    if gray.dtype != np.uint8:
        gray = np.clip(gray, 0, 255).astype(np.uint8)
    return gray


def _edges(gray: np.ndarray) -> np.ndarray:
    return cv2.Canny(cv2.GaussianBlur(gray, (0, 0), EDGE_BLUR_SIGMA_PX), CANNY_LOW, CANNY_HIGH)


def _project(
    points_T: np.ndarray, X_CT: Pose, K: np.ndarray, dist: np.ndarray | None
) -> np.ndarray:
    rvec, _ = cv2.Rodrigues(X_CT.R)
    uv, _ = cv2.projectPoints(points_T.reshape(-1, 1, 3), rvec, X_CT.p.reshape(3, 1), K, dist)
    return uv.reshape(-1, 2)


def _pose(rvec: np.ndarray, tvec: np.ndarray) -> Pose:
    R, _ = cv2.Rodrigues(rvec)
    return Pose(R, np.asarray(tvec, dtype=float).reshape(3))


# --- corners ------------------------------------------------------------------------------------


def corners_pose(
    gray: np.ndarray, info: CameraInfo, target: TargetModel, prior_X_CT: Pose
) -> OpenCVEstimate:
    """The corners system's point features (panel corners, bolt and fastener discs):
    Shi–Tomasi detections near their projections under the prior, sub-pixel refined, each
    feature labelled by the nearest detection (a detection nearest to two features labels
    neither), then ``solvePnP`` ITERATIVE from the prior on the four or more labelled."""
    model_T = target.points_T()
    predicted = _project(model_T, prior_X_CT, info.K, info.dist)
    depths = prior_X_CT.apply(model_T)[:, 2]
    inside = (
        (depths > 0)
        & (predicted[:, 0] >= 0)
        & (predicted[:, 0] < info.width)
        & (predicted[:, 1] >= 0)
        & (predicted[:, 1] < info.height)
    )
    if np.count_nonzero(inside) < 4:
        return OpenCVEstimate("corners", "fewer than 4 point features in view")
    model_T, predicted = model_T[inside], predicted[inside]
    gate = gate_px(info, float(np.min(depths[inside])))
    mask = np.zeros(gray.shape, np.uint8)
    for u, v in predicted:
        cv2.circle(mask, (round(u), round(v)), round(gate), 255, -1)
    blurred = cv2.GaussianBlur(gray, (0, 0), CORNER_BLUR_SIGMA_PX)
    found = cv2.goodFeaturesToTrack(
        blurred, maxCorners=MAX_CORNERS_PER_FEATURE * len(model_T), qualityLevel=0.05,
        minDistance=3, mask=mask, blockSize=5,
    )  # fmt: skip
    if found is None or len(found) < 4:
        return OpenCVEstimate("corners", "fewer than 4 corners detected")
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)
    found = cv2.cornerSubPix(blurred, found.astype(np.float32), (3, 3), (-1, -1), criteria)
    found = found.reshape(-1, 2)
    distances = np.linalg.norm(found[None, :, :] - predicted[:, None, :], axis=2)
    nearest = distances.argmin(axis=1)
    counts = np.bincount(nearest, minlength=len(found))
    labelled = (distances[np.arange(len(model_T)), nearest] <= gate) & (counts[nearest] == 1)
    if np.count_nonzero(labelled) < 4:
        return OpenCVEstimate("corners", "fewer than 4 point features labelled")
    rvec, _ = cv2.Rodrigues(prior_X_CT.R)
    tvec = prior_X_CT.p.reshape(3, 1).copy()
    ok, rvec, tvec = cv2.solvePnP(
        model_T[labelled], found[nearest[labelled]].astype(np.float64), info.K, info.dist,
        rvec, tvec, useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE,
    )  # fmt: skip
    if not ok:
        return OpenCVEstimate("corners", "solvePnP failed")
    return OpenCVEstimate("corners", X_CT=_pose(rvec, tvec))


# --- lines --------------------------------------------------------------------------------------


def _line_through(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Homogeneous line (a, b, c), a² + b² = 1, through two pixels."""
    line = np.cross([a[0], a[1], 1.0], [b[0], b[1], 1.0])
    return line / np.linalg.norm(line[:2])


def _distances(points: np.ndarray, line: np.ndarray) -> np.ndarray:
    return np.abs(points @ line[:2] + line[2])


def lines_pose(
    gray: np.ndarray, view: PinholeView, target: TargetModel, prior_X_CT: Pose
) -> OpenCVEstimate:
    """Panel edges: Canny + HoughLinesP, per predicted edge the nearest aligned segment and
    ``fitLine`` on the edge pixels along it, the lines intersected into the four corners,
    IPPE's solution nearer the prior."""
    info = view.info
    K = info.K
    model_T = target.panel_corners_T
    predicted = _project(model_T, prior_X_CT, K, None)
    gate = gate_px(info, float(np.min(prior_X_CT.apply(model_T)[:, 2])))
    if region_around(predicted, 0.0, info) is None:
        return OpenCVEstimate("lines", "the panel is out of view")
    edges = _edges(view.undistorted(gray))
    shortest = min(np.linalg.norm(predicted[i] - predicted[i - 1]) for i in range(4))
    segments = cv2.HoughLinesP(
        edges, 1, np.pi / 180, threshold=max(8, int(0.1 * shortest)),
        minLineLength=max(8.0, 0.15 * shortest), maxLineGap=10,
    )  # fmt: skip
    if segments is None:
        return OpenCVEstimate("lines", "no line segments")
    segments = segments.reshape(-1, 4).astype(float)
    ends_a, ends_b = segments[:, :2], segments[:, 2:]
    ys, xs = np.nonzero(edges)
    pixels = np.column_stack([xs, ys]).astype(float)
    fitted = []
    for i in range(4):
        a, b = predicted[i], predicted[(i + 1) % 4]
        line = _line_through(a, b)
        length = float(np.linalg.norm(b - a))
        off_a, off_b = _distances(ends_a, line), _distances(ends_b, line)
        near = (off_a < gate) & (off_b < gate)  # both ends near: along the edge
        if not np.any(near):
            return OpenCVEstimate("lines", f"no segment along panel edge {i}")
        best = np.flatnonzero(near)[np.argmin((off_a + off_b)[near])]
        along = (pixels - a) @ ((b - a) / length)
        inside = (along > 0.1 * length) & (along < 0.9 * length)
        # Edge pixels along the segment (a short segment's direction is rough: fit, then
        # refit on the pixels along the first fit).
        estimate = _line_through(ends_a[best], ends_b[best])
        for band_px in (3.0, 1.5):
            on = inside & (_distances(pixels, estimate) < band_px)
            if np.count_nonzero(on) < 5:
                return OpenCVEstimate("lines", f"too few edge pixels along panel edge {i}")
            vx, vy, px, py = cv2.fitLine(
                pixels[on].astype(np.float32), cv2.DIST_HUBER, 0, 0.01, 0.01
            ).ravel()
            estimate = _line_through(np.array([px, py]), np.array([px + vx, py + vy]))
        fitted.append(estimate)
    corners = []
    for i in range(4):  # corner i lies on edges i − 1 and i
        point = np.cross(fitted[i - 1], fitted[i])
        if abs(point[2]) < 1e-12:
            return OpenCVEstimate("lines", "parallel panel edges")
        corners.append(point[:2] / point[2])
    count, rvecs, tvecs, _ = cv2.solvePnPGeneric(
        model_T, np.array(corners), K, None, flags=cv2.SOLVEPNP_IPPE
    )
    if count == 0:
        return OpenCVEstimate("lines", "solvePnP IPPE failed")
    poses = [_pose(r, t) for r, t in zip(rvecs, tvecs, strict=True)]
    nearest = min(poses, key=lambda X: rotation_error_rpy_norm(prior_X_CT, X))
    return OpenCVEstimate("lines", X_CT=nearest)


# --- ellipses -----------------------------------------------------------------------------------


def ellipse_conic(
    center_px: tuple[float, float], axes_px: tuple[float, float], angle_deg: float
) -> np.ndarray:
    """Symmetric 3×3 conic C (xᵀ C x = 0 for homogeneous pixels x) of an OpenCV RotatedRect
    ellipse: full axis lengths ``axes_px`` (width along the direction ``angle_deg``)."""
    return conic_from_parameters(
        center_px[0], center_px[1], axes_px[0] / 2.0, axes_px[1] / 2.0, np.radians(angle_deg)
    )


def circle_poses_from_conic(
    conic_px: np.ndarray, K: np.ndarray, radius_m: float
) -> list[tuple[np.ndarray, np.ndarray]]:
    """The circle's two poses (centre in C, m; unit normal in C pointing at the camera) whose
    image is the ellipse ``conic_px`` (pixels, pinhole camera K), by the standard closed form
    (Chen et al. 2004, section 3): with the cone Q = Kᵀ C K = V diag(λ1, λ2, λ3) Vᵀ, λ1, λ2 of
    one sign, λ3 of the other, |λ1| ≥ |λ2|,

        n = V [ S2·√((λ1 − λ2)/(λ1 − λ3)), 0, −S1·√((λ2 − λ3)/(λ1 − λ3)) ]
        c = z0 · V [ S2·(λ3/λ2)·√((λ1 − λ2)/(λ1 − λ3)), 0, −S1·(λ1/λ2)·√((λ2 − λ3)/(λ1 − λ3)) ]
        z0 = S3 · λ2 · r / √(−λ1 λ3)

    over the signs S1, S2, S3 = ±1, keeping the centre in front of the camera and the normal
    towards it: two solutions (one when the circle faces the camera squarely)."""
    Q = K.T @ conic_px @ K
    Q = Q / np.cbrt(np.linalg.det(Q)) if np.linalg.det(Q) != 0 else Q
    values, V = np.linalg.eigh(Q)
    # One eigenvalue differs in sign from the other two; make the pair positive.
    if np.sum(values > 0) == 1:
        values = -values
    odd = int(np.argmin(values))  # the negative one
    pair = [i for i in range(3) if i != odd]
    pair.sort(key=lambda i: -abs(values[i]))
    order = [*pair, odd]
    l1, l2, l3 = values[order]
    V = V[:, order]
    g = np.sqrt(max(l1 - l2, 0.0) / (l1 - l3))
    h = np.sqrt(max(l2 - l3, 0.0) / (l1 - l3))
    solutions: list[tuple[np.ndarray, np.ndarray]] = []
    for s1, s2, s3 in itertools.product((1.0, -1.0), repeat=3):
        z0 = s3 * l2 * radius_m / np.sqrt(-l1 * l3)
        center = z0 * V @ np.array([s2 * (l3 / l2) * g, 0.0, -s1 * (l1 / l2) * h])
        normal = V @ np.array([s2 * g, 0.0, -s1 * h])
        if center[2] <= 0 or normal @ center >= 0:
            continue
        if not any(np.allclose(normal, n, atol=1e-9) for _, n in solutions):
            solutions.append((center, normal / np.linalg.norm(normal)))
    return solutions


def _circle_points(circle: Circle3D, count: int) -> np.ndarray:
    u = np.cross(circle.normal_T, [1.0, 0.0, 0.0])
    if np.linalg.norm(u) < 0.1:
        u = np.cross(circle.normal_T, [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(circle.normal_T, u)
    t = np.linspace(0.0, 2.0 * np.pi, count, endpoint=False)
    return circle.center_T + circle.radius * (np.outer(np.cos(t), u) + np.outer(np.sin(t), v))


def ellipse_pose(
    gray: np.ndarray, view: PinholeView, target: TargetModel, prior_X_CT: Pose
) -> OpenCVEstimate:
    """Outer ring: Canny + contours, the contour points along the ring projected under the
    prior, ``fitEllipseAMS``, the circle's closed-form pose whose normal is nearer the prior's."""
    info = view.info
    K = info.K
    outer = target.circle("ring_outer")
    inner = target.circle("ring_inner")
    predicted = _project(_circle_points(outer, ELLIPSE_SAMPLES), prior_X_CT, K, None)
    depth = float(prior_X_CT.apply(outer.center_T)[2])
    band_px = (outer.radius - inner.radius) * K[0, 0] / depth
    gate = max(2.0, RING_GATE_FRACTION * band_px)
    if region_around(predicted, 0.0, info) is None:
        return OpenCVEstimate("ellipses", "the ring is out of view")
    edges = _edges(view.undistorted(gray))
    # Only edges within the gate of the predicted ellipse (its outline drawn, then a distance
    # transform), then their contours.
    outline = np.full(edges.shape, 255, np.uint8)
    polygon = np.round(predicted).astype(np.int32).reshape(-1, 1, 2)
    cv2.polylines(outline, [polygon], True, 0, 1)
    near = cv2.distanceTransform(outline, cv2.DIST_L2, 3) <= gate
    edges[~near] = 0
    contours, _ = cv2.findContours(edges, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    chosen = [c.reshape(-1, 2) for c in contours if len(c) >= 10]
    if not chosen:
        return OpenCVEstimate("ellipses", "no contour along the outer ring")
    points = np.concatenate(chosen).astype(np.float32)
    if len(points) < 20:
        return OpenCVEstimate("ellipses", "too few contour points along the outer ring")
    (cx, cy), axes, angle = cv2.fitEllipseAMS(points)
    if not (np.all(np.isfinite([cx, cy, *axes, angle])) and min(axes) > 0):
        return OpenCVEstimate("ellipses", "ellipse fit failed")
    solutions = circle_poses_from_conic(ellipse_conic((cx, cy), axes, angle), K, outer.radius)
    if not solutions:
        return OpenCVEstimate("ellipses", "no circle pose for the ellipse")
    prior_normal = prior_X_CT.R @ outer.normal_T
    center, normal = min(solutions, key=lambda s: normal_angle(prior_normal, s[1]))
    return OpenCVEstimate("ellipses", circle=outer.name, center_C=center, normal_C=normal)


# --- one call per system ------------------------------------------------------------------------

OpenCVPipeline = Callable[[Frame, Pose], OpenCVEstimate]


def opencv_pipeline(system: str, target: TargetModel, info: CameraInfo) -> OpenCVPipeline:
    """The OpenCV pipeline for ``system``: a function (frame, prior X_CT) → ``OpenCVEstimate``,
    with what depends on the camera only (undistortion maps) computed now."""
    if system not in OPENCV_SYSTEMS:
        raise ValueError(f"no OpenCV pipeline for {system!r}; there is one for {OPENCV_SYSTEMS}")
    view = PinholeView.of(info)

    def run(frame: Frame, prior_X_CT: Pose) -> OpenCVEstimate:
        gray = to_gray(frame.image)
        if system == "corners":
            return corners_pose(gray, info, target, prior_X_CT)
        if system == "lines":
            return lines_pose(gray, view, target, prior_X_CT)
        return ellipse_pose(gray, view, target, prior_X_CT)

    return run


@dataclass(frozen=True, slots=True)
class EstimateError:
    """Position (m) and attitude (rad) error of an estimate: for a pose, of the target's origin
    and its rotation (norm of roll/pitch/yaw, the reference study's metric); for a circle, of
    its centre and normal. NaN when there is no estimate."""

    position_m: float
    attitude_rad: float


NO_ERROR = EstimateError(float("nan"), float("nan"))


def opencv_error(estimate: OpenCVEstimate, X_CT_true: Pose, target: TargetModel) -> EstimateError:
    """Errors of an OpenCV estimate against the true pose of the target in the camera."""
    if not estimate.valid:
        return NO_ERROR
    if estimate.X_CT is not None:
        return EstimateError(
            translation_error(X_CT_true, estimate.X_CT),
            rotation_error_rpy_norm(X_CT_true, estimate.X_CT),
        )
    circle = target.circle(estimate.circle or "ring_outer")
    center_true = X_CT_true.apply(circle.center_T)
    normal_true = X_CT_true.R @ circle.normal_T
    return EstimateError(
        float(np.linalg.norm(estimate.center_C - center_true)),
        normal_angle(normal_true, estimate.normal_C),
    )
