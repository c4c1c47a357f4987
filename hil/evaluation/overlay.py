"""Draw what an estimator saw and concluded on top of the frame (for people, not for code)."""

from __future__ import annotations

import cv2
import numpy as np

from estimators.conics import circle_points
from estimators.frame import CameraInfo
from estimators.measurement import Measurement
from estimators.target import TargetModel

# BGR colours
_GREY = (150, 150, 150)
_GREEN = (60, 220, 60)
_RED = (60, 60, 255)
_CYAN = (255, 220, 0)
_YELLOW = (0, 220, 255)


def _polyline(image: np.ndarray, uv: np.ndarray, color, closed: bool) -> None:
    if len(uv) >= 2 and np.all(np.isfinite(uv)):
        pts = np.round(uv * 16).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(image, [pts], closed, color, 1, cv2.LINE_AA, shift=4)


def draw_measurement(
    image: np.ndarray,
    m: Measurement,
    camera: CameraInfo,
    target: TargetModel,
    *,
    model_color: tuple[int, int, int] = _RED,
    text_row: int = 0,
) -> np.ndarray:
    """A BGR copy of ``image`` with the measurement drawn on it.

    Grey: every ``extracted`` feature; green: ``labeled`` ones; ``model_color`` (red): the
    target model reprojected with the estimated pose (panel outline, circles); cyan: a 5-DOF
    circle; text: status, on line ``text_row`` (several systems on one frame).
    """
    canvas = image.copy()
    if canvas.ndim == 2:
        canvas = cv2.cvtColor(canvas, cv2.COLOR_GRAY2BGR)
    if canvas.dtype != np.uint8:
        canvas = np.clip(np.nan_to_num(canvas) * 255, 0, 255).astype(np.uint8)
    extracted = m.features.get("extracted")
    if extracted is not None:
        for u, v in np.asarray(extracted).reshape(-1, 2):
            cv2.circle(canvas, (round(u), round(v)), 1, _GREY, -1)
    labeled = m.features.get("labeled")
    if labeled is not None:
        for u, v in np.asarray(labeled).reshape(-1, 2):
            cv2.circle(canvas, (round(u), round(v)), 4, _GREEN, 1, cv2.LINE_AA)
    if m.X_CT is not None:
        corners_C = m.X_CT.apply(target.panel_corners_T)
        if np.all(camera.in_view(corners_C, margin_px=-50)):
            _polyline(canvas, camera.project(corners_C), model_color, closed=True)
        for circle in target.circles:
            rim_C = m.X_CT.apply(
                circle_points(circle.center_T, circle.normal_T, circle.radius, 180)
            )
            visible = camera.in_view(rim_C, margin_px=-50)
            if np.any(visible):
                _polyline(
                    canvas,
                    camera.project(rim_C[visible]),
                    model_color,
                    closed=bool(np.all(visible)),
                )
    elif m.center_C is not None and m.normal_C is not None and m.circle is not None:
        radius = target.circle(m.circle).radius
        rim_C = circle_points(m.center_C, m.normal_C, radius, 180)
        visible = camera.in_view(rim_C, margin_px=-50)
        if np.any(visible):
            _polyline(canvas, camera.project(rim_C[visible]), _CYAN, closed=bool(np.all(visible)))
    text = f"{m.system}: {m.status}"
    if m.reason:
        text += f" ({m.reason})"
    elif np.isfinite(m.residual_px):
        text += f"  rms {m.residual_px:.2f} px"
    origin = (8, 20 + 18 * text_row)
    cv2.putText(canvas, text, origin, cv2.FONT_HERSHEY_SIMPLEX, 0.5, _YELLOW, 1, cv2.LINE_AA)
    return canvas
