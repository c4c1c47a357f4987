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
from hil.logs.triallog import (
    EVENT_TOPIC,
    FOOTER_METADATA,
    HEADER_METADATA,
    TICK_TOPIC,
    TrialLog,
    TrialLogError,
    TrialLogWriter,
    recover,
    to_jsonable,
)
from tests.hil.logs.synthetic_log import make_trial, synthetic_frame, write_trial

REPO = Path(__file__).resolve().parents[2]


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


def test_writer_round_trip_header_ticks_events_frames(tmp_path, trial):
    path = tmp_path / "run.mcap"
    writer = write_trial(path, trial, frames_every=50)
    assert writer.error is None and writer.counts["invalid_ticks"] == 0
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
        assert read == json.loads(json.dumps(to_jsonable(written)))
    assert ticks[40]["truth"]["X_CT"] == trial.ticks[40]["truth"]["X_CT"].to_list()
    events = list(log.events())
    assert [e["message"] for e in events] == [e[2] for e in sorted(trial.events)]
    assert events[0] == {
        "t": pytest.approx(0.5),
        "kind": "phase",
        "message": "idle → acquire",
        "data": {"from": "idle", "to": "acquire"},
    }
    frames = list(log.frames())
    assert [f.t for f in frames] == pytest.approx([r["t"] for r in trial.ticks[::50]], abs=1e-9)
    expected = synthetic_frame(trial.ticks[50]["range_m"])
    assert np.abs(frames[1].image().astype(int) - expected).mean() < 2.0  # JPEG, lossy
    assert log.footer["ticks"] == str(len(trial.ticks))


def test_frames_png_is_lossless_and_colour_survives(tmp_path):
    rng = np.random.default_rng(1)
    colour = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
    with TrialLogWriter(tmp_path / "f.mcap", _header()) as writer:
        assert writer.write_frame(0.25, colour, encoding="png", frame_id="wrist")
    (frame,) = TrialLog.open(tmp_path / "f.mcap").frames()
    assert (frame.t, frame.format, frame.frame_id) == (0.25, "png", "wrist")
    assert np.array_equal(frame.image(), colour)


def test_standard_mcap_reader_sees_header_first_and_all_channels(tmp_path, trial):
    path = tmp_path / "run.mcap"
    write_trial(path, trial)
    with path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        topics = {c.topic: c for c in summary.channels.values()}
        assert {TICK_TOPIC, EVENT_TOPIC, "/trial/header"} <= set(topics)
        for channel in topics.values():
            schema = summary.schemas[channel.schema_id]
            assert channel.message_encoding == "json" and schema.encoding == "jsonschema"
            assert json.loads(schema.data)["type"] == "object"
        first = next(reader.iter_messages(log_time_order=False))
        assert first[1].topic == "/trial/header"
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    assert metadata[HEADER_METADATA]["seed"] == "7"
    assert json.loads(metadata[HEADER_METADATA]["config"])["sequencer"]["standoff_m"] == 0.5
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
    with TrialLogWriter(path, _header()) as writer:
        assert writer.write_tick(trial.ticks[0])
        bad = {**trial.ticks[1], "arm": {**trial.ticks[1]["arm"], "driver": object()}}
        assert writer.write_tick(bad) is False
        assert writer.write_tick("not a record") is False
        assert writer.write_tick(trial.ticks[2])
    log = TrialLog.open(path)
    assert [t["tick"] for t in log.ticks()] == [0, 2]
    messages = [e["message"] for e in log.events() if e["kind"] == "log"]
    assert len(messages) == 2
    assert "tick 1 not logged" in messages[0] and "tick.arm.driver" in messages[0]
    assert "must be a mapping" in messages[1]
    assert log.footer["replaced"] == "2"


def test_write_tick_keeps_a_record_that_breaks_the_schema_and_says_why(tmp_path, trial):
    path = tmp_path / "schema.mcap"
    record = {**trial.ticks[30], "phase": "cruise", "extra_key": {"anything": 1}}
    del record["command"]
    with TrialLogWriter(path, _header()) as writer:
        assert writer.write_tick({**trial.ticks[30], "extra_key": [1, 2]})  # extra keys: fine
        assert writer.write_tick(record) is False
    log = TrialLog.open(path)
    ticks = list(log.ticks())
    assert len(ticks) == 2 and ticks[1]["phase"] == "cruise" and ticks[0]["extra_key"] == [1, 2]
    (event,) = log.events()
    assert event["kind"] == "log" and "tick 30 does not match the tick schema" in event["message"]
    assert "'cruise' is not one of" in event["message"] and "missing 'command'" in event["message"]


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
            flushed_at_size.append((path.stat().st_size, record["tick"] + 1))
    writer.close()
    data = path.read_bytes()
    rng = np.random.default_rng(3)
    for cut in sorted(rng.integers(flushed_at_size[0][0], len(data) - 30, 4)):
        cut_path = tmp_path / f"cut_{cut}.mcap"
        cut_path.write_bytes(data[:cut])
        log = TrialLog.open(cut_path)
        assert log.recovered and not log.complete and log.stopped
        ticks = [t["tick"] for t in log.ticks()]
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


CHILD = """
import sys, time
from hil.logs.triallog import TrialLogWriter
from tests.hil.logs.synthetic_log import make_trial

trial = make_trial(seed=5)
writer = TrialLogWriter(sys.argv[1], trial.header, flush_interval_s=1.0)
start, tick = time.monotonic(), 0
print("started", flush=True)
while True:
    record = dict(trial.ticks[tick % len(trial.ticks)])
    now = time.monotonic()
    record.update(t=now - start, tick=tick, wall=now)
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
        assert child.stdout.readline().strip() == "started"
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
    return Killed(path, kill_time, flushed)


def test_killed_writer_log_opens_with_every_tick_up_to_the_last_flush(killed_log):
    log = TrialLog.open(killed_log.path)
    assert log.recovered and not log.complete and log.header["seed"] == 5
    ticks = list(log.ticks())
    numbers = [t["tick"] for t in ticks]
    assert numbers == list(range(len(numbers)))
    last_flushed = max(t for t, _ in killed_log.flushed)
    assert numbers[-1] >= last_flushed
    # Everything written more than 1 s before the kill is in the log (30 ms of slack for the
    # scheduling of a loaded machine).
    newest = ticks[-1]["wall"]
    print(f"kill − newest logged tick: {killed_log.kill_time - newest:.3f} s")
    assert killed_log.kill_time - newest <= 1.0 + 0.03, killed_log.kill_time - newest
    assert ticks[-1]["measurements"] and ticks[-1]["truth"]["X_CT"]


def test_recover_of_a_killed_log_opens_with_the_standard_reader(killed_log, tmp_path):
    fixed = recover(killed_log.path, tmp_path / "fixed.mcap")
    with fixed.open("rb") as f:
        ticks = [json.loads(m[2].data) for m in make_reader(f).iter_messages(topics=[TICK_TOPIC])]
    original = list(TrialLog.open(killed_log.path).ticks())
    assert ticks == original
