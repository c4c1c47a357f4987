"""JSON Schemas of the trial-log channels, a validator for them, and their Foxglove form.

The tick and vision schemas are derived from their record classes (``hil.logs.records``); the
header, event, measurement and image schemas are written here.

The schemas are standard JSON Schema (draft 2020-12 keywords: ``type`` — possibly a list, for
nullable values —, ``enum``, ``properties``, ``required``, ``additionalProperties``, ``items``,
``minItems``, ``maxItems``). They are tolerant: unknown keys are allowed everywhere, so the
sequencer can add fields without breaking old readers.

Foxglove's JSON-Schema parser (``parseJsonSchema`` in its ``mcap-support`` package) accepts
only one type per field and no arrays of arrays, and throws on anything else, which would
hide the whole channel. ``foxglove_schema`` derives the subset it can parse (a nullable field
keeps its non-null type; matrices — 4×4 poses, covariances — are left out of ``properties``
and stay visible in the Raw Messages panel). The log embeds that subset per channel and the
full schemas in a metadata record (see docs/trial_logs.md).
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import Any

MEASUREMENT_STATUSES = ("acquired", "tracking", "lost")

NUMBER = {"type": "number"}
NUMBER_OR_NULL = {"type": ["number", "null"]}
STRING = {"type": "string"}
STRING_OR_NULL = {"type": ["string", "null"]}
BOOLEAN = {"type": "boolean"}


def _vector(n: int, *, nullable: bool = False) -> dict:
    return {
        "type": ["array", "null"] if nullable else "array",
        "items": NUMBER,
        "minItems": n,
        "maxItems": n,
    }


def _matrix(rows: int, cols: int, *, nullable: bool = True, description: str = "") -> dict:
    schema = {
        "type": ["array", "null"] if nullable else "array",
        "items": _vector(cols),
        "minItems": rows,
        "maxItems": rows,
    }
    if description:
        schema["description"] = description
    return schema


def _pose(description: str, *, nullable: bool = True) -> dict:
    return _matrix(4, 4, nullable=nullable, description=f"{description} (4×4, row-major, m)")


def _object(properties: dict, required: tuple[str, ...] = (), **extra: Any) -> dict:
    schema: dict[str, Any] = {"type": "object", "properties": properties}
    if required:
        schema["required"] = list(required)
    schema.update(extra)
    return schema


MEASUREMENT_SCHEMA = _object(
    {
        "system": STRING,
        "status": {"type": "string", "enum": list(MEASUREMENT_STATUSES)},
        "reason": STRING,
        "stamp": NUMBER,
        "seq": {"type": "integer"},
        "X_CT": _pose("target in camera"),
        "covariance": _matrix(6, 6, description="6×6 over [δθ, δp] of X_CT"),
        "circle": STRING_OR_NULL,
        "center_C": _vector(3, nullable=True),
        "normal_C": _vector(3, nullable=True),
        "covariance_5dof": _matrix(5, 5, description="5×5 over [δc, α, β]"),
        "residual_px": NUMBER_OR_NULL,
        "ambiguous": BOOLEAN,
        "time_ms": NUMBER,
    },
    ("system", "status"),
    description="estimators.measurement.Measurement.to_dict()",
)

EVENT_SCHEMA = _object(
    {
        "t": {"type": "number", "description": "seconds since the trial started"},
        "kind": {"type": "string", "description": "phase | fault | abort | info | log | …"},
        "message": STRING,
        "data": {"type": "object", "properties": {}},
    },
    ("t", "kind", "message", "data"),
    title="satgrasp.Event",
)

HEADER_SCHEMA = _object(
    {
        "format": STRING,
        "format_version": {"type": "integer"},
        "satgrasp_version": STRING,
        "python": STRING,
        "versions": {
            "type": "object",
            "properties": {},
            "additionalProperties": STRING_OR_NULL,
            "description": "installed version of each key package (null: not installed)",
        },
        "host": STRING,
        "platform": STRING,
        "start_time_utc": {"type": "string", "description": "ISO 8601"},
        "start_time_unix_ns": {"type": "integer"},
        "seed": {"type": ["integer", "null"]},
        "config": {
            "type": "object",
            "properties": {},
            "description": "the full resolved configuration",
        },
        "notes": STRING,
    },
    ("format", "format_version", "satgrasp_version", "start_time_unix_ns", "seed", "config"),
    title="satgrasp.TrialHeader",
)

# foxglove.CompressedImage, written from the field list of Foxglove's published schema so the
# Image panel shows the frames.
COMPRESSED_IMAGE_SCHEMA = _object(
    {
        "timestamp": _object(
            {
                "sec": {"type": "integer", "minimum": 0},
                "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999},
            },
            ("sec", "nsec"),
            title="time",
        ),
        "frame_id": STRING,
        "data": {"type": "string", "contentEncoding": "base64"},
        "format": STRING,
    },
    ("timestamp", "frame_id", "data", "format"),
    title="foxglove.CompressedImage",
    description="A compressed image",
)

_JSON_TYPES = {
    "null": lambda v: v is None,
    "boolean": lambda v: isinstance(v, bool),
    "integer": lambda v: isinstance(v, int) and not isinstance(v, bool),
    "number": lambda v: isinstance(v, int | float) and not isinstance(v, bool),
    "string": lambda v: isinstance(v, str),
    "array": lambda v: isinstance(v, list),
    "object": lambda v: isinstance(v, dict),
}


def validate(value: Any, schema: dict, *, limit: int = 10) -> list[str]:
    """Problems of a JSON value (``json.loads`` output) against ``schema``, each naming its
    path (``$.measurement.status: 'lots' is not one of …``); empty when it conforms.

    Implements the keywords the schemas here use (see the module docstring); stops after
    ``limit`` problems. Schemas are compiled to checking functions once and cached.
    """
    problems: list[str] = []
    _compiled(schema)(value, "$", problems, limit)
    return problems


# A value's path is built only for a problem: (parent path, ".key" or "[i]"), from "$".
_Path = str | tuple
_Checker = Callable[[Any, _Path, list, int], None]
_CACHE: dict[int, tuple[dict, _Checker]] = {}
#: The Python types ``json.loads`` gives for each JSON type (exact types: a fast first test).
_PY_TYPES = {
    "null": (type(None),),
    "boolean": (bool,),
    "integer": (int,),
    "number": (int, float),
    "string": (str,),
    "array": (list,),
    "object": (dict,),
}


def _where(path: _Path) -> str:
    parts = []
    while isinstance(path, tuple):
        path, part = path
        parts.append(part)
    return path + "".join(reversed(parts))


def _compiled(schema: dict) -> _Checker:
    entry = _CACHE.get(id(schema))
    if entry is None or entry[0] is not schema:
        entry = (schema, _compile(schema))
        _CACHE[id(schema)] = entry
    return entry[1]


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _numbers_only(items: Any) -> frozenset[type] | None:
    """The exact types of a numbers-only ``items`` schema (vectors, matrix rows; null where
    NaN was written), else None."""
    if items == NUMBER:
        return frozenset((float, int))
    if items == NUMBER_OR_NULL:
        return frozenset((float, int, type(None)))
    return None


def _compile(schema: dict) -> _Checker:
    """A function (value, path, problems, limit) that appends the problems of ``value``."""
    kinds = schema.get("type")
    kinds = [kinds] if isinstance(kinds, str) else kinds
    type_tests = [_JSON_TYPES[k] for k in kinds] if kinds else []
    exact_types = frozenset(t for k in kinds or () for t in _PY_TYPES[k])
    enum = schema.get("enum")
    minimum, maximum = schema.get("minimum"), schema.get("maximum")
    bounded = minimum is not None or maximum is not None
    properties = {k: _compile(v) for k, v in schema.get("properties", {}).items()}
    required = schema.get("required", ())
    extra = schema.get("additionalProperties", True)
    extra_check = _compile(extra) if isinstance(extra, dict) else None
    min_items, max_items = schema.get("minItems"), schema.get("maxItems")
    items = schema.get("items")
    item_check = _compile(items) if isinstance(items, dict) else None
    # numbers-only items, or rows of numbers of a fixed length (matrices): one pass instead of
    # a call per element
    numeric = _numbers_only(items)
    row_numeric = _numbers_only(items.get("items")) if isinstance(items, dict) else None
    row_length = items.get("minItems") if isinstance(items, dict) else None
    if row_numeric is None or row_length is None or items.get("maxItems") != row_length:
        row_numeric = None

    def check(value: Any, path: _Path, problems: list[str], limit: int) -> None:
        if len(problems) >= limit:
            return
        # exact types first; the general tests accept subclasses (numpy floats)
        if (
            type_tests
            and type(value) not in exact_types
            and not any(test(value) for test in type_tests)
        ):
            problems.append(
                f"{_where(path)}: expected {' or '.join(kinds)}, got {_describe(value)}"
            )
            return
        if enum is not None and value not in enum:
            problems.append(f"{_where(path)}: {value!r} is not one of {', '.join(map(str, enum))}")
            return
        if isinstance(value, dict):
            for key in required:
                if key not in value:
                    problems.append(f"{_where(path)}: missing {key!r}")
            for key, item in value.items():
                sub = properties.get(key)
                if sub is not None:
                    sub(item, (path, f".{key}"), problems, limit)
                elif extra is False:
                    problems.append(f"{_where(path)}: unexpected key {key!r}")
                elif extra_check is not None:
                    extra_check(item, (path, f".{key}"), problems, limit)
        elif isinstance(value, list):
            if min_items is not None and len(value) < min_items:
                problems.append(
                    f"{_where(path)}: {len(value)} items, expected at least {min_items}"
                )
            if max_items is not None and len(value) > max_items:
                problems.append(f"{_where(path)}: {len(value)} items, expected at most {max_items}")
            if numeric is not None and all(t in numeric for t in map(type, value)):
                return
            if row_numeric is not None and all(
                type(row) is list
                and len(row) == row_length
                and all(t in row_numeric for t in map(type, row))
                for row in value
            ):
                return
            if item_check is not None:
                for i, item in enumerate(value):
                    item_check(item, (path, f"[{i}]"), problems, limit)
                    if len(problems) >= limit:
                        return
        elif bounded and _is_number(value):
            if minimum is not None and value < minimum:
                problems.append(f"{_where(path)}: {value} is less than {minimum}")
            if maximum is not None and value > maximum:
                problems.append(f"{_where(path)}: {value} is greater than {maximum}")

    return check


def _describe(value: Any) -> str:
    if value is None:
        return "null"
    for name in ("boolean", "integer", "number", "string", "array", "object"):
        if _JSON_TYPES[name](value):
            return name
    return type(value).__name__


def foxglove_schema(schema: dict) -> dict:
    """The part of ``schema`` that Foxglove's JSON-Schema parser accepts (see module doc)."""
    out = copy.deepcopy(schema)
    _foxglove_node(out)
    return out


def _single_type(node: dict) -> str | None:
    kinds = node.get("type")
    if isinstance(kinds, list):
        non_null = [k for k in kinds if k != "null"]
        kinds = non_null[0] if non_null else None
        node["type"] = kinds
    return kinds


def _foxglove_node(node: dict) -> bool:
    """Rewrite ``node`` in place; False when Foxglove cannot represent it at all."""
    kind = _single_type(node)
    if kind == "object":
        node.setdefault("properties", {})
        node.pop("additionalProperties", None)
        for key in list(node["properties"]):
            if not _foxglove_node(node["properties"][key]):
                del node["properties"][key]
        if "required" in node:
            node["required"] = [k for k in node["required"] if k in node["properties"]]
        return True
    if kind == "array":
        items = node.get("items")
        if not isinstance(items, dict):
            return False
        item_kind = _single_type(items)
        if item_kind == "object":
            return _foxglove_node(items)
        return item_kind in ("boolean", "string", "number", "integer") and not (
            item_kind == "string" and "contentEncoding" in items
        )
    return kind in ("boolean", "string", "number", "integer")
