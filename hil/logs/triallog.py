"""Trial logs: one self-describing MCAP file per trial, written tick by tick, readable after a
crash.

Layout (format 2; details in docs/trial_logs.md): the header — versions, host, start time,
seed, the resolved configuration, notes — comes first, as the metadata record
``satgrasp.header`` and as the first message on ``/trial/header``; then one ``TickRecord`` per
control tick on ``/trial/tick``, one ``VisionRecord`` per estimator result on
``/vision/result`` (``hil.logs.records``), events on ``/trial/event`` and optional
``foxglove.CompressedImage`` frames on ``/camera/image``. Messages are JSON with a JSON Schema
per channel, in zstd chunks. A log of an older format is refused with one line that says so.

Crash safety: the writer closes its chunk and flushes the file about once a second, so a
process killed with SIGKILL loses only the open chunk. ``TrialLog.open`` reads such a file
record by record up to the last complete chunk (``recovered`` is then True) and ``recover``
rewrites it as a valid MCAP file.

Writing never raises into the control loop for a bad value: NaN and ±inf become null, numpy
arrays and poses become lists (4×4 for a ``Pose``), a record that does not match its schema is
written with a ``log`` event naming the problems, and a record that cannot be serialised is
replaced by a ``log`` event that says why.
"""

from __future__ import annotations

import base64
import contextlib
import dataclasses
import datetime as dt
import enum
import io
import json
import logging
import math
import numbers
import os
import platform
import socket
import struct
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path, PurePath
from typing import Any, BinaryIO

import cv2
import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    Chunk,
    Footer,
    Header,
    Message,
    MessageIndex,
    Metadata,
    Schema,
)
from mcap.stream_reader import CRCValidationError, breakup_chunk
from mcap.writer import CompressionType, Writer

from estimators.geometry import Pose
from hil.logs.logschema import (
    COMPRESSED_IMAGE_SCHEMA,
    EVENT_SCHEMA,
    HEADER_SCHEMA,
    foxglove_schema,
    validate,
)
from hil.logs.records import (
    FORMAT_VERSION,
    TICK_SCHEMA,
    VISION_SCHEMA,
    TickRecord,
    VisionRecord,
    from_json,
    to_json,
)

FORMAT = "satgrasp.trial_log"
HEADER_TOPIC = "/trial/header"
TICK_TOPIC = "/trial/tick"
VISION_TOPIC = "/vision/result"
EVENT_TOPIC = "/trial/event"
FRAME_TOPIC = "/camera/image"
HEADER_METADATA = "satgrasp.header"
FOOTER_METADATA = "satgrasp.footer"
SCHEMAS_METADATA = "satgrasp.schemas"
RECOVERY_METADATA = "satgrasp.recovery"
MCAP_MAGIC = bytes([137, 77, 67, 65, 80, 48, 13, 10])

#: Packages whose versions every header records (distribution names).
KEY_PACKAGES = (
    "numpy",
    "scipy",
    "opencv-python-headless",
    "pybullet",
    "mcap",
    "zstandard",
    "pydantic",
    "filterpy",
    "ur-rtde",
    "depthai",
    "pymodbus",
    "matplotlib",
)
#: Header keys the writer fills in itself.
ENVIRONMENT_KEYS = (
    "format",
    "format_version",
    "satgrasp_version",
    "python",
    "versions",
    "host",
    "platform",
    "start_time_utc",
    "start_time_unix_ns",
)
#: Schema-mismatch events written per log before they are only counted (in the footer).
MAX_SCHEMA_EVENTS = 20

_SCHEMAS = {
    HEADER_TOPIC: ("satgrasp.TrialHeader", HEADER_SCHEMA),
    TICK_TOPIC: (TICK_SCHEMA["title"], TICK_SCHEMA),
    VISION_TOPIC: (VISION_SCHEMA["title"], VISION_SCHEMA),
    EVENT_TOPIC: ("satgrasp.Event", EVENT_SCHEMA),
    FRAME_TOPIC: ("foxglove.CompressedImage", COMPRESSED_IMAGE_SCHEMA),
}

log = logging.getLogger(__name__)


class TrialLogError(ValueError):
    """A file that is not a readable satgrasp trial log (the message names the file)."""


# --- values to JSON -------------------------------------------------------------------------


