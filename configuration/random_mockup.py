"""Random mock-ups and lights: seeded draws of everything a user's mock-up may differ in, for
testing the estimators on mock-ups they were never tuned on.

``random_mockup(seed)`` draws the face (size, colour), the marman ring (size, width, height,
colour brighter or darker than the face), the centre panel (size, thickness, polarity, on or
off the ring's axis; at least 0.2 m: a smaller panel alone cannot hold the corner and line
systems' 3 m targets, ../shared/LIMITS.md), fastener layouts (holes or bolts on the ring, fasteners on the panel,
bolts on the face, markers inside the ring; each darker or brighter than its surface), a
thruster or none. Contrasts stay within what a camera can see (at least 0.12 on [0, 1] between
neighbouring parts, rarely more than 0.5). The four-fold symmetry of the square panel is broken
by whatever the draw holds — a thruster, an irregular layout, a marker, a panel off the axis —
and in about one draw in eight by nothing at all (``has_symmetry_breaker`` says which).

``random_lighting(seed)`` draws an ambient + sun light: from soft and frontal to a low sun
from the side with specular highlights and cast shadows.

Names: ``random:SEED`` (``load_mockup`` and the CLI accept it); ``random:A-B`` or a comma list
for several (``mockup_names``). The draws are pure functions of the seed.
"""

from __future__ import annotations

import math

import numpy as np

from configuration.mockup import MockupConfig
from configuration.render import HARSH_LIGHTING, Lighting

PREFIX = "random:"
#: Smallest grey-level difference between neighbouring parts a draw allows.
MIN_CONTRAST = 0.12
_LUMA = np.array([0.299, 0.587, 0.114])


def is_random_name(name: str) -> bool:
    return str(name).startswith(PREFIX)


def seed_of(name: str) -> int:
    """The seed of a ``random:SEED`` name (ValueError naming the text otherwise)."""
    text = str(name)[len(PREFIX) :]
    try:
        return int(text)
    except ValueError:
        raise ValueError(f"a random mock-up is named random:SEED; got {name!r}") from None


def mockup_names(spec: str) -> list[str]:
    """Mock-up names from a spec: ``random:0-19`` (twenty random mock-ups), or a comma list
    of names and paths (each may itself be a ``random:A-B`` range)."""
    names: list[str] = []
    for part in (p.strip() for p in str(spec).split(",")):
        if not part:
            continue
        if is_random_name(part) and "-" in part[len(PREFIX) :]:
            first, last = part[len(PREFIX) :].split("-", 1)
            try:
                a, b = int(first), int(last)
            except ValueError:
                raise ValueError(
                    f"a range of random mock-ups is random:A-B; got {part!r}"
                ) from None
            if b < a:
                raise ValueError(f"empty range of random mock-ups: {part!r}")
            names.extend(f"{PREFIX}{s}" for s in range(a, b + 1))
        else:
            names.append(part)
    if not names:
        raise ValueError(f"no mock-up named in {spec!r}")
    return names


def _color(rng: np.random.Generator, luma: float) -> tuple[float, float, float]:
    """A colour of the given grey level (Rec. 601 luma) with a random, moderate tint."""
    for _ in range(20):
        tint = rng.uniform(-0.25, 0.25, 3)
        rgb = luma + tint - float(_LUMA @ tint)
        if np.all((rgb >= 0.0) & (rgb <= 1.0)):
            return tuple(float(round(c, 4)) for c in rgb)  # type: ignore[return-value]
    return (float(luma),) * 3  # type: ignore[return-value]


def _contrasting(rng: np.random.Generator, base: float, low: float, high: float) -> float:
    """A grey level at least ``low`` (at most ``high``) above or below ``base``, within what
    a sensor shows (0.04–0.95)."""
    for _ in range(20):
        level = base + float(rng.choice([-1.0, 1.0])) * float(rng.uniform(low, high))
        if 0.04 <= level <= 0.95:
            return level
    return float(np.clip(base + (low if base < 0.5 else -low), 0.04, 0.95))


def _spread(rng, count: int, free, size: float, limit: int = 400) -> list[tuple[float, float]]:
    """Up to ``count`` positions drawn by ``free()`` that keep 2.5 sizes apart."""
    placed: list[tuple[float, float]] = []
    for _ in range(limit):
        if len(placed) == count:
            break
        x, y = free()
        if all(math.hypot(x - a, y - b) > 2.5 * size for a, b in placed):
            placed.append((round(float(x), 4), round(float(y), 4)))
    return placed


