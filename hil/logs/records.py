"""The typed records of a trial log, defined once: the loop builds them, the log writer writes
them, the analysis reads them back, and their JSON Schemas are derived from the same classes.

A record is a frozen dataclass whose fields hold rich values — ``Pose``, numpy vectors and
matrices, ``Measurement`` — so the analysis computes with them directly. ``to_json`` turns one
into plain JSON data (poses as 4×4 nested lists, NaN and ±inf as null); ``from_json`` is its
inverse; ``json_schema`` gives the JSON Schema (the subset ``hil.logs.logschema`` validates and
turns into Foxglove's form). Time fields named ``t`` or ending ``_t`` are seconds since the
trial started; ``*_ms`` are milliseconds.

Two streams: one ``TickRecord`` per control tick (what the control loop knew and did), and one
``VisionRecord`` per estimator result (a frame's measurement: when the frame was captured,
arrived, was processed and fused, what fusion made of it, and the truth at the capture instant
in simulation — so a measurement is judged against the world it saw, not the world 150 ms later).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import types
import typing
from dataclasses import dataclass, field
from typing import Any, Literal, Union

import numpy as np

from estimators.geometry import Pose
from estimators.measurement import Measurement
from hil.logs.logschema import MEASUREMENT_SCHEMA

FORMAT_VERSION = 2


def _shape(*dims: int, doc: str = "") -> dict[str, Any]:
    """Field metadata: the shape of a numpy field (and its description)."""
    return {"shape": dims, "doc": doc}


def _doc(text: str) -> dict[str, Any]:
    return {"doc": text}


# --- tick ------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, eq=False)
class EstimateRecord:
    """The fused estimate the control loop acted on at this tick (one answer of the filter: its
    newest state predicted to the tick's time)."""

    health: str
    X_CT: Pose | None = field(default=None, metadata=_doc("fused target in camera"))
    X_MT: Pose | None = field(default=None, metadata=_doc("fused target in track carriage"))
    V_MT: np.ndarray | None = field(
        default=None, metadata=_shape(6, doc="target twist [ω, v] in M (rad/s, m/s)")
    )
    covariance: np.ndarray | None = field(
        default=None, metadata=_shape(6, 6, doc="pose covariance over [δθ, δp] in M")
    )
    age_s: float | None = field(
        default=None, metadata=_doc("since the capture of the newest accepted measurement")
    )
    updated_t: float | None = field(
        default=None, metadata=_doc("capture time of the filter's newest update")
    )


@dataclass(frozen=True, slots=True, eq=False)
class CommandRecord:
    """What was sent: the flange twist (or a stop and why), the track velocity, the gripper."""

    V_BE: np.ndarray = field(metadata=_shape(6, doc="flange twist [v (m/s), ω (rad/s)] in B"))
    stop: bool
    reason: str = ""
    track_velocity: float = 0.0
    gripper: str | None = None


@dataclass(frozen=True, slots=True, eq=False)
class ArmRecord:
    q: np.ndarray = field(metadata=_shape(6, doc="joint angles (rad)"))
    X_BE: Pose = field(metadata=_doc("flange in base"))
    V_BE: np.ndarray = field(metadata=_shape(6, doc="flange twist [v, ω] in B"))
    protective_stop: bool = False
    emergency_stop: bool = False
    fault: str | None = None
    wrench_B: np.ndarray | None = field(default=None, metadata=_shape(6, doc="TCP wrench in B"))


@dataclass(frozen=True, slots=True)
class TrackRecord:
    position: float
    velocity: float
    moving: bool = False
    fault: str | None = None


@dataclass(frozen=True, slots=True)
class GripperRecord:
    position: float
    object_detected: bool
    activated: bool = True
    moving: bool = False
    fault: str | None = None


@dataclass(frozen=True, slots=True, eq=False)
class TruthRecord:
    """Simulator ground truth at the tick (absent on real hardware)."""

    X_CT: Pose = field(metadata=_doc("true target in camera"))
    X_WT: Pose | None = field(default=None, metadata=_doc("true target in world"))
    X_WC: Pose | None = field(default=None, metadata=_doc("true camera in world"))


@dataclass(frozen=True, slots=True)
class TimingRecord:
    """Timing of the tick. ``period_ms``: since the previous tick started; ``late_ms``: how late
    it started after its deadline; ``work_ms``: its own work, from reading the devices to writing
    the log; ``deadline_miss``: it started half a period late or its work overran the period.
    Under ``--clock wall`` all of it is wall-clock time. Under ``--clock sim`` the period is
    simulated (never late) and ``work_ms`` is the tick's CPU time: the simulation shares the
    machine with other runs, and the work is what must fit the real period; there the misses are
    counted but only lateness in simulated time trips the supervisor's deadline rule.
    ``cpu_ms``: the control thread's CPU time over the same work (None in logs from before it
    was kept). A long tick whose CPU time is its work ran the whole time: slow code, or a core
    taken from the thread without its knowing (interrupts the kernel charges to it, a virtual
    machine's CPU paused by its host). One with little CPU time waited: for a lock, I/O, the
    interpreter's lock or a core."""

    period_ms: float | None
    late_ms: float
    work_ms: float
    deadline_miss: bool
    cpu_ms: float | None = None


@dataclass(frozen=True, slots=True)
class VisionCounters:
    """The vision pipeline's running totals at this tick. ``frames_received``: frames the
    pipeline got from the camera; ``frames_processed``: frames at least one estimator took;
    ``frames_dropped``: frames superseded before any estimator was free (stale);
    ``results_stale``: results discarded because their frame was too old when they came;
    ``newest_frame_t``: capture time of the newest frame received."""

    frames_received: int = 0
    frames_processed: int = 0
    frames_dropped: int = 0
    results_stale: int = 0
    newest_frame_t: float | None = None


@dataclass(frozen=True, slots=True, eq=False)
class TickRecord:
    """One control tick."""

    t: float
    tick: int
    phase: str
    range_m: float | None = field(
        metadata=_doc("camera to ring face along the optical axis, from the estimate")
    )
    estimate: EstimateRecord
    command: CommandRecord
    timing: TimingRecord
    vision: VisionCounters
    arm: ArmRecord | None = None
    track: TrackRecord | None = None
    gripper: GripperRecord | None = None
    truth: TruthRecord | None = None


# --- vision ----------------------------------------------------------------------------------

VisionOutcome = Literal["accepted", "rejected", "not_measured", "stale"]


@dataclass(frozen=True, slots=True, eq=False)
class VisionRecord:
    """One estimator's result for one frame, and what fusion made of it.

    ``capture_t`` (mid-exposure), ``arrival_t`` (the pipeline got the frame), ``started_t`` /
    ``finished_t`` (processing), ``t`` (handed to fusion, or discarded). ``outcome``: accepted,
    rejected (``reason`` says why: gate, ambiguity, …), not_measured (the estimator lost the
    target; the measurement's own reason) or stale (the frame was too old when the result came).
    ``fused_at``: the stamp fusion applied it at (the capture time, or the arrival time when
    the pipeline is configured to fuse at arrival). ``truth_X_CT``: the true target in the
    camera at the capture instant (simulation only).
    """

    t: float
    system: str
    seq: int
    capture_t: float
    arrival_t: float | None
    started_t: float
    finished_t: float
    outcome: VisionOutcome
    measurement: Measurement
    reason: str = ""
    fused_at_t: float | None = None
    processing_ms: float = 0.0
    truth_X_CT: Pose | None = field(default=None, metadata=_doc("true target in camera at capture"))

    @property
    def latency_ms(self) -> float:
        """Capture to fusion (ms)."""
        return 1000.0 * (self.t - self.capture_t)


# --- JSON ------------------------------------------------------------------------------------


def to_json(record: Any, path: str = "$") -> Any:
    """A record as plain JSON data (see the module docstring); raises ``TypeError`` naming the
    path (``$.arm.q``) of a value it cannot write."""
    try:
        return _plain(record)
    except _Unwritable as exc:
        raise TypeError(f"{path}{exc.where}: {exc}") from None


class _Unwritable(TypeError):
    """A value ``to_json`` cannot write; ``where`` grows from the value up to the record (the
    path is built only on this error path: records are written at the control rate)."""

    def __init__(self, message: str):
        super().__init__(message)
        self.where = ""


#: Field names per record class (``dataclasses.fields`` is slow to call per value).
_FIELD_NAMES: dict[type, tuple[str, ...]] = {}


def _plain(value: Any) -> Any:
    kind = type(value)
    if kind is float:
        return value if math.isfinite(value) else None
    if value is None or kind is str or kind is bool or kind is int:
        return value
    names = _FIELD_NAMES.get(kind)
    if names is None and dataclasses.is_dataclass(kind) and kind not in (Pose, Measurement):
        names = _FIELD_NAMES[kind] = tuple(f.name for f in dataclasses.fields(kind))
    if names is not None:
        out = {}
        for name in names:
            try:
                out[name] = _plain(getattr(value, name))
            except _Unwritable as exc:
                exc.where = f".{name}{exc.where}"
                raise
        return out
    if isinstance(value, Pose):  # a diverged pose keeps its shape; its NaNs become null
        return _array_json(value.matrix)
    if isinstance(value, np.ndarray):
        if value.dtype.kind not in "biuf":
            raise _Unwritable(f"cannot write a numpy array of dtype {value.dtype}")
        return _array_json(np.asarray(value, dtype=float))
    if isinstance(value, Measurement):
        return value.to_dict()
    if isinstance(value, float):  # numpy floats
        return float(value) if math.isfinite(value) else None
    if isinstance(value, bool | str | int):
        return value
    if isinstance(value, list | tuple):
        out = []
        for i, item in enumerate(value):
            try:
                out.append(_plain(item))
            except _Unwritable as exc:
                exc.where = f"[{i}]{exc.where}"
                raise
        return out
    raise _Unwritable(f"cannot write a {kind.__name__} into a trial-log record")


def _array_json(values: np.ndarray) -> Any:
    if np.isfinite(values).all():
        return values.tolist()
    return np.where(np.isfinite(values), values, None).tolist()


RecordT = typing.TypeVar("RecordT")


def from_json(cls: type[RecordT], data: Any) -> RecordT:
    """The record of type ``cls`` from its JSON data; raises ``ValueError`` naming the field
    when the data does not fit."""
    return _parser(cls)(data, cls.__name__)


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _required(kind: type) -> list[str]:
    """The fields of a record class that have no default."""
    return [
        f.name
        for f in dataclasses.fields(kind)
        if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
    ]


def _optional(kind: Any) -> tuple[Any, bool]:
    """(the non-None type, whether None is allowed) of an annotation."""
    if typing.get_origin(kind) in (Union, types.UnionType):
        args = [a for a in typing.get_args(kind) if a is not type(None)]
        return (args[0] if len(args) == 1 else Union[tuple(args)]), True  # noqa: UP007
    return kind, False


def _is_record(kind: Any) -> bool:
    return dataclasses.is_dataclass(kind) and kind not in (Pose, Measurement)


def _pose(value: Any) -> Pose:
    # Logged poses hold every digit of float64, so they are rigid transforms as written.
    X = np.asarray(value, dtype=float)
    if X.shape != (4, 4):
        raise ValueError(f"a pose must be 4×4; got shape {X.shape}")
    return Pose.unchecked(X[:3, :3], X[:3, 3])


_LEAF_PARSERS: dict[Any, Any] = {
    Pose: _pose,
    np.ndarray: lambda value: np.array(value, dtype=float),  # null (a NaN) becomes nan
    Measurement: Measurement.from_dict,
    float: float,
    int: int,
    str: lambda value: value,
    bool: lambda value: value,
}


@functools.cache
def _parser(annotation: Any):
    """A function (json value, where) → value for a field's annotation, built once per type:
    reading a log parses thousands of ticks."""
    kind, nullable = _optional(annotation)
    if _is_record(kind):
        hints = _hints(kind)
        fields = [(f.name, _parser(hints[f.name])) for f in dataclasses.fields(kind)]
        required = _required(kind)

        def parse_record(value: Any, where: str) -> Any:
            if value is None:
                if nullable:
                    return None
                raise ValueError(f"{where}: missing value")
            if not isinstance(value, dict):
                raise ValueError(f"{where}: expected an object")
            values = {
                name: parse(value[name], f"{where}.{name}")
                for name, parse in fields
                if name in value
            }
            try:
                return kind(**values)
            except TypeError:  # a required field is missing
                missing = [name for name in required if name not in value]
                raise ValueError(f"{where}: missing {', '.join(missing)}") from None

        return parse_record
    leaf = _LEAF_PARSERS.get(kind)
    if leaf is None and typing.get_origin(kind) is Literal:
        leaf = _LEAF_PARSERS[str]
    if leaf is None:
        raise TypeError(f"no parser for {kind!r}")

    def parse_leaf(value: Any, where: str) -> Any:
        if value is None:
            if nullable:
                return None
            if kind is float:  # a NaN was written as null
                return math.nan
            raise ValueError(f"{where}: missing value")
        try:
            return leaf(value)
        except (TypeError, KeyError, ValueError) as exc:
            raise ValueError(f"{where}: {exc}") from None

    return parse_leaf


# --- JSON Schema -----------------------------------------------------------------------------


def json_schema(cls: type, *, title: str | None = None, description: str = "") -> dict[str, Any]:
    """The JSON Schema of a record class (draft 2020-12 keywords, as ``hil.logs.logschema``)."""

    def schema_of(kind: Any, metadata: typing.Mapping[str, Any]) -> dict[str, Any]:
        kind, nullable = _optional(kind)
        if _is_record(kind):
            node = object_of(kind)
        elif kind is Pose:
            node = _matrix_schema(4, 4)
        elif kind is np.ndarray:
            node = _array_schema(metadata.get("shape", ()))
        elif kind is Measurement:
            node = dict(MEASUREMENT_SCHEMA)
        elif kind is float:
            node = {"type": "number"}
        elif kind is int:
            node = {"type": "integer"}
        elif kind is bool:
            node = {"type": "boolean"}
        elif kind is str:
            node = {"type": "string"}
        elif typing.get_origin(kind) is Literal:
            node = {"type": "string", "enum": list(typing.get_args(kind))}
        else:
            raise TypeError(f"no JSON Schema for {kind!r}")
        if nullable:
            base = node["type"]
            node["type"] = [*base, "null"] if isinstance(base, list) else [base, "null"]
        if metadata.get("doc"):
            node["description"] = metadata["doc"]
        return node

    def object_of(kind: type) -> dict[str, Any]:
        hints = _hints(kind)
        fields = dataclasses.fields(kind)
        return {
            "type": "object",
            "properties": {f.name: schema_of(hints[f.name], f.metadata) for f in fields},
            "required": _required(kind),
        }

    schema = object_of(cls)
    schema["title"] = title or f"satgrasp.{cls.__name__.removesuffix('Record')}"
    if description:
        schema["description"] = description
    return schema


def _array_schema(shape: tuple[int, ...]) -> dict[str, Any]:
    """A numpy vector or matrix; its elements may be null (NaN when written)."""
    number = {"type": ["number", "null"]}
    if len(shape) == 2:
        row = {"type": "array", "items": number, "minItems": shape[1], "maxItems": shape[1]}
        return {"type": "array", "items": row, "minItems": shape[0], "maxItems": shape[0]}
    node: dict[str, Any] = {"type": "array", "items": number}
    if shape:
        node["minItems"] = node["maxItems"] = shape[0]
    return node


def _matrix_schema(rows: int, cols: int) -> dict[str, Any]:
    row = {"type": "array", "items": {"type": "number"}, "minItems": cols, "maxItems": cols}
    return {"type": "array", "items": row, "minItems": rows, "maxItems": rows}


TICK_SCHEMA = json_schema(TickRecord, description="One control tick.")
VISION_SCHEMA = json_schema(
    VisionRecord, description="One estimator result for one frame, and what fusion made of it."
)
