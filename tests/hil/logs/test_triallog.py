import base64
import dataclasses
import json
import math
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from drivers.base import ArmState
from estimators.geometry import Pose
from hil.logs.records import CommandRecord, to_json
from hil.logs.triallog import (
    EVENT_TOPIC,
    FOOTER_METADATA,
    HEADER_METADATA,
    TICK_TOPIC,
    VISION_TOPIC,
    TrialLog,
    TrialLogError,
    TrialLogWriter,
    frame_message,
    recover,
    to_jsonable,
)
from tests.hil.logs.synthetic_log import (
    chunk_spans,
    distance_at,
    flip_a_byte,
    make_trial,
    synthetic_frame,
    write_format1_log,
    write_trial,
)

REPO = Path(__file__).resolve().parents[3]


class FakeClock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture(scope="module")
def trial():
    return make_trial(seed=7)


def _header(**extra):
    return {"config": {"camera": "reference", "gain": 1.5}, "seed": 42, **extra}


def _same(a, b) -> bool:
    """Records equal as logged (poses and arrays compared by their JSON values)."""
    return json.dumps(to_json(a)) == json.dumps(to_json(b))


def test_writer_round_trip_header_ticks_vision_events_frames(tmp_path, trial):
    path = tmp_path / "run.mcap"
    writer = write_trial(path, trial, frames_every=50)
    assert writer.error is None and writer.counts["invalid_ticks"] == 0
    assert writer.counts["invalid_vision"] == 0 and writer.counts["replaced"] == 0
    log = TrialLog.open(path)
    assert (log.recovered, log.complete) == (False, True)
    header = log.header
    assert header["seed"] == 7 and header["config"] == json.loads(
        json.dumps(trial.header["config"])
    )
    assert header["notes"].startswith("synthetic approach")
    assert header["versions"]["numpy"] == np.__version__ and header["versions"]["mcap"]
    assert header["python"] == sys.version.split()[0] and header["host"]
    ticks = list(log.ticks())
    assert len(ticks) == len(trial.ticks) == log.tick_count
    for written, read in zip(trial.ticks, ticks, strict=True):
        assert type(read) is type(written) and _same(read, written), written.tick
    assert np.array_equal(ticks[40].truth.X_CT.matrix, trial.ticks[40].truth.X_CT.matrix)
    assert ticks[40].timing == trial.ticks[40].timing and ticks[40].vision == trial.ticks[40].vision
    assert ticks[0].estimate.X_CT is None and ticks[0].timing.period_ms is None
    vision = list(log.vision())
    assert len(vision) == len(trial.vision) == log.vision_count and not log.problems
    for written, read in zip(trial.vision, vision, strict=True):
        assert type(read) is type(written) and _same(read, written), (written.system, written.seq)
    events = list(log.events())
    assert [e["message"] for e in events] == [
        e[2] for e in sorted(trial.events, key=lambda e: e[0])
    ]
    assert events[0] == {
        "t": next(r.t for r in trial.ticks if r.phase == "acquire"),
        "kind": "phase",
        "message": "idle → acquire",
        "data": {"from": "idle", "to": "acquire"},
    }
    frames = list(log.frames())
    assert len(frames) == len(trial.image_t) >= 4
    assert [f.t for f in frames] == pytest.approx(trial.image_t, abs=1e-9)
    expected = synthetic_frame(distance_at(trial.image_t[1]))
    assert np.abs(frames[1].image().astype(int) - expected).mean() < 2.0  # JPEG, lossy
    assert log.footer["ticks"] == str(len(trial.ticks))
    assert log.footer["vision"] == str(len(trial.vision))


def test_frames_png_is_lossless_and_colour_survives(tmp_path):
    rng = np.random.default_rng(1)
    colour = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
    with TrialLogWriter(tmp_path / "f.mcap", _header()) as writer:
        assert writer.write_frame(0.25, colour, encoding="png", frame_id="wrist")
    (frame,) = TrialLog.open(tmp_path / "f.mcap").frames()
    assert (frame.t, frame.format, frame.frame_id) == (0.25, "png", "wrist")
    assert np.array_equal(frame.image(), colour)