def _draw(seed: int) -> dict:
    rng = np.random.default_rng([seed, 13])
    symmetric = rng.uniform() < 0.125  # nothing breaks the panel's four-fold symmetry
    width, height = (float(round(v, 3)) for v in rng.uniform(1.2, 2.0, 2))
    face_luma = float(rng.uniform(0.2, 0.6))
    half = min(width, height) / 2
    outer_r = float(rng.uniform(0.26, min(0.42, half - 0.18)))
    radial = float(rng.uniform(0.03, min(0.08, 0.25 * outer_r)))
    protrusion = float(rng.uniform(0.02, 0.09))
    inner_r = outer_r - radial
    ring_luma = _contrasting(rng, face_luma, 0.2, 0.45)
    side = float(max(0.2, rng.uniform(0.6, 0.85) * inner_r * math.sqrt(2.0) * 0.95))
    panel_luma = _contrasting(rng, face_luma, 0.15, 0.4)
    room = inner_r * 0.97 - side / math.sqrt(2.0)  # how far the panel may leave the axis
    center = (0.0, 0.0)
    if not symmetric and rng.uniform() < 0.25 and room > 0.02:
        angle, offset = rng.uniform(0, 2 * math.pi), rng.uniform(0.01, min(room, 0.05))
        center = (round(offset * math.cos(angle), 4), round(offset * math.sin(angle), 4))
    config: dict = {
        "name": f"random-{seed}",
        "bus_face": {
            "width": width,
            "height": height,
            "depth": float(round(rng.uniform(0.3, 0.6), 3)),
            "color": _color(rng, face_luma),
        },
        "marman_ring": {
            "outer_diameter": round(2 * outer_r, 4),
            "radial_width": round(radial, 4),
            "protrusion": round(protrusion, 4),
            "color": _color(rng, ring_luma),
        },
        "centre_panel": {
            "side": round(side, 4),
            "thickness": round(float(rng.uniform(0.002, min(0.015, 0.5 * protrusion))), 4),
            "color": _color(rng, panel_luma),
            "center": center,
        },
        "fasteners": [],
        "thruster": None,
    }
    thruster_r = 0.0
    if not symmetric and rng.uniform() < 0.5:
        exit_r = float(rng.uniform(0.04, 0.08))
        reach = exit_r + 0.02

        def on_face():
            return rng.uniform(-width / 2 + reach, width / 2 - reach), rng.uniform(
                -height / 2 + reach, height / 2 - reach
            )

        for _ in range(200):
            x, y = on_face()
            if math.hypot(x, y) - exit_r > outer_r + 0.03:
                config["thruster"] = {
                    "center": (round(float(x), 4), round(float(y), 4)),
                    "exit_diameter": round(2 * exit_r, 4),
                    "base_diameter": round(float(rng.uniform(0.5, 0.9)) * 2 * exit_r, 4),
                    "length": round(float(rng.uniform(0.06, 0.14)), 4),
                    "lip_width": round(float(rng.uniform(0.004, 0.012)), 4),
                    "color": _color(rng, _contrasting(rng, face_luma, 0.15, 0.4)),
                    "interior_color": _color(rng, float(rng.uniform(0.03, 0.1))),
                }
                thruster_r = exit_r
                break
    fasteners = config["fasteners"]
    if rng.uniform() < 0.8:  # holes or bolts on the ring's face
        count = int(rng.choice([4, 8, 12])) if symmetric else int(rng.choice([4, 5, 6, 8, 12]))
        diameter = float(rng.uniform(0.012, min(0.03, 0.6 * radial)))
        fasteners.append(
            {
                "name": "ring_hole",
                "surface": "ring",
                "diameter": round(diameter, 4),
                "height": round(float(rng.uniform(0.0003, 0.002)), 4),
                "color": _color(rng, _contrasting(rng, ring_luma, 0.12, 0.5)),
                "circle_pattern": {
                    "radius": round(inner_r + radial / 2, 4),
                    "count": count,
                    "phase_deg": round(float(rng.uniform(0, 360 / count)), 2),
                },
            }
        )
    if rng.uniform() < 0.6:  # fasteners near the panel's corners
        diameter = float(rng.uniform(0.012, min(0.025, 0.12 * side)))
        inset = side / 2 - float(rng.uniform(1.5, 3.0)) * diameter
        corners = [(inset, inset), (-inset, inset), (-inset, -inset), (inset, -inset)]
        if not symmetric and rng.uniform() < 0.5:
            corners.pop(int(rng.integers(4)))  # an irregular layout
        fasteners.append(
            {
                "name": "panel_fastener",
                "surface": "panel",
                "diameter": round(diameter, 4),
                "height": round(float(rng.uniform(0.0005, 0.002)), 4),
                "color": _color(rng, _contrasting(rng, panel_luma, 0.2, 0.5)),
                "positions": [
                    (round(center[0] + x, 4), round(center[1] + y, 4)) for x, y in corners
                ],
            }
        )
    if rng.uniform() < 0.7:  # bolts on the face, outside the ring
        diameter = float(rng.uniform(0.02, 0.05))
        r = diameter / 2
        if symmetric:
            s = float(rng.uniform(outer_r + 0.06, half - 0.06))
            positions = [(s, s), (-s, s), (-s, -s), (s, -s)]
        else:

            def outside_ring():
                while True:
                    x = rng.uniform(-width / 2 + 2 * r, width / 2 - 2 * r)
                    y = rng.uniform(-height / 2 + 2 * r, height / 2 - 2 * r)
                    clear = math.hypot(x, y) - r > outer_r + 0.03
                    if clear and thruster_r > 0:
                        tx, ty = config["thruster"]["center"]
                        clear = math.hypot(x - tx, y - ty) > thruster_r + r + 0.03
                    if clear:
                        return x, y

            positions = _spread(rng, int(rng.integers(2, 7)), outside_ring, diameter)
        fasteners.append(
            {
                "name": "bus_bolt",
                "surface": "bus",
                "diameter": round(diameter, 4),
                "height": round(float(rng.uniform(0.001, 0.004)), 4),
                "color": _color(rng, _contrasting(rng, face_luma, 0.2, 0.5)),
                "positions": [(round(float(x), 4), round(float(y), 4)) for x, y in positions],
            }
        )
    if not symmetric and rng.uniform() < 0.35:  # markers on the face inside the ring
        diameter = float(rng.uniform(0.015, 0.04))
        r = diameter / 2

        def in_bore():
            while True:
                angle = rng.uniform(0, 2 * math.pi)
                rho = rng.uniform(0.0, inner_r - r - 0.01)
                x, y = rho * math.cos(angle), rho * math.sin(angle)
                if max(abs(x - center[0]), abs(y - center[1])) > side / 2 + r + 0.01:
                    return x, y

        if inner_r - side / math.sqrt(2.0) > diameter + 0.02:
            fasteners.append(
                {
                    "name": "marker",
                    "surface": "bus",
                    "diameter": round(diameter, 4),
                    "height": 0.0003,
                    "color": _color(rng, _contrasting(rng, face_luma, 0.2, 0.5)),
                    "positions": _spread(rng, int(rng.integers(1, 3)), in_bore, diameter),
                }
            )
    count = sum(
        len(f["positions"]) if "positions" in f else f["circle_pattern"]["count"] for f in fasteners
    )
    if count < 8:  # the schema asks for 8 point features: a ring of bolts makes them up
        fasteners = [f for f in fasteners if f["name"] != "ring_hole"]
        fasteners.append(
            {
                "name": "ring_hole",
                "surface": "ring",
                "diameter": round(float(rng.uniform(0.012, min(0.03, 0.6 * radial))), 4),
                "height": 0.001,
                "color": _color(rng, _contrasting(rng, ring_luma, 0.15, 0.5)),
                "circle_pattern": {
                    "radius": round(inner_r + radial / 2, 4),
                    "count": 8,
                    "phase_deg": round(float(rng.uniform(0, 45)), 2),
                },
            }
        )
        config["fasteners"] = fasteners
    return config


