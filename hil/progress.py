"""Live, one-line progress of a running trial (formatting only; printing is the CLI's)."""

from __future__ import annotations

import math

import numpy as np

from estimators.geometry import Pose, rotation_error_geodesic, translation_error


def tick_line(record: dict) -> str:
    """'t 12.4 s  approach  range 0.85 m  fused error 1.2 mm 0.05°  accepted corners,lines'."""
    parts = [f"t {record.get('t', math.nan):5.1f} s", f"{record.get('phase', '?'):8s}"]
    range_m = record.get("range_m")
    parts.append(f"range {range_m:.3f} m" if range_m is not None else "range   –  ")
    estimate = record.get("estimate") or {}
    truth = record.get("truth") or {}
    if estimate.get("X_CT") is not None and truth.get("X_CT") is not None:
        X_est = Pose.from_matrix(np.array(estimate["X_CT"]), orthonormalize=True)
        X_true = Pose.from_matrix(np.array(truth["X_CT"]), orthonormalize=True)
        parts.append(
            f"fused error {1000 * translation_error(X_true, X_est):5.1f} mm "
            f"{math.degrees(rotation_error_geodesic(X_true, X_est)):4.2f}°"
        )
    else:
        parts.append(f"estimate {estimate.get('health', '?')}")
    if estimate.get("accepted"):
        parts.append("accepted " + ",".join(estimate["accepted"]))
    return "  ".join(parts)
