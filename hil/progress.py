"""Live, one-line progress of a running trial (formatting only; printing is the CLI's)."""

from __future__ import annotations

import math

from estimators.geometry import rotation_error_geodesic, translation_error
from hil.logs.records import TickRecord


def tick_line(record: TickRecord) -> str:
    """'t  12.4 s  approach  range 0.850 m  fused error   1.2 mm 0.05°  age 0.14 s  frames
    120 (2 dropped)  period 8.0 ms'. The fused error needs simulator truth; without it the
    estimate's health is shown instead."""
    parts = [f"t {record.t:5.1f} s", f"{record.phase:8s}"]
    parts.append(f"range {record.range_m:.3f} m" if record.range_m is not None else "range   –  ")
    estimate = record.estimate
    if estimate.X_CT is not None and record.truth is not None:
        X_true = record.truth.X_CT
        parts.append(
            f"fused error {1000 * translation_error(X_true, estimate.X_CT):5.1f} mm "
            f"{math.degrees(rotation_error_geodesic(X_true, estimate.X_CT)):4.2f}°"
        )
    else:
        parts.append(f"estimate {estimate.health}")
    if estimate.age_s is not None:
        parts.append(f"age {estimate.age_s:.2f} s")
    vision = record.vision
    parts.append(f"frames {vision.frames_received} ({vision.frames_dropped} dropped)")
    if record.timing.period_ms is not None:
        parts.append(f"period {record.timing.period_ms:.1f} ms")
    if record.timing.deadline_miss:
        parts.append("DEADLINE MISS")
    return "  ".join(parts)
