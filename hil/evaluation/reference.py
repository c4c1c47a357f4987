"""The reference study's published numbers (../shared/REFERENCE.md): the floor to beat.

Mean errors at low noise, as ranges over the maneuvers: translation (m) and rotation (rad;
for the ellipse system the angle between normals).
"""

from __future__ import annotations

import numpy as np

_CM = 0.01
_DEG = np.pi / 180.0

#: system → distance (m) → ((translation min, max) m, (rotation min, max) rad)
REFERENCE_LOW_NOISE: dict[str, dict[float, tuple[tuple[float, float], tuple[float, float]]]] = {
    "corners": {
        3.0: ((6.5 * _CM, 9.0 * _CM), (2.4 * _DEG, 3.6 * _DEG)),
        2.0: ((3.8 * _CM, 4.8 * _CM), (1.3 * _DEG, 1.7 * _DEG)),
        1.2: ((1.8 * _CM, 2.4 * _CM), (0.46 * _DEG, 0.60 * _DEG)),
    },
    "lines": {
        3.0: ((6.3 * _CM, 8.2 * _CM), (4.9 * _DEG, 7.1 * _DEG)),
        2.0: ((1.2 * _CM, 2.3 * _CM), (3.4 * _DEG, 4.7 * _DEG)),
        1.2: ((0.9 * _CM, 1.1 * _CM), (0.6 * _DEG, 1.9 * _DEG)),
    },
    "ellipses": {
        3.0: ((3.0 * _CM, 3.7 * _CM), (9.0 * _DEG, 14.0 * _DEG)),
        2.0: ((3.2 * _CM, 4.1 * _CM), (8.7 * _DEG, 13.9 * _DEG)),
        1.2: ((4.7 * _CM, 6.4 * _CM), (10.0 * _DEG, 13.4 * _DEG)),
    },
}


def reference_text(system: str, distance_m: float) -> str:
    """The reference's low-noise range for one system and distance, e.g. '6.5–9.0 cm / 2.4–3.6°'."""
    ranges = REFERENCE_LOW_NOISE.get(system, {}).get(distance_m)
    if ranges is None:
        return "–"
    (t0, t1), (r0, r1) = ranges
    return f"{t0 / _CM:.1f}–{t1 / _CM:.1f} cm / {r0 / _DEG:.2g}–{r1 / _DEG:.2g}°"


#: What the reference says of high noise (variance 0.1), where it gives a figure: corners'
#: rotation rose to about 5° at 3 m; lines kept track at 3.8–7.7 cm at 3 m. None: not given.
REFERENCE_HIGH_NOISE: dict[
    str, dict[float, tuple[tuple[float, float] | None, tuple[float, float] | None]]
] = {
    "corners": {3.0: (None, (5.0 * _DEG, 5.0 * _DEG))},
    "lines": {3.0: ((3.8 * _CM, 7.7 * _CM), None)},
}


def reference_ranges(
    system: str, distance_m: float, noise: str
) -> tuple[tuple[float, float] | None, tuple[float, float] | None]:
    """(translation (min, max) m, rotation (min, max) rad) the reference reports for a
    system, distance and noise level over its maneuvers; None where it gives no figure."""
    table = {"low": REFERENCE_LOW_NOISE, "high": REFERENCE_HIGH_NOISE}.get(noise, {})
    for distance, ranges in table.get(system, {}).items():
        if abs(distance - distance_m) < 1e-6:
            return ranges
    return None, None