def test_frame_message_is_the_json_encoder_s_own_bytes():
    # Joined around the base64 text instead of encoded whole: the same bytes, escapes and all.
    encoded = bytes(range(256)) * 3
    stamp_ns = 12_345_678_901
    message = frame_message(stamp_ns, 'wrist "left"', encoded, "jpeg")
    record = {
        "timestamp": {"sec": 12, "nsec": 345_678_901},
        "frame_id": 'wrist "left"',
        "data": base64.b64encode(encoded).decode("ascii"),
        "format": "jpeg",
    }
    assert message == json.dumps(record, separators=(",", ":")).encode()


def test_standard_mcap_reader_sees_header_first_and_all_channels(tmp_path, trial):
    path = tmp_path / "run.mcap"
    write_trial(path, trial)
    with path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        topics = {c.topic: c for c in summary.channels.values()}
        assert set(topics) == {TICK_TOPIC, VISION_TOPIC, EVENT_TOPIC, "/trial/header"}
        names = {}
        for topic, channel in topics.items():
            schema = summary.schemas[channel.schema_id]
            assert channel.message_encoding == "json" and schema.encoding == "jsonschema"
            assert json.loads(schema.data)["type"] == "object"
            names[topic] = schema.name
        assert names[TICK_TOPIC] == "satgrasp.Tick" and names[VISION_TOPIC] == "satgrasp.Vision"
        first = next(reader.iter_messages(log_time_order=False))
        assert first[1].topic == "/trial/header"
        counts = summary.statistics.channel_message_counts
        assert counts[topics[VISION_TOPIC].id] == len(trial.vision)
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    assert metadata[HEADER_METADATA]["seed"] == "7"
    assert json.loads(metadata[HEADER_METADATA]["config"])["approach"]["standoff_m"] == 0.5
    assert metadata[HEADER_METADATA]["format_version"] == "2"
    assert metadata[FOOTER_METADATA]["ticks"] == str(len(trial.ticks))


def test_to_jsonable_converts_nan_numpy_pose_and_dataclasses():
    pose = Pose.from_rpy(0.1, 0.2, 0.3, np.array([1.0, 2.0, 3.0]))
    arm = ArmState(0.5, np.arange(6.0), pose, np.array([0, 0, np.nan, 0, 0, 0]))

    class Health:
        def to_dict(self):
            return {"ok": np.bool_(True)}

    value = {
        "nan": math.nan,
        "inf": -math.inf,
        "f32": np.float32(1.5),
        "i64": np.int64(3),
        "vec": np.array([1.0, np.inf, 2.0]),
        "ints": np.array([[1, 2], [3, 4]], dtype=np.int16),
        "tuple": (1, 2.0, None),
        "rows": [[0.5, math.nan]],
        "pose": pose,
        "arm": arm,
        "path": Path("/tmp/x"),
        "obj": Health(),
        7: "int key",
    }
    out = to_jsonable(value)
    json.dumps(out, allow_nan=False)  # strict JSON
    assert out["nan"] is None and out["inf"] is None
    assert out["f32"] == 1.5 and type(out["i64"]) is int
    assert out["vec"] == [1.0, None, 2.0] and out["ints"] == [[1, 2], [3, 4]]
    assert out["tuple"] == [1, 2.0, None] and out["rows"] == [[0.5, None]]
    assert out["pose"] == pose.matrix.tolist()
    assert out["arm"]["X_BE"] == pose.matrix.tolist() and out["arm"]["V_BE"][2] is None
    assert out["path"] == "/tmp/x" and out["obj"] == {"ok": True} and out["7"] == "int key"
    with pytest.raises(TypeError, match=r"\$\.arm\.extra\[1\]: cannot log a value of type object"):
        to_jsonable({"arm": {"extra": [1, object()]}})
    with pytest.raises(TypeError, match="complex128"):
        to_jsonable(np.array([1j]))