def to_jsonable(value: Any, path: str = "$") -> Any:
    """``value`` as plain JSON data: NaN/±inf → None, numpy arrays and scalars → lists and
    Python numbers, ``Pose`` → 4×4 nested lists, objects with ``to_dict()`` and dataclasses →
    dicts, tuples → lists, paths → strings, enums → their value.

    Raises ``TypeError`` naming the path (``$.arm.q``) of a value it cannot represent.
    """
    kind = type(value)  # exact-type dispatch first: ticks are mostly dicts, lists and floats
    if kind is float:
        return value if math.isfinite(value) else None
    if kind is dict:
        return {_key(k, path): to_jsonable(v, f"{path}.{k}") for k, v in value.items()}
    if kind is list or kind is tuple:
        if all(type(item) is float for item in value):  # vectors, matrix rows
            return [item if math.isfinite(item) else None for item in value]
        return [to_jsonable(item, f"{path}[{i}]") for i, item in enumerate(value)]
    if value is None or kind is str or kind is bool or kind is int:
        return value
    if isinstance(value, bool | str):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real):
        value = float(value)
        return value if math.isfinite(value) else None
    if isinstance(value, Pose):
        return value.to_list()
    if isinstance(value, np.ndarray):
        return _array_to_json(value, path)
    if isinstance(value, Mapping):
        return {_key(k, path): to_jsonable(v, f"{path}.{k}") for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [to_jsonable(item, f"{path}[{i}]") for i, item in enumerate(value)]
    if isinstance(value, enum.Enum):
        return to_jsonable(value.value, path)
    if isinstance(value, PurePath):
        return str(value)
    to_dict = getattr(value, "to_dict", None)
    if callable(to_dict):
        return to_jsonable(to_dict(), path)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {
            f.name: to_jsonable(getattr(value, f.name), f"{path}.{f.name}")
            for f in dataclasses.fields(value)
        }
    raise TypeError(f"{path}: cannot log a value of type {type(value).__name__}")


def _key(key: Any, path: str) -> str:
    if type(key) is str:
        return key
    if isinstance(key, str | int) and not isinstance(key, bool):
        return str(key)
    raise TypeError(f"{path}: keys must be strings; got {type(key).__name__} {key!r}")


def _array_to_json(array: np.ndarray, path: str) -> Any:
    kind = array.dtype.kind
    if kind == "f":
        if np.all(np.isfinite(array)):
            return array.tolist()
        return np.where(np.isfinite(array), array, None).tolist()
    if kind in "biu":
        return array.tolist()
    if kind == "O":
        return to_jsonable(array.tolist(), path)
    raise TypeError(f"{path}: cannot log a numpy array of dtype {array.dtype}")


def _dumps(value: Any) -> bytes:
    return json.dumps(value, separators=(",", ":"), allow_nan=False).encode("utf-8")


def frame_message(stamp_ns: int, frame_id: str, encoded: bytes, encoding: str) -> bytes:
    """The JSON of a ``foxglove.CompressedImage`` record, the bytes ``_dumps`` writes for it,
    joined around the base64 text rather than passed through the JSON encoder: the base64
    alphabet needs no escaping, and encoding a 1280×800 frame's megabyte of it as a JSON
    string took 2.8 ms of the control tick that logs it."""
    head = {
        "timestamp": {"sec": stamp_ns // 1_000_000_000, "nsec": stamp_ns % 1_000_000_000},
        "frame_id": frame_id,
    }
    return b"".join(
        (
            _dumps(head)[:-1],
            b',"data":"',
            base64.b64encode(encoded),
            b'","format":',
            _dumps(encoding),
            b"}",
        )
    )


# --- header ---------------------------------------------------------------------------------


def _package_version(name: str) -> str | None:
    try:
        return version(name)
    except PackageNotFoundError:
        return None


def environment(start: dt.datetime) -> dict[str, Any]:
    """The header fields the writer fills in: format, versions, host and start time."""
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "satgrasp_version": _package_version("satgrasp") or "unknown",
        "python": sys.version.split()[0],
        "versions": {name: _package_version(name) for name in KEY_PACKAGES},
        "host": socket.gethostname(),
        "platform": platform.platform(),
        "start_time_utc": start.isoformat(),
        "start_time_unix_ns": int(start.timestamp() * 1e9),
    }


def build_header(header: Mapping[str, Any], start: dt.datetime) -> dict[str, Any]:
    """The complete, validated JSON header from the caller's part (``config``, ``seed``,
    optional ``notes`` and any other keys). Raises ``ValueError`` naming a bad field."""
    if not isinstance(header, Mapping):
        raise ValueError(f"trial log header must be a mapping; got {type(header).__name__}")
    for key in ("config", "seed"):
        if key not in header:
            raise ValueError(f"trial log header needs {key!r}")
    taken = sorted(set(header) & set(ENVIRONMENT_KEYS))
    if taken:
        raise ValueError(f"trial log header: {', '.join(taken)} are filled in by the writer")
    try:
        user = to_jsonable(dict(header), "header")
    except (TypeError, RecursionError) as exc:
        raise ValueError(f"trial log header cannot be serialised: {exc}") from None
    full = {**environment(start), "notes": "", **user}
    problems = validate(full, HEADER_SCHEMA)
    if problems:
        raise ValueError("trial log header: " + "; ".join(p.replace("$.", "") for p in problems))
    return full


def _metadata_strings(record: Mapping[str, Any]) -> dict[str, str]:
    """MCAP metadata is string → string: strings stay readable, the rest is JSON."""
    return {k: v if isinstance(v, str) else json.dumps(v) for k, v in record.items()}


# --- writer ---------------------------------------------------------------------------------


class TrialLogWriter:
    """Writes one trial's log (see the module docstring). Use as a context manager.

    ``header``: ``config`` (the full resolved configuration, JSON-able), ``seed`` (int or
    None), optional ``notes`` and any other keys; the writer adds versions, host and the UTC
    start time. A bad header raises ``ValueError`` here, before the trial starts; afterwards
    the ``write_*`` methods never raise: they return False when a record was not written as
    given, and ``error`` holds the first I/O failure (after which nothing more is written).

    ``flush_interval_s``: the open chunk is closed and the file flushed at the last write
    before this long (by ``clock``) would have passed since the previous flush, judged from
    the typical interval between writes; so with writes at a steady rate a killed writer loses
    at most the records of the last ``flush_interval_s``. Thread-safe.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        header: Mapping[str, Any],
        *,
        flush_interval_s: float = 0.25,
        clock: Callable[[], float] = time.monotonic,
    ):
        if not flush_interval_s > 0:
            raise ValueError(f"flush_interval_s must be positive; got {flush_interval_s}")
        self.path = Path(path)
        self._clock = clock
        self._flush_interval_s = float(flush_interval_s)
        start = dt.datetime.now(dt.UTC)
        self.header = build_header(header, start)
        self._start_ns: int = self.header["start_time_unix_ns"]
        self._lock = threading.RLock()
        self._closed = False
        self.error: str | None = None
        #: Trial time (s) of the last record handed to the writer when ``error`` happened.
        self.error_t: float | None = None
        self.counts = {
            "ticks": 0,
            "vision": 0,
            "events": 0,
            "frames": 0,
            "invalid_ticks": 0,
            "invalid_vision": 0,
            "replaced": 0,
            "other": 0,  # messages of add_channel's channels (Foxglove's)
        }
        #: How many times the open chunk was closed and the file flushed (for tests/monitors).
        self.flush_count = 0
        self._last_t = 0.0
        self._sequence: dict[int, int] = {}
        self._channels: dict[str, int] = {}
        self._last_flush = clock()
        self._last_write: float | None = None
        self._write_period = 0.0  # running mean of the interval between writes (clock s)
        self._writes = 0
        try:  # never over an earlier trial's log
            self._file: BinaryIO = open(self.path, "xb")  # noqa: SIM115 — closed in close()
        except FileExistsError:
            raise TrialLogError(
                f"trial log {self.path} already exists; logs are never overwritten"
            ) from None
        except OSError as exc:
            raise TrialLogError(f"cannot create trial log {self.path}: {exc}") from None
        try:
            self._start_file()
        except Exception as exc:
            self._fail(exc)
        if self.error is not None:
            self._closed = True
            with contextlib.suppress(OSError):  # the buffered bytes cannot be written either
                self._file.close()
            raise TrialLogError(f"cannot write trial log {self.path}: {self.error}")

    def _start_file(self) -> None:
        """Header first: metadata records, channels, the header message; then flush."""
        self._writer = Writer(self._file, compression=CompressionType.ZSTD)
        self._writer.start(profile="", library=f"satgrasp {self.header['satgrasp_version']}")
        self._writer.add_metadata(HEADER_METADATA, _metadata_strings(self.header))
        self._writer.add_metadata(
            SCHEMAS_METADATA,
            {topic: json.dumps(schema) for topic, (_, schema) in _SCHEMAS.items()},
        )
        for topic in (HEADER_TOPIC, TICK_TOPIC, VISION_TOPIC, EVENT_TOPIC):
            self._register(topic)
        self._add(HEADER_TOPIC, 0.0, _dumps(self.header))
        self.flush()  # the header is on disk before the first tick

    # --- public API -----------------------------------------------------------------------
    def write_tick(self, record: TickRecord) -> bool:
        """Log one control tick (``hil.logs.records.TickRecord``). A record that does not match
        the tick schema is still written, with a ``log`` event naming the problems; one that
        cannot be serialised is replaced by such an event. True when written as given."""
        with self._lock:
            return self._write_record(TICK_TOPIC, record, TickRecord, "tick", "ticks")

    def write_vision(self, record: VisionRecord) -> bool:
        """Log one estimator result (``hil.logs.records.VisionRecord``), as ``write_tick``."""
        with self._lock:
            return self._write_record(VISION_TOPIC, record, VisionRecord, "vision", "vision")

    def _write_record(self, topic: str, record: Any, kind: type, what: str, count: str) -> bool:
        t = self._time_of(record)
        name = _label(record) if isinstance(record, kind) else f"{what} record"
        try:
            if not isinstance(record, kind):
                raise TypeError(f"expected a {kind.__name__}; got {type(record).__name__}")
            clean = to_json(record, what)
            data = _dumps(clean)
        except Exception as exc:  # a bad value must never stop the control loop
            self.counts["replaced"] += 1
            self._log_event(t, f"{name} not logged: {exc}")
            return False
        schema = _SCHEMAS[topic][1]
        problems = validate(clean, schema, limit=3)
        if problems:
            self.counts[f"invalid_{count}"] += 1
            if self.counts[f"invalid_{count}"] <= MAX_SCHEMA_EVENTS:
                self._log_event(
                    t, f"{name} does not match the {what} schema: {'; '.join(problems)}"
                )
        if not self._add(topic, t, data):
            return False
        self.counts[count] += 1
        return not problems

    def write_event(self, t: float, kind: str, message: str, /, **data: Any) -> bool:
        """Log an event (``phase``, ``fault``, ``abort``, ``info``, …) at trial time ``t`` (s)
        with free-form ``data``; data that cannot be serialised is replaced by its error."""
        with self._lock:
            return self._write_event(t, kind, message, data)

    def _write_event(self, t: float, kind: str, message: str, data: dict[str, Any]) -> bool:
        replaced = False
        try:
            clean_data = to_jsonable(data, "data")
        except Exception as exc:
            clean_data, replaced = {"unserialisable": str(exc)}, True
            self.counts["replaced"] += 1
        t = self._time_of({"t": t})
        record = {"t": t, "kind": str(kind), "message": str(message), "data": clean_data}
        if not self._add(EVENT_TOPIC, t, _dumps(record)):
            return False
        self.counts["events"] += 1
        return not replaced

    def write_frame(
        self,
        t: float,
        image: np.ndarray,
        *,
        encoding: str = "jpeg",
        frame_id: str = "camera",
        jpeg_quality: int = 90,
    ) -> bool:
        """Log a camera image (uint8 HxW or HxWx3 BGR) as a ``foxglove.CompressedImage``.
        Decimation is the caller's choice. A bad image is replaced by a ``log`` event.
        Encoding a VGA frame takes several milliseconds: a real-time caller encodes elsewhere
        (``encode_image``) and hands the bytes to ``write_encoded_frame``."""
        try:
            encoded = encode_image(image, encoding, jpeg_quality)
        except Exception as exc:
            with self._lock:
                self.counts["replaced"] += 1
                self._log_event(self._time_of({"t": t}), f"frame not logged: {exc}")
            return False
        return self.write_encoded_frame(t, encoded, encoding=encoding, frame_id=frame_id)

    def write_encoded_frame(
        self, t: float, data: bytes, *, encoding: str = "jpeg", frame_id: str = "camera"
    ) -> bool:
        """Log an already encoded camera image (``encoding``: jpeg or png)."""
        with self._lock:
            return self._write_frame(t, data, encoding, frame_id)

    def _write_frame(self, t: float, encoded: bytes, encoding: str, frame_id: str) -> bool:
        t = self._time_of({"t": t})
        if FRAME_TOPIC not in self._channels and not self._closed and self.error is None:
            try:
                self._register(FRAME_TOPIC)
            except Exception as exc:
                self._fail(exc)
        if not self._add(
            FRAME_TOPIC, t, frame_message(self._log_time(t), frame_id, encoded, encoding)
        ):
            return False
        self.counts["frames"] += 1
        return True

    def add_channel(
        self, topic: str, schema_name: str, schema_encoding: str, schema: bytes, encoding: str
    ) -> bool:
        """Register a channel of another encoding (e.g. Foxglove's protobuf schemas,
        ``hil.logs.foxglove``) for ``write_message``; False if logging has stopped."""
        with self._lock:
            if self._closed or self.error is not None:
                return False
            if topic in self._channels:
                return True
            try:
                schema_id = self._writer.register_schema(schema_name, schema_encoding, schema)
                self._channels[topic] = self._writer.register_channel(topic, encoding, schema_id)
            except Exception as exc:
                self._fail(exc)
                return False
            return True

    def write_message(self, topic: str, t: float, data: bytes) -> bool:
        """Log an already encoded message on a channel of ``add_channel`` at trial time ``t``."""
        with self._lock:
            if topic not in self._channels:
                return False
            if not self._add(topic, self._time_of({"t": t}), data):
                return False
            self.counts["other"] += 1
            return True

    def flush(self) -> None:
        """Close the open chunk and push everything written so far to the OS."""
        with self._lock:
            if self._closed or self.error is not None:
                return
            self._flush_now()

    def close(self) -> None:
        """Write the footer (counts, end time) and the MCAP summary; idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            try:
                if self.error is None:
                    end = dt.datetime.now(dt.UTC)
                    footer = {
                        **self.counts,
                        "end_time_utc": end.isoformat(),
                        "last_t": self._last_t,
                    }
                    self._writer.flush()  # the last chunk goes before the footer record
                    self._writer.add_metadata(FOOTER_METADATA, _metadata_strings(footer))
                    self._writer.finish()
                    self._file.flush()
                    os.fsync(self._file.fileno())
            except Exception as exc:
                self._fail(exc)
            finally:
                with contextlib.suppress(OSError):
                    self._file.close()

    @property
    def closed(self) -> bool:
        return self._closed

    def __enter__(self) -> TrialLogWriter:
        return self

    def __exit__(self, exc_type, exc, traceback) -> None:
        if exc_type is not None:
            self._log_event(self._last_t, f"trial ended by {exc_type.__name__}: {exc}")
        self.close()

    # --- internals ------------------------------------------------------------------------
    def _register(self, topic: str) -> None:
        name, schema = _SCHEMAS[topic]
        schema_id = self._writer.register_schema(
            name, "jsonschema", json.dumps(foxglove_schema(schema)).encode("utf-8")
        )
        self._channels[topic] = self._writer.register_channel(topic, "json", schema_id)

    def _time_of(self, record: Any) -> float:
        """The record's ``t`` (s), or the last one when it has none usable."""
        t = record.get("t") if isinstance(record, Mapping) else getattr(record, "t", None)
        if isinstance(t, numbers.Real) and not isinstance(t, bool) and math.isfinite(t):
            self._last_t = max(self._last_t, float(t))
            return float(t)
        return self._last_t

    def stamp_ns(self, t: float) -> int:
        """The log time (ns since the Unix epoch) of trial time ``t`` (s): the start + ``t``."""
        return self._log_time(t)

    def _log_time(self, t: float) -> int:
        return self._start_ns + round(max(t, 0.0) * 1e9)

    def _log_event(self, t: float, message: str, **data: Any) -> None:
        log.warning("%s: %s", self.path, message)
        self.write_event(t, "log", message, **data)

    def _add(self, topic: str, t: float, data: bytes) -> bool:
        with self._lock:
            if self._closed or self.error is not None:
                if self._closed and self.error is None:
                    log.warning("%s: write after close dropped", self.path)
                return False
            try:
                channel = self._channels[topic]
                sequence = self._sequence.get(channel, 0)
                self._sequence[channel] = sequence + 1
                stamp = self._log_time(t)
                self._writer.add_message(channel, stamp, data, stamp, sequence)
            except Exception as exc:  # disk full, file gone: stop logging, keep the loop alive
                self._fail(exc)
                return False
            now = self._clock()
            if self._last_write is not None:
                gap = max(0.0, now - self._last_write)
                weight = 1.0 if self._writes == 1 else 0.2  # the first gap sets the mean
                self._write_period += weight * (gap - self._write_period)
            self._last_write = now
            self._writes += 1
            # flush now if waiting for the next write would overrun the interval
            if now - self._last_flush + self._write_period >= self._flush_interval_s:
                self._flush_now()
            return self.error is None

    def _flush_now(self) -> None:
        try:
            self._writer.flush()
        except Exception as exc:
            self._fail(exc)
            return
        self._last_flush = self._clock()
        self.flush_count += 1

    def _fail(self, exc: BaseException) -> None:
        if self.error is None:
            self.error = f"{type(exc).__name__}: {exc}"
            self.error_t = self._last_t
            log.error("%s: trial log writing failed, nothing more is written: %s", self.path, exc)


def _label(record: TickRecord | VisionRecord) -> str:
    """How log events name a record: ``tick 12``, ``vision result corners frame 40``."""
    if isinstance(record, TickRecord):
        return f"tick {record.tick}"
    return f"vision result {record.system} frame {record.seq}"


def encode_image(image: np.ndarray, encoding: str = "jpeg", jpeg_quality: int = 90) -> bytes:
    """``image`` (uint8 HxW or HxWx3 BGR) as JPEG or PNG bytes; ``ValueError`` or ``TypeError``
    saying what is wrong with it."""
    if encoding not in ("jpeg", "png"):
        raise ValueError(f"encoding must be 'jpeg' or 'png'; got {encoding!r}")
    if not isinstance(image, np.ndarray):
        raise TypeError(f"image must be a numpy array; got {type(image).__name__}")
    if image.dtype != np.uint8 or image.ndim not in (2, 3) or image.size == 0:
        raise ValueError(
            f"image must be non-empty uint8 HxW or HxWx3; got {image.dtype} {image.shape}"
        )
    if image.ndim == 3 and image.shape[2] not in (1, 3):
        raise ValueError(f"image must have 1 or 3 channels; got shape {image.shape}")
    params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if encoding == "jpeg" else []
    ok, buffer = cv2.imencode(".jpg" if encoding == "jpeg" else ".png", image, params)
    if not ok:
        raise ValueError(f"OpenCV could not encode the image as {encoding}")
    return buffer.tobytes()


# --- reader ---------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Unreadable:
    """A stretch of a log file that could not be read: ``what`` (a chunk, a metadata record,
    …) at byte ``offset``, ``length`` bytes, and why; for a chunk the log times (ns) of the
    messages it held, and how many per channel id its message indexes list."""

    what: str
    offset: int
    length: int
    reason: str
    start_ns: int | None = None
    end_ns: int | None = None
    lost: dict[int, int] = dataclasses.field(default_factory=dict)


@dataclass
class _Scan:
    """Everything found reading a (possibly truncated or corrupt) MCAP file from the start."""

    header: Header | None = None
    schemas: dict[int, Schema] = dataclasses.field(default_factory=dict)
    channels: dict[int, Channel] = dataclasses.field(default_factory=dict)
    messages: list[Message] = dataclasses.field(default_factory=list)
    counts: dict[int, int] = dataclasses.field(default_factory=dict)  # messages per channel
    metadata: dict[str, dict[str, str]] = dataclasses.field(default_factory=dict)
    #: The MCAP footer was reached: the writer finished the file.
    complete: bool = False
    #: Why the scan ended before a footer ("" when it reached one).
    stopped: str = ""
    #: Records inside the file that could not be read (the file is corrupt), in file order.
    unreadable: list[Unreadable] = dataclasses.field(default_factory=list)


def _check_file(path: Path) -> None:
    if not path.exists():
        raise FileNotFoundError(f"trial log {path} does not exist")
    if not path.is_file():
        raise TrialLogError(f"trial log {path} is not a file")
    size = path.stat().st_size
    if size == 0:
        raise TrialLogError(f"trial log {path} is empty (0 bytes): the writer never started")
    with path.open("rb") as f:
        magic = f.read(len(MCAP_MAGIC))
    if magic != MCAP_MAGIC:
        raise TrialLogError(f"{path} is not an MCAP file (its first bytes are not MCAP's magic)")


_RECORD_READERS: dict[int, Callable[[ReadDataStream, int], Any]] = {
    Opcode.HEADER: lambda stream, _: Header.read(stream),
    Opcode.FOOTER: lambda stream, _: Footer.read(stream),
    Opcode.SCHEMA: lambda stream, _: Schema.read(stream),
    Opcode.CHANNEL: lambda stream, _: Channel.read(stream),
    Opcode.MESSAGE: Message.read,
    Opcode.CHUNK: lambda stream, _: Chunk.read(stream),
    Opcode.MESSAGE_INDEX: lambda stream, _: MessageIndex.read(stream),
    Opcode.METADATA: lambda stream, _: Metadata.read(stream),
}
#: Records a reader of trial logs passes over (indexes and summaries it does not need).
_SKIPPED = {
    Opcode.ATTACHMENT,
    Opcode.ATTACHMENT_INDEX,
    Opcode.CHUNK_INDEX,
    Opcode.DATA_END,
    Opcode.METADATA_INDEX,
    Opcode.STATISTICS,
    Opcode.SUMMARY_OFFSET,
}


def _scan(path: Path, keep: Callable[[Channel], bool]) -> _Scan:
    """Read records in file order until the MCAP footer.

    MCAP frames every record with its opcode and length, so a record that does not read — a
    chunk whose CRC or compressed data is wrong, say — is passed over and the scan goes on
    (``unreadable``: the file is corrupt). The scan ends early, ``stopped`` saying why, when
    the file ends before the footer (a writer killed, or one that could not write: the records
    it had flushed are all there), or when the framing itself is lost (a corrupt length or
    opcode: nothing after it can be found)."""
    scan = _Scan()
    size = path.stat().st_size
    after_bad_chunk: Unreadable | None = None
    with path.open("rb") as f:
        f.seek(len(MCAP_MAGIC))  # checked by _check_file
        while not scan.complete:
            offset = f.tell()
            head = f.read(9)
            if len(head) < 9:
                scan.stopped = "the file ends without a footer" + (
                    "" if not head else " (within a record's start)"
                )
                break
            opcode, length = struct.unpack("<BQ", head)
            if opcode not in _RECORD_READERS and opcode not in _SKIPPED and opcode < 0x80:
                scan.stopped = _lost_framing(scan, offset, size, f"no MCAP record type {opcode}")
                break
            if offset + 9 + length > size:
                if _ends_with_magic(f, size):  # a finished file: the length is corrupt
                    scan.stopped = _lost_framing(scan, offset, size, f"a length of {length} B")
                else:
                    scan.stopped = (
                        f"the file ends without a footer, within a record of {length} bytes "
                        f"that starts at byte {offset}"
                    )
                break
            payload = f.read(length)
            if opcode not in _RECORD_READERS:
                continue
            record = None
            try:
                record = _RECORD_READERS[opcode](ReadDataStream(io.BytesIO(payload)), length)
                records = [record]
                if opcode == Opcode.CHUNK:
                    records = breakup_chunk(record, validate_crc=True)
            except Exception as exc:  # CRC, zstd, struct, UTF-8: this record is corrupt
                bad = Unreadable(
                    _RECORD_NAMES.get(opcode, "record"),
                    offset,
                    9 + length,
                    _reason(exc),
                    getattr(record, "message_start_time", None),
                    getattr(record, "message_end_time", None),
                )
                scan.unreadable.append(bad)
                after_bad_chunk = bad if opcode == Opcode.CHUNK else after_bad_chunk
                continue
            if opcode == Opcode.CHUNK:
                after_bad_chunk = None
            elif opcode == Opcode.MESSAGE_INDEX and after_bad_chunk is not None:
                index = record  # what the chunk before held, per channel
                lost = after_bad_chunk.lost
                lost[index.channel_id] = lost.get(index.channel_id, 0) + len(index.records)
            for item in records:
                _take(scan, item, keep)
    return scan


def _take(scan: _Scan, record: Any, keep: Callable[[Channel], bool]) -> None:
    if isinstance(record, Message):
        scan.counts[record.channel_id] = scan.counts.get(record.channel_id, 0) + 1
        channel = scan.channels.get(record.channel_id)
        if channel is not None and keep(channel):
            scan.messages.append(record)
    elif isinstance(record, Channel):
        scan.channels[record.id] = record
    elif isinstance(record, Schema):
        scan.schemas[record.id] = record
    elif isinstance(record, Metadata):
        scan.metadata[record.name] = dict(record.metadata)
    elif isinstance(record, Header):
        scan.header = record
    elif isinstance(record, Footer):
        scan.complete = True


_RECORD_NAMES = {
    Opcode.HEADER: "header record",
    Opcode.FOOTER: "footer record",
    Opcode.SCHEMA: "schema record",
    Opcode.CHANNEL: "channel record",
    Opcode.MESSAGE: "message record",
    Opcode.CHUNK: "chunk",
    Opcode.MESSAGE_INDEX: "message index",
    Opcode.METADATA: "metadata record",
}


def _reason(exc: BaseException) -> str:
    text = str(exc)
    if isinstance(exc, CRCValidationError):
        text = "its CRC does not match its data"
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _ends_with_magic(f: BinaryIO, size: int) -> bool:
    """Whether the file ends with MCAP's magic (its writer finished it)."""
    if size < 2 * len(MCAP_MAGIC):
        return False
    position = f.tell()
    f.seek(size - len(MCAP_MAGIC))
    magic = f.read(len(MCAP_MAGIC))
    f.seek(position)
    return magic == MCAP_MAGIC


def _lost_framing(scan: _Scan, offset: int, size: int, found: str) -> str:
    """The record boundaries are lost at ``offset`` (a corrupt length or type): the rest of
    the file is unreadable."""
    reason = f"corrupt record framing ({found})"
    scan.unreadable.append(Unreadable("data", offset, size - offset, reason))
    return f"{reason} at byte {offset}: the {size - offset} bytes after it could not be read"


@dataclass(frozen=True, slots=True)
class LoggedFrame:
    """A logged camera image: trial time ``t`` (s), ``format`` (jpeg/png), encoded ``data``."""

    t: float
    format: str
    frame_id: str
    data: bytes

    def image(self) -> np.ndarray:
        """The decoded image (uint8, as written; JPEG is lossy)."""
        image = cv2.imdecode(np.frombuffer(self.data, np.uint8), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise ValueError(f"frame at t={self.t:.3f} s: cannot decode its {self.format} data")
        return image


class TrialLog:
    """A trial log opened for reading: ``header``, ``ticks()``, ``vision()``, ``events()``,
    ``frames()``.

    ``recovered`` is True when the file has no MCAP footer (its writer was killed, or could not
    write) and the records were read from the complete chunks; ``complete`` is True when the
    writer closed the log normally (its ``satgrasp.footer`` is present). ``unreadable`` lists
    the parts of the file that do not read (a corrupt file: ``damage()`` says what they held);
    the rest was read all the same. ``problems`` lists the records that
    ``ticks()`` and ``vision()`` skipped because they do not read back as records (each
    naming the record and the field), filled in as they are read. Open with ``TrialLog.open``.
    """

    def __init__(self, path: Path, scan: _Scan):
        self.path = path
        self.recovered = not scan.complete
        self.stopped = scan.stopped
        self.metadata = scan.metadata
        self.footer: dict[str, str] | None = scan.metadata.get(FOOTER_METADATA)
        self.complete = self.footer is not None
        self.recovery: dict[str, str] | None = scan.metadata.get(RECOVERY_METADATA)
        self.unreadable: list[Unreadable] = scan.unreadable
        topics = {channel.id: channel.topic for channel in scan.channels.values()}
        self._topics = topics
        by_topic: dict[str, list[Message]] = {}
        for message in scan.messages:
            by_topic.setdefault(topics[message.channel_id], []).append(message)
        for messages in by_topic.values():
            messages.sort(key=lambda m: (m.log_time, m.sequence))
        headers = by_topic.get(HEADER_TOPIC, [])
        if not headers:
            ours = scan.header is not None and scan.header.library.startswith("satgrasp")
            if ours or HEADER_METADATA in scan.metadata or HEADER_TOPIC in topics.values():
                raise TrialLogError(
                    f"trial log {path} holds no header message: its writer stopped before "
                    f"the header was flushed ({scan.stopped or 'no header written'})"
                )
            raise TrialLogError(
                f"{path} is an MCAP file but not a satgrasp trial log (no {HEADER_TOPIC} channel)"
            )
        self.header: dict[str, Any] = self._decode(headers[0], "header")
        if self.header.get("format") != FORMAT:
            raise TrialLogError(
                f"{path}: header format is {self.header.get('format')!r}, not {FORMAT!r}"
            )
        _check_format_version(path, self.header)
        self._start_ns = int(self.header["start_time_unix_ns"])
        self._ticks = by_topic.get(TICK_TOPIC, [])
        self._vision = by_topic.get(VISION_TOPIC, [])
        self._events = by_topic.get(EVENT_TOPIC, [])
        self.problems: list[str] = []
        self.frame_count = sum(
            n for channel_id, n in scan.counts.items() if topics.get(channel_id) == FRAME_TOPIC
        )

    @classmethod
    def open(cls, path: str | os.PathLike[str]) -> TrialLog:
        """Open a trial log, complete or cut off by a crash. Raises ``FileNotFoundError`` or
        ``TrialLogError`` (naming the file) for a missing, empty, non-MCAP or foreign file."""
        path = Path(path)
        _check_file(path)
        topics = (HEADER_TOPIC, TICK_TOPIC, VISION_TOPIC, EVENT_TOPIC)
        scan = _scan(path, keep=lambda c: c.topic in topics)
        return cls(path, scan)

    @property
    def corrupt(self) -> bool:
        """Some part of the file does not read (a flipped byte, a damaged disk): not a killed
        writer, which leaves only a cut-off tail."""
        return bool(self.unreadable)

    def damage(self) -> str | None:
        """What the unreadable parts of a corrupt log held, in one sentence (None when it has
        none): where they are, why they do not read, their time span and the records lost."""
        if not self.unreadable:
            return None
        parts, lost = [], {}
        for bad in self.unreadable:
            span = ""
            if bad.start_ns is not None and bad.end_ns is not None:
                first, last = ((ns - self._start_ns) / 1e9 for ns in (bad.start_ns, bad.end_ns))
                span = f", t {first:.2f}–{last:.2f} s"
            parts.append(
                f"{bad.what} at bytes {bad.offset}–{bad.offset + bad.length}{span} ({bad.reason})"
            )
            for channel_id, count in bad.lost.items():
                topic = self._topics.get(channel_id, f"channel {channel_id}")
                lost[topic] = lost.get(topic, 0) + count
        names = {TICK_TOPIC: "ticks", VISION_TOPIC: "vision results", EVENT_TOPIC: "events"}
        kept = {TICK_TOPIC: self.tick_count, VISION_TOPIC: self.vision_count}
        held = [
            f"{count} {names.get(topic, topic)}"
            + (f" of {count + kept[topic]}" if topic in kept else "")
            for topic, count in sorted(lost.items())
        ]
        framing_lost = self.unreadable[-1].what == "data"
        return (
            f"{len(parts)} unreadable part{'s' if len(parts) > 1 else ''}: {'; '.join(parts)}"
            + (f"; lost with them: {', '.join(held)}" if held else "")
            + ("" if framing_lost else "; every other record was read")
        )

    @property
    def tick_count(self) -> int:
        return len(self._ticks)

    @property
    def vision_count(self) -> int:
        return len(self._vision)

    @property
    def event_count(self) -> int:
        return len(self._events)

    def ticks(self) -> Iterator[TickRecord]:
        """Tick records in time order (NaN written as null reads back as NaN)."""
        return self._records(self._ticks, TickRecord, "tick")

    def vision(self) -> Iterator[VisionRecord]:
        """Vision records (one per estimator result) in the order they reached fusion."""
        return self._records(self._vision, VisionRecord, "vision result")

    def _records(self, messages: list[Message], kind: type, what: str) -> Iterator[Any]:
        for message in messages:
            data = self._decode(message, what)
            try:
                yield from_json(kind, data)
            except ValueError as exc:  # written with a schema problem (the log says which)
                self.problems.append(f"{what} message {message.sequence} skipped: {exc}")

    def events(self) -> Iterator[dict[str, Any]]:
        """Events in time order: ``t``, ``kind``, ``message``, ``data``."""
        for message in self._events:
            yield self._decode(message, "event")

    def frames(self) -> Iterator[LoggedFrame]:
        """Logged camera images in time order (read from the file on each call)."""
        scan = _scan(self.path, keep=lambda c: c.topic == FRAME_TOPIC)
        for message in sorted(scan.messages, key=lambda m: (m.log_time, m.sequence)):
            record = self._decode(message, "frame")
            yield LoggedFrame(
                t=(message.log_time - self._start_ns) / 1e9,
                format=record.get("format", ""),
                frame_id=record.get("frame_id", ""),
                data=base64.b64decode(record.get("data", "")),
            )

    def messages(self, topic_prefix: str) -> Iterator[tuple[str, float, bytes]]:
        """(topic, trial time s, raw data) of every message on topics starting with
        ``topic_prefix`` (e.g. Foxglove's ``/camera/features/``), in time order, read from the
        file (a killed writer's too) on each call."""
        scan = _scan(self.path, keep=lambda c: c.topic.startswith(topic_prefix))
        topics = {channel.id: channel.topic for channel in scan.channels.values()}
        for message in sorted(scan.messages, key=lambda m: (m.log_time, m.sequence)):
            t = (message.log_time - self._start_ns) / 1e9
            yield topics[message.channel_id], t, message.data

    def _decode(self, message: Message, what: str) -> dict[str, Any]:
        try:
            return json.loads(message.data)
        except (ValueError, UnicodeDecodeError) as exc:
            raise TrialLogError(
                f"trial log {self.path}: {what} message {message.sequence} is not JSON ({exc})"
            ) from None


def _check_format_version(path: Path, header: Mapping[str, Any]) -> None:
    """One clear line for a log this reader cannot read (older or newer format)."""
    found = header.get("format_version")
    if found == FORMAT_VERSION:
        return
    written = f"satgrasp {header.get('satgrasp_version', '?')}, {header.get('start_time_utc', '?')}"
    if isinstance(found, int) and found < FORMAT_VERSION:
        raise TrialLogError(
            f"{path}: trial log format {found}, written before the typed records of format "
            f"{FORMAT_VERSION} ({written}); re-run the trial to analyse it"
        )
    raise TrialLogError(
        f"{path}: trial log format {found!r} ({written}) is not the format {FORMAT_VERSION} "
        "this satgrasp reads; use the satgrasp that wrote it"
    )


def recover(path: str | os.PathLike[str], out_path: str | os.PathLike[str]) -> Path:
    """Rewrite the readable part of ``path`` (e.g. a log whose writer was killed) as a valid
    MCAP file ``out_path`` with a summary and index; adds a ``satgrasp.recovery`` metadata
    record saying what was recovered. Returns ``out_path``."""
    source, target = Path(path), Path(out_path)
    if source.resolve() == target.resolve():
        raise ValueError(f"recover: write to a new file, not over {source}")
    _check_file(source)
    scan = _scan(source, keep=lambda c: True)
    with target.open("wb") as f:
        writer = Writer(f, compression=CompressionType.ZSTD)
        profile = scan.header.profile if scan.header is not None else ""
        writer.start(profile=profile, library=scan.header.library if scan.header else "")
        for name, data in scan.metadata.items():
            writer.add_metadata(name, data)
        schema_ids = {
            old: writer.register_schema(s.name, s.encoding, s.data)
            for old, s in sorted(scan.schemas.items())
        }
        channel_ids = {
            old: writer.register_channel(
                c.topic, c.message_encoding, schema_ids.get(c.schema_id, 0), dict(c.metadata)
            )
            for old, c in sorted(scan.channels.items())
        }
        for m in scan.messages:
            writer.add_message(
                channel_ids[m.channel_id], m.log_time, m.data, m.publish_time, m.sequence
            )
        writer.add_metadata(
            RECOVERY_METADATA,
            {
                "source": str(source),
                "recovered_at_utc": dt.datetime.now(dt.UTC).isoformat(),
                "messages": str(len(scan.messages)),
                "source_complete": str(scan.complete).lower(),
                "stopped": scan.stopped,
            },
        )
        writer.finish()
    return target
