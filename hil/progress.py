"""Live, one-line progress of a running trial or campaign (formatting only; printing is the
CLI's)."""

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


def campaign_line(key: str, seconds: float, done: int, total: int, elapsed_s: float) -> str:
    """'[12/67] matrix/2.0-none-s0-… 41 s; 8 min elapsed, ETA 37 min' — one line per finished
    trial, for a campaign whose output is a file rather than a terminal's progress bar. The ETA
    assumes the remaining trials take what the finished ones took on average (trials that
    were already done when the run began are not counted)."""
    eta = "" if done == 0 else f", ETA {_minutes(elapsed_s / done * (total - done))}"
    return f"[{done}/{total}] {key} {seconds:.0f} s; {_minutes(elapsed_s)} elapsed{eta}"


def _minutes(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 90 else f"{seconds / 60:.0f} min"
