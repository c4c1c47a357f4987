"""The track and gripper on I/O threads (``drivers.threaded_io``): the control side never waits
on a round trip, yet every failure still reaches it, stops are sent at once and win over
posted moves, and a track left moving by a silent control loop is stopped."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from drivers import threaded_io
from drivers.base import DeviceError, DeviceFault, DeviceTimeout, Gripper, Track
from drivers.gripper_robotiq import RobotiqGripper, RobotiqRegisters
from drivers.modbus_link import registers_to_int32
from drivers.threaded_io import DeviceIo, ThreadedGripper, ThreadedTrack, stale_after
from drivers.track_modbus import ModbusTrack
from tests.drivers.register_fakes import RecordingLink
from tests.drivers.test_track_modbus import R, limits_image, status_image

PERIOD = 0.005
STALE = stale_after(0.1, PERIOD)


def eventually(condition, timeout_s=2.0):
    """Wait for ``condition()`` to hold (the I/O thread runs on its own time)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(PERIOD / 2)
    return False


def threaded_track(**options):
    link = RecordingLink(limits_image() | status_image())
    options = {"period_s": PERIOD, "stale_after_s": STALE} | options
    track = ThreadedTrack(ModbusTrack(link), **options)
    track.connect()
    track.activate()
    link.writes.clear()
    return link, track


def threaded_gripper():
    link = RecordingLink()
    gripper = ThreadedGripper(RobotiqGripper(link), period_s=PERIOD, stale_after_s=STALE)
    gripper.connect()
    return link, gripper


@pytest.fixture
def track():
    link, track = threaded_track()
    yield link, track
    track.close()


def velocity_writes(link):
    return [values for address, values in link.writes if values[1] == R.MODE_VELOCITY]


def sent_velocity(words) -> float:
    return registers_to_int32(words[R.TARGET_VELOCITY], words[R.TARGET_VELOCITY + 1]) / 1e6


def test_threaded_devices_implement_their_protocols(track):
    _, threaded = track
    assert isinstance(threaded, Track)
    assert isinstance(
        ThreadedGripper(RobotiqGripper(RecordingLink()), period_s=PERIOD, stale_after_s=STALE),
        Gripper,
    )
    assert (threaded.travel_min, threaded.travel_max) == (-0.5, 2.05)
    assert (threaded.max_speed, threaded.max_acceleration) == (0.25, 0.5)


def test_threaded_track_state_follows_the_device_without_a_read_per_call(track):
    link, threaded = track
    link.inputs.update(status_image(R.ST_MOVING, position=0.5, velocity=0.1))
    assert eventually(lambda: threaded.state().position == pytest.approx(0.5))
    reads = []
    link.read_input = lambda *a, _read=link.read_input: reads.append(a) or _read(*a)
    before = len(reads)
    for _ in range(100):
        assert threaded.state().velocity == pytest.approx(0.1)
    assert len(reads) - before < 50  # the thread's reads, not one per call


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_threaded_track_refuses_a_velocity_at_once_on_both_signs(track, sign):
    link, threaded = track
    with pytest.raises(ValueError, match=r"outside ±0\.25 m/s"):
        threaded.move_velocity(sign * 0.26)
    threaded.move_velocity(sign * 0.25)
    assert eventually(lambda: velocity_writes(link))
    assert sent_velocity(velocity_writes(link)[-1]) == sign * 0.25


def test_threaded_track_refuses_motion_before_activation():
    link = RecordingLink(limits_image() | status_image())
    threaded = ThreadedTrack(ModbusTrack(link), period_s=PERIOD, stale_after_s=STALE)
    threaded.connect()
    try:
        with pytest.raises(DeviceError, match="not active"):
            threaded.move_velocity(0.1)
        time.sleep(5 * PERIOD)
        assert link.writes == []
    finally:
        threaded.close()


def test_threaded_track_sends_the_newest_velocity_and_repeats_an_unchanged_one_rarely(track):
    link, threaded = track
    for v in (0.01, 0.02, 0.03):
        threaded.move_velocity(v)
    assert eventually(lambda: velocity_writes(link))
    time.sleep(3 * PERIOD)
    sent = [sent_velocity(w) for w in velocity_writes(link)]
    assert sent[-1] == 0.03 and 0.01 not in sent[1:]  # older posts were replaced
    count, start = len(sent), time.monotonic()
    for _ in range(10):  # the same velocity every control tick
        threaded.move_velocity(0.03)
        time.sleep(0.002)
    resends = (time.monotonic() - start) / threaded.resend_s + 1
    assert len(velocity_writes(link)) - count <= resends


def test_threaded_track_stop_is_sent_at_once_and_wins_over_a_posted_move(track):
    link, threaded = track
    threaded.move_velocity(0.2)
    threaded.stop()
    assert link.writes and link.writes[-1][1][1] == R.MODE_STOP  # sent before stop() returned
    time.sleep(5 * PERIOD)
    stop_at = max(i for i, (_, w) in enumerate(link.writes) if w[1] == R.MODE_STOP)
    assert all(w[1] != R.MODE_VELOCITY for _, w in link.writes[stop_at:])


