import dataclasses
import json
import math

import numpy as np
import pytest

from hil.logs.records import (
    TICK_SCHEMA,
    VISION_SCHEMA,
    TickRecord,
    TimingRecord,
    VisionRecord,
    from_json,
    to_json,
)
from tests.hil.logs.synthetic_log import make_trial


@pytest.fixture(scope="module")
def trial():
    return make_trial(seed=3, rate_hz=10.0)


def _through_json(record):
    return json.loads(json.dumps(to_json(record), allow_nan=False))


def test_records_round_trip_through_json_exactly(trial):
    tick = trial.ticks[80]
    back = from_json(TickRecord, _through_json(tick))
    assert back.timing == tick.timing and back.vision == tick.vision and back.track == tick.track
    assert np.array_equal(back.estimate.X_CT.matrix, tick.estimate.X_CT.matrix)
    assert np.array_equal(back.estimate.covariance, tick.estimate.covariance)
    assert np.array_equal(back.arm.q, tick.arm.q) and back.command.stop == tick.command.stop
    for result in (
        next(r for r in trial.vision if r.system == "ellipses" and r.outcome == "accepted"),
        next(r for r in trial.vision if r.outcome == "not_measured"),
    ):
        back = from_json(VisionRecord, _through_json(result))
        assert (back.outcome, back.reason, back.capture_t, back.t) == (
            result.outcome,
            result.reason,
            result.capture_t,
            result.t,
        )
        assert back.latency_ms == pytest.approx(result.latency_ms)
        assert back.measurement.to_dict() == result.measurement.to_dict()
        assert np.array_equal(back.truth_X_CT.matrix, result.truth_X_CT.matrix)


def test_to_json_writes_nan_as_null_and_names_the_path_of_a_bad_value(trial):
    tick = dataclasses.replace(
        trial.ticks[80],
        timing=TimingRecord(period_ms=math.nan, late_ms=0.0, work_ms=math.inf, deadline_miss=False),
        command=dataclasses.replace(trial.ticks[80].command, V_BE=np.array([np.nan, *[0.0] * 5])),
    )
    data = _through_json(tick)
    assert data["timing"]["period_ms"] is None and data["timing"]["work_ms"] is None
    assert data["command"]["V_BE"][0] is None
    back = from_json(TickRecord, data)
    assert back.timing.period_ms is None  # a nullable field reads back as None…
    assert math.isnan(back.timing.work_ms)  # …a non-nullable float as NaN
    assert math.isnan(back.command.V_BE[0]) and back.command.V_BE[1] == 0.0
    bad = dataclasses.replace(tick, gripper=dataclasses.replace(tick.gripper, fault={1, 2}))
    with pytest.raises(TypeError, match=r"^\$\.gripper\.fault: cannot write a set"):
        to_json(bad)
    with pytest.raises(TypeError, match="dtype complex128"):
        to_json(
            dataclasses.replace(
                tick, command=dataclasses.replace(tick.command, V_BE=np.ones(6) * 1j)
            )
        )


def test_from_json_names_the_field_that_does_not_fit(trial):
    data = _through_json(trial.ticks[80])
    del data["timing"]["work_ms"]
    with pytest.raises(ValueError, match=r"^TickRecord\.timing: missing work_ms$"):
        from_json(TickRecord, data)
    data = _through_json(trial.ticks[80])
    data["truth"]["X_CT"] = data["truth"]["X_CT"][:3]
    with pytest.raises(ValueError, match=r"TickRecord\.truth\.X_CT: a pose must be 4×4"):
        from_json(TickRecord, data)
    data = _through_json(trial.ticks[80])
    data["arm"] = [1, 2]
    with pytest.raises(ValueError, match=r"TickRecord\.arm: expected an object"):
        from_json(TickRecord, data)
    result = _through_json(trial.vision[5])
    result["measurement"]["status"] = "found"
    with pytest.raises(ValueError, match=r"VisionRecord\.measurement: "):
        from_json(VisionRecord, result)


def test_json_schema_follows_the_record_classes():
    assert TICK_SCHEMA["title"] == "satgrasp.Tick" and VISION_SCHEMA["title"] == "satgrasp.Vision"
    assert TICK_SCHEMA["required"] == [
        "t",
        "tick",
        "phase",
        "range_m",
        "estimate",
        "command",
        "timing",
        "vision",
    ]
    properties = TICK_SCHEMA["properties"]
    assert properties["range_m"]["type"] == ["number", "null"]
    assert properties["truth"]["type"] == ["object", "null"]
    assert properties["estimate"]["properties"]["covariance"]["minItems"] == 6
    assert properties["arm"]["properties"]["X_BE"]["items"]["minItems"] == 4
    assert VISION_SCHEMA["properties"]["outcome"]["enum"] == [
        "accepted",
        "rejected",
        "not_measured",
        "stale",
    ]