def test_write_tick_replaces_an_unserialisable_record_with_an_event(tmp_path, trial):
    path = tmp_path / "bad.mcap"
    arm = trial.ticks[1].arm
    with TrialLogWriter(path, _header()) as writer:
        assert writer.write_tick(trial.ticks[0])
        bad = dataclasses.replace(trial.ticks[1], arm=dataclasses.replace(arm, fault=object()))
        assert writer.write_tick(bad) is False
        assert writer.write_tick("not a record") is False
        assert writer.write_tick(trial.vision[0]) is False  # a record of the other channel
        assert writer.write_vision(trial.ticks[2]) is False
        result = trial.vision[1]
        odd = dataclasses.replace(result, measurement={"system": "corners"})
        assert writer.write_vision(odd) is False
        assert writer.write_vision(result) and writer.write_tick(trial.ticks[2])
    log = TrialLog.open(path)
    assert [t.tick for t in log.ticks()] == [0, 2]
    assert [(r.system, r.seq) for r in log.vision()] == [(result.system, result.seq)]
    messages = [e["message"] for e in log.events() if e["kind"] == "log"]
    expected = [  # one event each (in the log's time order: a record's event carries its t)
        "tick 1 not logged: tick.arm.fault: cannot write a object",
        "tick record not logged: expected a TickRecord; got str",
        "tick record not logged: expected a TickRecord; got VisionRecord",
        "vision record not logged: expected a VisionRecord; got TickRecord",
        f"vision result {result.system} frame {result.seq} not logged: "
        "vision.measurement: cannot write a dict",
    ]
    assert len(messages) == 5
    for text in expected:
        assert sum(m.startswith(text) for m in messages) == 1, (text, messages)
    assert log.footer["replaced"] == "5"


def test_write_tick_keeps_a_record_that_breaks_the_schema_and_says_why(tmp_path, trial):
    """Written anyway, with a log event naming the problems; reading skips what does not read
    back as a record and says which."""
    path = tmp_path / "schema.mcap"
    record = trial.ticks[30]
    broken = dataclasses.replace(
        record,
        phase=None,
        command=CommandRecord(V_BE=np.zeros(5), stop="no"),
    )
    with TrialLogWriter(path, _header()) as writer:
        assert writer.write_tick(record)
        assert writer.write_tick(broken) is False
        assert writer.write_tick(dataclasses.replace(record, tick=31))
    log = TrialLog.open(path)
    assert log.footer["invalid_ticks"] == "1"
    (event,) = log.events()
    assert event["kind"] == "log" and "tick 30 does not match the tick schema" in event["message"]
    assert "$.phase: expected string, got null" in event["message"]
    assert "$.command.V_BE: 5 items, expected at least 6" in event["message"]
    assert "$.command.stop: expected boolean, got string" in event["message"]
    assert log.tick_count == 3 and [t.tick for t in log.ticks()] == [30, 31]
    assert log.problems == ["tick message 1 skipped: TickRecord.phase: missing value"]


def test_write_event_and_frame_never_raise_for_bad_input(tmp_path):
    path = tmp_path / "ev.mcap"
    with TrialLogWriter(path, _header()) as writer:
        assert writer.write_event(1.0, "fault", "arm", code=np.int32(3), where=np.array([1.0]))
        assert writer.write_event(2.0, "info", "odd data", thing=object()) is False
        assert writer.write_event(math.nan, "info", "no time") is True
        assert writer.write_frame(3.0, np.zeros((4, 4), np.float32)) is False
        assert writer.write_frame(3.0, np.zeros((4, 4), np.uint8), encoding="bmp") is False
    events = list(TrialLog.open(path).events())
    assert events[0]["data"] == {"code": 3, "where": [1.0]}
    assert "cannot log a value of type object" in events[1]["data"]["unserialisable"]
    assert events[2]["t"] == 2.0  # no usable time: the last one
    frame_errors = [e["message"] for e in events if e["message"].startswith("frame not logged")]
    assert "uint8" in frame_errors[0] and "'jpeg' or 'png'" in frame_errors[1]


def test_writer_io_failure_stops_logging_without_raising(tmp_path, trial, monkeypatch):
    writer = TrialLogWriter(tmp_path / "io.mcap", _header())
    assert writer.write_tick(trial.ticks[0])

    def disk_full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(writer._writer, "add_message", disk_full)
    assert writer.write_tick(trial.ticks[1]) is False
    assert "No space left" in writer.error
    assert writer.write_event(1.0, "info", "after failure") is False
    writer.close()
    writer.close()  # idempotent
    assert writer.write_tick(trial.ticks[2]) is False  # after close: dropped, no exception