def random_mockup(seed: int) -> MockupConfig:
    """The random mock-up of ``seed`` (see the module docstring); a draw the schema refuses
    (rare: parts crowding each other) is drawn again from a derived seed."""
    last = None
    for attempt in range(20):
        config = _draw(seed if attempt == 0 else seed * 7919 + attempt)
        config["name"] = f"random-{seed}"
        try:
            return MockupConfig.model_validate(config)
        except ValueError as exc:
            last = exc
    raise ValueError(f"random mock-up {seed}: no valid draw ({last})")


def has_symmetry_breaker(mockup: MockupConfig) -> bool:
    """Whether anything of the mock-up tells the panel's quarter turns apart."""
    from estimators.acquisition import quarter_turns

    target = mockup.target_model()
    turn = quarter_turns(target)[1]
    moved = turn.apply(target.points_T())
    points = target.points_T()
    for p, feature in zip(moved, target.point_features, strict=True):
        match = np.linalg.norm(points - p, axis=1) < 1e-3
        if not any(
            m and f.kind == feature.kind and f.brighter == feature.brighter
            for m, f in zip(match, target.point_features, strict=True)
        ):
            return True
    for circle in target.circles:
        centre = turn.apply(circle.center_T[None])[0]
        if not any(np.linalg.norm(c.center_T - centre) < 1e-3 for c in target.circles):
            return True
    return False


def random_lighting(seed: int) -> Lighting:
    """A random ambient + sun light (see the module docstring)."""
    rng = np.random.default_rng([seed, 29])
    ambient = float(rng.uniform(0.08, 0.5))
    elevation = float(rng.uniform(math.radians(15), math.radians(80)))
    azimuth = float(rng.uniform(0, 2 * math.pi))
    sun = (
        math.cos(elevation) * math.cos(azimuth),
        math.cos(elevation) * math.sin(azimuth),
        math.sin(elevation),
    )
    return Lighting(
        ambient=round(ambient, 3),
        diffuse=round(float(min(1.0, rng.uniform(0.5, 1.0))), 3),
        specular=round(float(rng.uniform(0.0, 0.5)), 3),
        sun_direction_T=tuple(round(c, 4) for c in sun),  # type: ignore[arg-type]
        shadows=bool(rng.uniform() < 0.5),
    )


LIGHT_NAMES = ("default", "harsh", "random")


def named_lighting(name: str, seed: int = 0) -> Lighting:
    """A light by name: ``default`` (soft, frontal), ``harsh`` (``HARSH_LIGHTING``) or
    ``random`` (``random_lighting(seed)``)."""
    if name == "default":
        return Lighting()
    if name == "harsh":
        return HARSH_LIGHTING
    if name == "random":
        return random_lighting(seed)
    raise ValueError(f"light must be one of {', '.join(LIGHT_NAMES)}; got {name!r}")
