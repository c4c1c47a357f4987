import json

import pytest

from hil.logs.logschema import (
    COMPRESSED_IMAGE_SCHEMA,
    EVENT_SCHEMA,
    HEADER_SCHEMA,
    TICK_SCHEMA,
    foxglove_schema,
    validate,
)
from hil.logs.triallog import to_jsonable
from tests.hil.logs.synthetic_log import make_trial


@pytest.fixture(scope="module")
def ticks():
    trial = make_trial(seed=4)
    return [json.loads(json.dumps(to_jsonable(t))) for t in trial.ticks]


def test_validate_accepts_every_synthetic_tick_and_extra_keys(ticks):
    for tick in ticks:
        assert validate(tick, TICK_SCHEMA) == [], tick["tick"]
    assert validate({**ticks[50], "debug": {"anything": [1, "x"]}}, TICK_SCHEMA) == []
    idle = ticks[0]
    assert idle["estimate"] is None and idle["range_m"] is None  # nullable fields


def test_validate_names_the_path_of_each_problem(ticks):
    tick = json.loads(json.dumps(ticks[60]))
    tick["phase"] = "hover"
    tick["measurements"][1]["status"] = "found"
    tick["estimate"]["X_CT"] = tick["estimate"]["X_CT"][:3]
    tick["command"]["V_BE"][2] = None
    tick["tick"] = -1
    del tick["arm"]
    problems = validate(tick, TICK_SCHEMA)
    assert any(p.startswith("$.phase: 'hover' is not one of idle, acquire") for p in problems)
    expected = [
        "$.tick: -1 is less than 0",
        "$: missing 'arm'",
        "$.measurements[1].status: 'found' is not one of acquired, tracking, lost",
        "$.estimate.X_CT: 3 items, expected at least 4",
        "$.command.V_BE[2]: expected number, got null",
    ]
    for text in expected:
        assert text in problems, problems
    assert len(validate(tick, TICK_SCHEMA, limit=2)) == 2


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
    "schema", [TICK_SCHEMA, EVENT_SCHEMA, HEADER_SCHEMA, COMPRESSED_IMAGE_SCHEMA]
)
def test_foxglove_schema_is_what_foxglove_can_parse(schema):
    derived = foxglove_schema(schema)
    _foxglove_parses(derived)
    json.dumps(derived)
    assert schema == json.loads(json.dumps(schema))  # the original is left as it was


def test_foxglove_schema_keeps_plottable_fields_and_drops_matrices():
    derived = foxglove_schema(TICK_SCHEMA)["properties"]
    assert derived["range_m"]["type"] == "number" and derived["t"]["type"] == "number"
    assert derived["command"]["properties"]["V_BE"]["items"]["type"] == "number"
    measurement = derived["measurements"]["items"]["properties"]
    assert measurement["status"]["enum"] == ["acquired", "tracking", "lost"]
    assert measurement["residual_px"]["type"] == "number"
    assert "X_CT" not in measurement and "covariance" not in measurement
    assert derived["truth"]["type"] == "object" and derived["truth"]["properties"] == {}
    assert derived["truth"]["required"] == []
    assert "X_CT" in TICK_SCHEMA["properties"]["truth"]["properties"]  # full schema untouched
    image = foxglove_schema(COMPRESSED_IMAGE_SCHEMA)["properties"]
    assert image["data"] == {"type": "string", "contentEncoding": "base64"}