def test_writer_flushes_on_its_clock_before_the_interval_runs_out(tmp_path, trial):
    """Writes every 0.25 s, interval 1 s: the file is flushed at the last write before a record
    would have waited 1 s unflushed, i.e. every 0.75 s (the header's flush is at t = 0)."""
    clock = FakeClock()
    path = tmp_path / "clock.mcap"
    writer = TrialLogWriter(path, _header(), flush_interval_s=1.0, clock=clock)
    on_disk = []
    for record in trial.ticks[:12]:
        clock.now += 0.25
        writer.write_tick(record)
        on_disk.append(TrialLog.open(path).tick_count)
    assert TrialLog.open(path).header["seed"] == 42
    assert on_disk == [0, 0, 3, 3, 3, 6, 6, 6, 9, 9, 9, 12]
    assert writer.flush_count == 5  # the header's and four
    writer.close()
    with pytest.raises(ValueError, match="flush_interval_s"):
        TrialLogWriter(tmp_path / "x.mcap", _header(), flush_interval_s=0)


def test_writer_rejects_a_bad_header_before_the_trial(tmp_path):
    path = tmp_path / "h.mcap"
    with pytest.raises(ValueError, match="needs 'config'"):
        TrialLogWriter(path, {"seed": 1})
    with pytest.raises(ValueError, match="needs 'seed'"):
        TrialLogWriter(path, {"config": {}})
    with pytest.raises(ValueError, match="host are filled in by the writer"):
        TrialLogWriter(path, {**_header(), "host": "me"})
    with pytest.raises(ValueError, match=r"header\.config\.camera: cannot log"):
        TrialLogWriter(path, {"config": {"camera": object()}, "seed": 1})
    with pytest.raises(ValueError, match="seed: expected integer or null"):
        TrialLogWriter(path, {"config": {}, "seed": "7"})
    with pytest.raises(TrialLogError, match=r"cannot create trial log .*missing"):
        TrialLogWriter(tmp_path / "missing" / "h.mcap", _header())
    earlier = tmp_path / "earlier.mcap"
    earlier.write_bytes(b"an earlier trial")
    with pytest.raises(TrialLogError, match=r"earlier\.mcap already exists; logs are never"):
        TrialLogWriter(earlier, _header())
    assert earlier.read_bytes() == b"an earlier trial"


def test_open_gives_clear_errors_for_bad_files(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"nowhere\.mcap does not exist"):
        TrialLog.open(tmp_path / "nowhere.mcap")
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    with pytest.raises(TrialLogError, match=r"empty\.mcap is empty"):
        TrialLog.open(empty)
    text = tmp_path / "notes.mcap"
    text.write_text("hello, this is not a log\n")
    with pytest.raises(TrialLogError, match=r"notes\.mcap is not an MCAP file"):
        TrialLog.open(text)
    with pytest.raises(TrialLogError, match="is not a file"):
        TrialLog.open(tmp_path)
    foreign = tmp_path / "foreign.mcap"
    from mcap.writer import Writer

    with foreign.open("wb") as f:
        w = Writer(f)
        w.start()
        channel = w.register_channel(
            "/chatter", "json", w.register_schema("x", "jsonschema", b"{}")
        )
        w.add_message(channel, 0, b"{}", 0)
        w.finish()
    with pytest.raises(TrialLogError, match=r"foreign\.mcap is an MCAP file but not a satgrasp"):
        TrialLog.open(foreign)
    killed_at_start = tmp_path / "early.mcap"
    TrialLogWriter(tmp_path / "whole.mcap", _header()).close()
    killed_at_start.write_bytes((tmp_path / "whole.mcap").read_bytes()[:200])
    with pytest.raises(TrialLogError, match=r"early\.mcap holds no header message: its writer"):
        TrialLog.open(killed_at_start)