def test_threaded_track_reports_a_failed_read_and_recovers(track):
    link, threaded = track
    link.unreadable = DeviceTimeout("recording link: no reply within 0.1 s")
    assert eventually(lambda: _raises(threaded.state, DeviceTimeout))
    link.unreadable = None
    assert eventually(lambda: not _raises(threaded.state, DeviceError))


def test_threaded_track_reports_a_refused_command_once(track):
    link, threaded = track
    link.refuse = DeviceError("recording link: exception 4")
    threaded.move_velocity(0.1)
    assert eventually(lambda: _raises(threaded.state, DeviceError))
    link.refuse = None
    assert not _raises(threaded.state, DeviceError)  # reported once, the reads are fine


def test_threaded_track_reports_a_stuck_thread_as_a_timeout():
    link = RecordingLink(limits_image() | status_image())
    threaded = ThreadedTrack(ModbusTrack(link), period_s=PERIOD, stale_after_s=0.05)
    threaded.connect()
    release = threading.Event()
    read = link.read_input
    link.read_input = lambda *a: release.wait(5) and read(*a)
    try:
        with pytest.raises(DeviceTimeout, match=r"no status for 0\.(0[5-9]|[1-9])"):
            time.sleep(0.1)
            threaded.state()
    finally:
        release.set()
        threaded.close()


def test_threaded_track_stops_itself_when_the_loop_stops_commanding_a_motion():
    link, threaded = threaded_track(command_timeout_s=0.03)
    try:
        threaded.move_velocity(0.1)
        assert eventually(lambda: velocity_writes(link))
        errors = []
        assert eventually(lambda: _raises(threaded.state, DeviceFault, errors), timeout_s=1.0)
        assert "no command from the control loop" in str(errors[0])
        assert link.writes[-1][1][1] == R.MODE_STOP
    finally:
        threaded.close()


def test_threaded_track_is_not_stopped_while_the_loop_keeps_commanding():
    link, threaded = threaded_track(command_timeout_s=0.3)
    try:
        for _ in range(80):  # 0.8 s of 10 ms ticks: well past the limit in all
            threaded.move_velocity(0.1)
            threaded.state()
            time.sleep(0.01)
        assert all(w[1] == R.MODE_VELOCITY for _, w in link.writes)
        threaded.move_velocity(0.0)  # at rest, silence is no fault
        time.sleep(0.4)
        threaded.state()
    finally:
        threaded.close()


def test_threaded_track_reports_any_exception_of_its_thread_as_a_device_error(track):
    link, threaded = track

    def broken(*_):
        raise ZeroDivisionError("bad decode")

    link.read_input = broken
    assert eventually(lambda: _raises(threaded.state, DeviceError))
    with pytest.raises(DeviceError, match="recording link: ZeroDivisionError: bad decode"):
        threaded.state()


def test_threaded_track_close_ends_the_thread_and_closes_the_link():
    link, threaded = threaded_track()
    threaded.close()
    assert link.closed
    assert not any(t.name == "recording link-io" for t in threading.enumerate())


def test_threaded_track_connect_fails_on_a_device_that_does_not_answer():
    link = RecordingLink(limits_image())
    threaded = ThreadedTrack(ModbusTrack(link), period_s=PERIOD, stale_after_s=STALE)
    read = link.read_input

    def status_unreadable(address, count):
        if address == R.STATUS:
            raise DeviceTimeout("recording link: no reply")
        return read(address, count)

    link.read_input = status_unreadable
    with pytest.raises(DeviceTimeout, match="no reply"):
        threaded.connect()


def test_threaded_gripper_posts_finger_commands_and_reads_its_status():
    link, gripper = threaded_gripper()
    try:
        gripper.grip()
        assert eventually(lambda: link.writes)
        assert link.writes[-1][0] == RobotiqRegisters.OUTPUT
        link.inputs[RobotiqRegisters.INPUT] = 0b11 << (8 + RobotiqRegisters.gSTA_SHIFT)
        assert eventually(lambda: gripper.state().activated)
    finally:
        gripper.close()
    assert link.closed


@pytest.mark.parametrize(
    ("period", "stale", "match"),
    [(0.0, 0.1, "period must be positive"), (0.01, 0.01, "must exceed the period")],
)
def test_device_io_refuses_a_bad_period(period, stale, match):
    with pytest.raises(ValueError, match=match):
        DeviceIo("dev", lambda: None, period_s=period, stale_after_s=stale)


def _raises(call, kind, caught: list | None = None) -> bool:
    try:
        call()
    except kind as exc:
        if caught is not None:
            caught.append(exc)
        return True
    return False


# --- from the mutation run's survivors (docs/faults.md) ------------------------------------------


def test_stale_limit_is_two_time_outs_and_two_periods():
    assert stale_after(0.1, 0.01) == pytest.approx(0.22)
    assert stale_after(0.5, 0.02) == pytest.approx(1.04)


def test_threaded_track_documented_defaults():
    _, threaded = threaded_track()
    try:
        assert (threaded.command_timeout_s, threaded.resend_s) == (0.1, 0.05)
    finally:
        threaded.close()


