import json

import pytest

from hil.logs.logschema import (
    COMPRESSED_IMAGE_SCHEMA,
    EVENT_SCHEMA,
    HEADER_SCHEMA,
    foxglove_schema,
    validate,
)
from hil.logs.records import TICK_SCHEMA, VISION_SCHEMA, to_json
from tests.hil.logs.synthetic_log import make_trial


@pytest.fixture(scope="module")
def trial():
    return make_trial(seed=4)


@pytest.fixture(scope="module")
def ticks(trial):
    return [json.loads(json.dumps(to_json(t))) for t in trial.ticks]


@pytest.fixture(scope="module")
def vision(trial):
    return [json.loads(json.dumps(to_json(r))) for r in trial.vision]


def test_validate_accepts_every_synthetic_record_and_extra_keys(ticks, vision):
    for tick in ticks:
        assert validate(tick, TICK_SCHEMA) == [], tick["tick"]
    for result in vision:
        assert validate(result, VISION_SCHEMA) == [], (result["system"], result["seq"])
    assert validate({**ticks[50], "debug": {"anything": [1, "x"]}}, TICK_SCHEMA) == []
    idle = ticks[0]
    assert idle["estimate"]["X_CT"] is None and idle["range_m"] is None  # nullable fields
    assert idle["timing"]["period_ms"] is None
    lost = next(r for r in vision if r["outcome"] == "not_measured")
    assert lost["measurement"]["X_CT"] is None
    with_nan = {**ticks[60], "command": {**ticks[60]["command"], "V_BE": [0.1, None] + [0.0] * 4}}
    assert validate(with_nan, TICK_SCHEMA) == []  # a NaN in a vector is written as null


def test_validate_names_the_path_of_each_problem(ticks, vision):
    tick = json.loads(json.dumps(ticks[60]))
    tick["phase"] = 3
    tick["estimate"]["X_CT"] = tick["estimate"]["X_CT"][:3]
    tick["command"]["V_BE"][2] = "fast"
    tick["vision"]["frames_dropped"] = 1.5
    del tick["timing"]
    problems = validate(tick, TICK_SCHEMA)
    expected = [
        "$.phase: expected string, got integer",
        "$: missing 'timing'",
        "$.estimate.X_CT: 3 items, expected at least 4",
        "$.command.V_BE[2]: expected number or null, got string",
        "$.vision.frames_dropped: expected integer, got number",
    ]
    for text in expected:
        assert text in problems, problems
    assert len(validate(tick, TICK_SCHEMA, limit=2)) == 2
    result = json.loads(json.dumps(vision[10]))
    result["outcome"] = "late"
    result["measurement"]["status"] = "found"
    problems = validate(result, VISION_SCHEMA)
    assert "$.outcome: 'late' is not one of accepted, rejected, not_measured, stale" in problems
    assert "$.measurement.status: 'found' is not one of acquired, tracking, lost" in problems


def _foxglove_parses(schema: dict, where: str = "") -> None:
    """The rules of Foxglove's JSON-Schema parser (mcap-support parseJsonSchema): objects
    list their properties; each field has one type among boolean/string/number/integer/
    object/array; arrays hold primitives or objects; base64 only on plain string fields."""
    assert schema.get("type") == "object", where
    assert isinstance(schema.get("properties"), dict), where
    for name, field in schema["properties"].items():
        kind = field.get("type")
        path = f"{where}.{name}"
        assert kind in ("boolean", "string", "number", "integer", "object", "array"), path
        if kind == "string":
            assert field.get("contentEncoding") in (None, "base64"), path
        elif kind == "object":
            _foxglove_parses(field, path)
        elif kind == "array":
            item = field["items"]
            assert item.get("type") in ("boolean", "string", "number", "integer", "object"), path
            if item["type"] == "object":
                _foxglove_parses(item, path)
            assert "contentEncoding" not in item, path


@pytest.mark.parametrize(
    "schema",
    [TICK_SCHEMA, VISION_SCHEMA, EVENT_SCHEMA, HEADER_SCHEMA, COMPRESSED_IMAGE_SCHEMA],
    ids=["tick", "vision", "event", "header", "image"],
)
def test_foxglove_schema_is_what_foxglove_can_parse(schema):
    before = json.dumps(schema)
    derived = foxglove_schema(schema)
    _foxglove_parses(derived)
    json.dumps(derived)
    assert json.dumps(schema) == before  # the original is left as it was


def test_foxglove_schema_keeps_plottable_fields_and_drops_matrices():
    derived = foxglove_schema(TICK_SCHEMA)["properties"]
    assert derived["range_m"]["type"] == "number" and derived["t"]["type"] == "number"
    # nullable number items (NaN written as null) become plain number items
    assert derived["command"]["properties"]["V_BE"]["items"] == {"type": "number"}
    assert derived["timing"]["properties"]["period_ms"]["type"] == "number"
    assert derived["vision"]["properties"]["frames_dropped"]["type"] == "integer"
    estimate = derived["estimate"]["properties"]
    assert estimate["V_MT"]["type"] == "array" and estimate["age_s"]["type"] == "number"
    assert "X_CT" not in estimate and "covariance" not in estimate
    assert derived["truth"]["type"] == "object" and "X_CT" not in derived["truth"]["properties"]
    assert derived["truth"]["required"] == []
    assert "X_CT" in TICK_SCHEMA["properties"]["truth"]["properties"]  # full schema untouched
    vision = foxglove_schema(VISION_SCHEMA)["properties"]
    assert vision["outcome"]["enum"] == ["accepted", "rejected", "not_measured", "stale"]
    measurement = vision["measurement"]["properties"]
    assert measurement["residual_px"]["type"] == "number" and "X_CT" not in measurement
    assert "truth_X_CT" not in vision and vision["processing_ms"]["type"] == "number"
    image = foxglove_schema(COMPRESSED_IMAGE_SCHEMA)["properties"]
    assert image["data"] == {"type": "string", "contentEncoding": "base64"}