def test_truncated_logs_open_as_recovered_prefixes_and_recover_to_valid_files(tmp_path, trial):
    """A log cut anywhere (as by a crash) opens with every tick of its complete chunks, in
    order from the first; ``recover`` rewrites it as a file the standard reader accepts."""
    clock = FakeClock()
    path = tmp_path / "full.mcap"
    writer = TrialLogWriter(path, trial.header, flush_interval_s=1.0, clock=clock)
    flushed_at_size = []  # (file size, ticks on disk) after each flush
    for record in trial.ticks:
        clock.now += 0.1
        flushes = writer.flush_count
        writer.write_tick(record)
        if writer.flush_count > flushes:
            flushed_at_size.append((path.stat().st_size, record.tick + 1))
    writer.close()
    data = path.read_bytes()
    rng = np.random.default_rng(3)
    for cut in sorted(rng.integers(flushed_at_size[0][0], len(data) - 30, 4)):
        cut_path = tmp_path / f"cut_{cut}.mcap"
        cut_path.write_bytes(data[:cut])
        log = TrialLog.open(cut_path)
        assert log.recovered and not log.complete and log.stopped
        assert not log.corrupt and log.damage() is None  # a cut-off tail is not corruption
        ticks = [t.tick for t in log.ticks()]
        on_disk = max(n for size, n in flushed_at_size if size <= cut)
        assert ticks == list(range(len(ticks))) and len(ticks) >= on_disk
        fixed = recover(cut_path, tmp_path / f"fixed_{cut}.mcap")
        with fixed.open("rb") as f:
            reader = make_reader(f)
            messages = list(reader.iter_messages(topics=[TICK_TOPIC]))
            assert reader.get_summary().statistics.message_count >= len(ticks) + 1
        assert [json.loads(m[2].data)["tick"] for m in messages] == ticks
        reopened = TrialLog.open(fixed)
        assert (reopened.recovered, reopened.complete) == (False, False)
        assert reopened.recovery["source"] == str(cut_path)
        assert reopened.header == log.header
    with pytest.raises(ValueError, match="not over"):
        recover(path, path)