def test_threaded_track_sends_the_first_command_even_if_it_is_zero(track):
    link, threaded = track
    threaded.move_velocity(0.0)
    assert eventually(lambda: velocity_writes(link))


def test_threaded_track_synchronous_calls_reach_the_device_before_returning(track):
    link, threaded = track
    threaded.move_to(0.5, 0.1)
    assert link.writes[-1][1][1] == R.MODE_POSITION
    assert sent_velocity(link.writes[-1][1]) == 0.0
    threaded.deactivate()
    assert link.writes[-1][1][:2] == [0, R.MODE_STOP]  # drive power off
    with pytest.raises(DeviceError, match="not active"):
        threaded.move_velocity(0.1)


def test_threaded_track_after_a_stop_silence_is_no_fault():
    link, threaded = threaded_track(command_timeout_s=0.03)
    try:
        threaded.move_velocity(0.1)
        threaded.stop()
        time.sleep(0.15)
        threaded.state()  # no "no command from the control loop"
        assert [w[1] for _, w in link.writes].count(R.MODE_STOP) == 1
    finally:
        threaded.close()


def test_threaded_track_watchdog_stops_once_and_reports_once():
    link, threaded = threaded_track(command_timeout_s=0.03)
    try:
        threaded.move_velocity(0.1)
        assert eventually(lambda: _raises(threaded.state, DeviceFault), timeout_s=1.0)
        time.sleep(0.1)
        threaded.state()
        assert [w[1] for _, w in link.writes].count(R.MODE_STOP) == 1
    finally:
        threaded.close()


def test_device_io_thread_is_a_named_daemon_and_close_before_connect_is_harmless():
    ThreadedTrack(ModbusTrack(RecordingLink()), period_s=PERIOD, stale_after_s=STALE).close()
    _, threaded = threaded_track()
    try:
        (io,) = [t for t in threading.enumerate() if t.name == "recording link-io"]
        assert io.daemon  # a stuck device must not keep the program from exiting
    finally:
        threaded.close()


def test_device_io_close_does_not_wait_forever_on_a_stuck_device(monkeypatch):
    monkeypatch.setattr(threaded_io, "_JOIN_S", 0.1)
    release = threading.Event()
    calls = []
    io = DeviceIo(
        "dev",
        lambda: calls.append(1) or (len(calls) > 1 and release.wait(5)),
        period_s=PERIOD,
        stale_after_s=STALE,
    )
    io.start()
    assert eventually(lambda: len(calls) > 1)
    start = time.monotonic()
    io.stop()
    assert time.monotonic() - start < 1.0
    release.set()


def test_device_io_staleness_on_its_own_clock_and_limit_inclusive():
    now = [0.0]
    release = threading.Event()
    calls = []

    def read():
        calls.append(now[0])
        if len(calls) > 1:
            release.wait(5)  # stuck from the second read on
        return "state"

    io = DeviceIo("dev", read, period_s=PERIOD, stale_after_s=0.5, clock=lambda: now[0])
    io.start()
    try:
        assert eventually(lambda: len(calls) > 1)
        now[0] = 0.5
        assert io.latest() == "state"  # exactly at the limit: still fresh
        now[0] = 0.5001
        with pytest.raises(DeviceTimeout, match=r"dev: no status for 0\.500 s"):
            io.latest()
    finally:
        release.set()
        io.stop()


def test_device_io_keeps_its_period_and_recovers_from_a_slow_round_trip():
    calls = []

    def read():
        calls.append(time.monotonic())
        if len(calls) == 3:
            time.sleep(0.15)  # one round trip three periods long
        return len(calls)

    io = DeviceIo("dev", read, period_s=0.05, stale_after_s=1.0)
    io.start()
    try:
        time.sleep(0.5)
    finally:
        io.stop()
    assert 6 <= len(calls) <= 10, len(calls)  # ~0.35 s of 0.05 s periods; no busy loop
    gaps = np.diff(calls)
    assert gaps[3] < 0.2 + 0.05  # the next read right after the slow one, not a second later
    assert np.all(gaps[4:] > 0.03)  # and no burst catching up


def test_device_io_names_the_device_in_a_command_failure():
    io = DeviceIo("dev", lambda: "state", period_s=PERIOD, stale_after_s=STALE)
    io.start()
    try:
        io.post(lambda: 1 / 0)
        caught = []
        assert eventually(lambda: _raises(io.latest, DeviceError, caught))
        assert str(caught[0]) == "dev: ZeroDivisionError: division by zero"
    finally:
        io.stop()


def test_threaded_gripper_synchronous_and_posted_commands():
    link, gripper = threaded_gripper()
    try:
        gripper.activate()
        assert len(link.writes) == 2  # reset, then activation request: both sent before return
        gripper.deactivate()
        gripper.open()
        assert eventually(lambda: len(link.writes) == 3)
        link.unreadable = DeviceTimeout("gateway silent")
        caught = []
        assert eventually(lambda: _raises(gripper.state, DeviceTimeout, caught))
        assert "gateway silent" in str(caught[0])
    finally:
        gripper.close()