def test_a_corrupt_chunk_is_passed_over_and_named_and_every_other_record_read(tmp_path, trial):
    path = write_trial(tmp_path / "whole.mcap", trial, trial_clock=True).path  # a chunk a second
    whole = [t.tick for t in TrialLog.open(path).ticks()]
    spans = chunk_spans(path)
    assert len(spans) >= 5
    offset, length = spans[len(spans) // 2]
    log = TrialLog.open(flip_a_byte(path, tmp_path / "bad.mcap", offset + length // 2))
    assert log.corrupt and log.complete and not log.recovered  # the writer did finish it
    ticks = [t.tick for t in log.ticks()]
    lost = sorted(set(whole) - set(ticks))
    assert lost and ticks[-1] == whole[-1]  # the chunks after the bad one were read
    assert lost == list(range(lost[0], lost[-1] + 1))  # one chunk: a run of ticks
    damage = log.damage()
    assert damage.startswith(f"1 unreadable part: chunk at bytes {offset}–{offset + length}, t ")
    assert f"lost with them: {len(lost)} ticks of {len(whole)}" in damage
    assert damage.endswith("; every other record was read")


def test_a_corrupt_record_length_ends_the_read_and_says_how_much_is_left(tmp_path, trial):
    path = write_trial(tmp_path / "whole.mcap", trial, trial_clock=True).path
    offset, _ = chunk_spans(path)[2]
    log = TrialLog.open(flip_a_byte(path, tmp_path / "bad.mcap", offset + 8))  # length's top
    assert log.corrupt and log.recovered
    size = path.stat().st_size
    assert log.stopped.startswith("corrupt record framing (a length of ")
    assert log.stopped.endswith(
        f"at byte {offset}: the {size - offset} bytes after it could not be read"
    )
    assert 0 < log.tick_count < len(trial.ticks)
    assert not log.damage().endswith("every other record was read")


CHILD = """
import dataclasses, sys, time
from hil.logs.triallog import TrialLogWriter
from tests.hil.logs.synthetic_log import make_trial

trial = make_trial(seed=5)
writer = TrialLogWriter(sys.argv[1], trial.header, flush_interval_s=1.0)
start, tick = time.monotonic(), 0
print("started", start, flush=True)
while True:
    now = time.monotonic()  # the same clock as the parent's (CLOCK_MONOTONIC)
    t = now - start
    record = dataclasses.replace(trial.ticks[tick % len(trial.ticks)], t=t, tick=tick)
    if tick % 10 == 0:  # a vision result every 0.1 s
        flushes = writer.flush_count
        writer.write_vision(dataclasses.replace(trial.vision[tick // 10 % len(trial.vision)], t=t))
        if writer.flush_count > flushes:  # flushed before this tick was written
            print("flushed", tick - 1, now, flush=True)
    flushes = writer.flush_count
    writer.write_tick(record)
    if writer.flush_count > flushes:
        print("flushed", tick, now, flush=True)
    tick += 1
    time.sleep(max(0.0, start + tick / 100.0 - time.monotonic()))  # 100 Hz of wall time
"""


@dataclass
class Killed:
    path: Path
    start: float
    kill_time: float
    flushed: list[tuple[int, float]]


@pytest.fixture(scope="module")
def killed_log(tmp_path_factory):
    path = tmp_path_factory.mktemp("kill") / "killed.mcap"
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(path)],
        cwd=REPO,
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )
    flushed = []
    try:
        word, start = child.stdout.readline().split()
        assert word == "started"
        while len(flushed) < 2:
            line = child.stdout.readline()
            assert line.startswith("flushed"), f"child said {line!r}"
            _, tick, when = line.split()
            flushed.append((int(tick), float(when)))
        time.sleep(
            0.9
        )  # shortly before the next flush (about 1 s after the last): near the worst case
        kill_time = time.monotonic()
        os.kill(child.pid, signal.SIGKILL)
    finally:
        child.kill()
        child.wait(timeout=10)
    assert child.returncode == -signal.SIGKILL
    flushed += [(int(t), float(w)) for _, t, w in (line.split() for line in child.stdout)]
    child.stdout.close()
    return Killed(path, float(start), kill_time, flushed)


def test_killed_writer_log_opens_with_every_tick_up_to_the_last_flush(killed_log):
    log = TrialLog.open(killed_log.path)
    assert log.recovered and not log.complete and log.header["seed"] == 5
    ticks = list(log.ticks())
    numbers = [t.tick for t in ticks]
    assert numbers == list(range(len(numbers)))
    last_flushed = max(t for t, _ in killed_log.flushed)
    assert numbers[-1] >= last_flushed
    # Everything written more than 1 s before the kill is in the log (30 ms of slack for the
    # scheduling of a loaded machine).
    newest = killed_log.start + ticks[-1].t
    print(f"kill − newest logged tick: {killed_log.kill_time - newest:.3f} s")
    assert killed_log.kill_time - newest <= 1.0 + 0.03, killed_log.kill_time - newest
    assert ticks[-1].truth is not None and ticks[-1].truth.X_CT is not None
    vision = list(log.vision())
    # A vision record is written before its tick (every tenth): when it set off the last flush,
    # it is in the log and its tick is not.
    last = numbers[-1]
    assert len(vision) in {last // 10 + 1, (last + 1) // 10 + 1} and not log.problems


def test_recover_of_a_killed_log_opens_with_the_standard_reader(killed_log, tmp_path):
    fixed = recover(killed_log.path, tmp_path / "fixed.mcap")
    with fixed.open("rb") as f:
        ticks = [json.loads(m[2].data) for m in make_reader(f).iter_messages(topics=[TICK_TOPIC])]
    log = TrialLog.open(killed_log.path)
    assert ticks == [json.loads(json.dumps(to_json(t))) for t in log.ticks()]
    with fixed.open("rb") as f:
        vision = [
            json.loads(m[2].data) for m in make_reader(f).iter_messages(topics=[VISION_TOPIC])
        ]
    assert vision == [json.loads(json.dumps(to_json(r))) for r in log.vision()] and vision


def test_open_refuses_a_format_1_log_in_one_line(tmp_path):
    path = write_format1_log(tmp_path / "old.mcap")
    with pytest.raises(TrialLogError) as caught:
        TrialLog.open(path)
    message = str(caught.value)
    assert "\n" not in message and message.startswith(f"{path}: trial log format 1, written")
    assert "before the typed records of format 2" in message and "2026-11-20" in message
    assert message.endswith("re-run the trial to analyse it")
    assert recover(path, tmp_path / "copy.mcap").exists()  # recovery works on any format


def test_write_tick_of_a_diverged_pose_keeps_the_tick_with_nan(tmp_path, trial):
    record = trial.ticks[120]
    X = np.array(record.estimate.X_CT.matrix)
    X[0, 3] = math.nan
    diverged = dataclasses.replace(
        record,
        estimate=dataclasses.replace(record.estimate, X_CT=Pose.unchecked(X[:3, :3], X[:3, 3])),
    )
    with TrialLogWriter(tmp_path / "nan.mcap", _header()) as writer:
        assert writer.write_tick(diverged) is False  # written, with a schema event
    log = TrialLog.open(tmp_path / "nan.mcap")
    (tick,) = log.ticks()
    assert math.isnan(tick.estimate.X_CT.p[0]) and tick.estimate.X_CT.p[2] == X[2, 3]
    (event,) = log.events()
    assert "$.estimate.X_CT[0][3]: expected number, got null" in event["message"]
