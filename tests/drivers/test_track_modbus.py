"""The track driver through the real pymodbus client against the real pymodbus server on
127.0.0.1 (each test starts and stops its own server); and the real track when SATGRASP_TRACK is
set (hardware)."""

import math
import socket
import threading
import time

import numpy as np
import pytest

from configuration.rig import load_rig
from drivers.base import DeviceError, DeviceFault, DeviceTimeout, Track
from drivers.modbus_link import int32_to_registers
from drivers.track_modbus import ModbusTrack, TrackRegisters, describe_faults
from sim_backends.modbus_server import ModbusDeviceServer
from sim_backends.track import TrackModel
from tests.drivers.hardware import modbus_address, needs
from tests.drivers.register_fakes import RecordingLink

CONFIG = load_rig().track


@pytest.fixture
def served_track():
    model = TrackModel(CONFIG)
    with ModbusDeviceServer({7: model}) as server:
        track = ModbusTrack.over_tcp("127.0.0.1", server.port, device_id=7, timeout_s=1.0)
        track.connect()
        track.activate()
        yield model, track, server
        track.close()


def run(model, track, seconds, period=0.05):
    state = None
    for _ in range(round(seconds / period)):
        model.step(period)
        state = track.state()
    return state


def test_modbus_track_implements_track_protocol(served_track):
    _, track, _ = served_track
    assert isinstance(track, Track)
    assert (track.travel_min, track.travel_max) == (CONFIG.travel_min, CONFIG.travel_max)
    assert track.max_speed == CONFIG.max_speed
    assert track.max_acceleration == CONFIG.max_acceleration


def test_modbus_track_moves_to_position_and_runs_at_velocity(served_track):
    model, track, _ = served_track
    track.move_to(0.5, 0.25)
    state = run(model, track, 3.5)
    assert state.position == pytest.approx(0.5, abs=1e-6)
    assert not state.moving and state.fault is None
    track.move_velocity(0.15)
    state = run(model, track, 1.0)
    assert state.velocity == pytest.approx(0.15, abs=1e-6) and state.moving
    track.stop()
    state = run(model, track, 1.0)
    assert state.velocity == 0.0 and not state.moving
    assert model.position == pytest.approx(state.position, abs=1e-6)


def test_modbus_track_soft_limit_sets_fault_bits_and_state_fault(served_track):
    model, track, _ = served_track
    track.move_to(CONFIG.travel_max, 0.25)
    run(model, track, 10.0)
    track.move_velocity(0.1)  # past the max soft limit
    state = run(model, track, 1.0)
    assert state.fault == "soft limit max crossed"
    regs = track.link.read_input(TrackRegisters.STATUS, 2)
    assert regs[0] & TrackRegisters.ST_FAULT
    assert regs[1] == TrackRegisters.FAULT_SOFT_LIMIT_MAX
    with pytest.raises(DeviceFault, match="refused the position command: soft limit max"):
        track.move_to(1.0, 0.1)
    track.reset_fault()
    track.move_to(1.0, 0.25)
    state = run(model, track, 6.0)
    assert state.fault is None and state.position == pytest.approx(1.0, abs=1e-6)


def test_modbus_track_reconnects_after_server_restart(served_track):
    model, track, server = served_track
    track.move_to(0.2, 0.2)
    run(model, track, 0.5)
    server.stop()
    with pytest.raises(DeviceError, match="link dropped") as error:
        track.state()
    assert not isinstance(error.value, DeviceTimeout)  # refused, not silent
    assert f"127.0.0.1:{server.port}" in str(error.value)
    server.start()  # same model, same port: as if the controller came back
    state = track.state()  # the driver reconnects by itself
    assert state.position == pytest.approx(model.position)
    track.move_to(0.3, 0.2)
    assert run(model, track, 2.0).position == pytest.approx(0.3, abs=1e-6)


def test_modbus_track_clear_error_when_nothing_listens():
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]  # free once the probe closes
    track = ModbusTrack.over_tcp("127.0.0.1", port, timeout_s=0.5)
    with pytest.raises(DeviceError, match=f"127.0.0.1:{port}.*nothing accepts connections"):
        track.connect()


def test_modbus_track_times_out_on_a_silent_device():
    # a TCP peer that accepts and never answers: the request must time out, not hang
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(1)
    accepted = []
    thread = threading.Thread(target=lambda: accepted.append(listener.accept()), daemon=True)
    thread.start()
    try:
        track = ModbusTrack.over_tcp("127.0.0.1", listener.getsockname()[1], timeout_s=0.3)
        with pytest.raises(DeviceTimeout, match=r"no reply within 0\.3 s"):
            track.connect()
    finally:
        thread.join(2.0)
        for connection, _ in accepted:
            connection.close()
        listener.close()


def test_modbus_track_wrong_device_id_is_a_silent_device():
    model = TrackModel(CONFIG)
    with ModbusDeviceServer({1: model}) as server:
        track = ModbusTrack.over_tcp("127.0.0.1", server.port, device_id=5, timeout_s=0.5)
        with pytest.raises(DeviceTimeout, match=r"device 5.*exception 11"):
            track.connect()


def test_describe_faults_names_every_bit():
    assert describe_faults(0) is None
    both = TrackRegisters.FAULT_SOFT_LIMIT_MIN | TrackRegisters.FAULT_WATCHDOG
    assert describe_faults(both) == (
        "soft limit min crossed; communication watchdog (no request in time)"
    )
    assert "unknown fault bits 0x0100" in describe_faults(0x0100)


def test_modbus_track_served_while_the_world_steps_in_another_thread():
    # the server thread reads registers while another thread steps the model: every sample
    # must be a consistent snapshot (position and velocity from the same control cycle)
    model = TrackModel(CONFIG.model_copy(update={"travel_max": 1000.0}))
    stop = threading.Event()

    def world():
        while not stop.is_set():
            model.step(0.004)
            time.sleep(0.0002)

    with ModbusDeviceServer({1: model}) as server:
        track = ModbusTrack.over_tcp("127.0.0.1", server.port, timeout_s=1.0)
        track.connect()
        track.activate()
        track.move_velocity(0.2)
        stepper = threading.Thread(target=world, daemon=True)
        stepper.start()
        try:
            samples = [track.state() for _ in range(300)]
        finally:
            stop.set()
            stepper.join(2.0)
        track.close()
    assert np.all(np.diff([s.position for s in samples]) >= 0.0)
    assert samples[-1].position > samples[0].position
    for s in samples:  # on the ramp x = v²/2a (exact for the model's integration), then cruise
        assert s.fault is None
        expected = min(0.2, (2 * CONFIG.max_acceleration * s.position) ** 0.5)
        assert s.velocity == pytest.approx(expected, abs=0.003)


def test_modbus_track_moves_only_while_active_and_deactivate_removes_power(served_track):
    model, track, _ = served_track
    track.deactivate()
    with pytest.raises(DeviceError, match="not active"):
        track.move_velocity(0.1)
    with pytest.raises(DeviceError, match="not active"):
        track.move_to(0.5, 0.1)
    track.stop()  # a stop is always accepted
    track.activate()
    track.move_velocity(0.1)
    run(model, track, 0.5)
    assert track.state().velocity == pytest.approx(0.1, abs=1e-3)
    track.deactivate()
    final = run(model, track, 1.0)
    assert final.velocity == 0.0 and not final.moving


# --- the driver's encodings, word by word (in-process) ----------------------------------------

R = TrackRegisters


def limits_image(travel=(-0.5, 2.05), speed=0.25, acceleration=0.5) -> dict[int, int]:
    values = [*travel, speed, acceleration]
    image = {}
    for i, value in enumerate(values):
        high, low = int32_to_registers(round(value * 1e6))
        image[R.SOFT_LIMIT_MIN + 2 * i], image[R.SOFT_LIMIT_MIN + 2 * i + 1] = high, low
    return image


def recording_track(active=True, **limits):
    link = RecordingLink(limits_image(**limits))
    track = ModbusTrack(link, clock=lambda: 7.25)
    track.connect()
    if active:
        track.activate()
    return link, track


def block(mode, *, control=R.CTRL_ENABLE, position=0.0, speed=0.0, velocity=0.0, beat=1):
    words = [control, mode]
    for value in (position, speed, velocity):
        words += int32_to_registers(round(value * 1e6))
    return (R.CONTROL, [*words, beat])


def test_modbus_track_connect_reads_the_limits_with_their_signs():
    link, track = recording_track(active=False, travel=(-0.5, 2.05))
    assert link.connected and link.writes == []
    assert (track.travel_min, track.travel_max) == (-0.5, 2.05)
    assert (track.max_speed, track.max_acceleration) == (0.25, 0.5)


@pytest.mark.parametrize(
    ("travel", "speed"), [((1.0, 1.0), 0.25), ((2.0, 1.0), 0.25), ((0.0, 1.0), 0.0), ((0, 1), -0.1)]
)
def test_modbus_track_connect_refuses_implausible_limits(travel, speed):
    link = RecordingLink(limits_image(travel=travel, speed=speed))
    with pytest.raises(DeviceError, match="recording link: implausible limits read from the track"):
        ModbusTrack(link).connect()


def test_modbus_track_commands_write_one_whole_block():
    link, track = recording_track()
    track.move_velocity(-0.125)
    track.move_to(1.5, 0.2)
    track.stop()
    track.reset_fault()
    track.deactivate()
    assert link.writes == [
        block(R.MODE_STOP, beat=1),  # activate: enabled, holding still
        block(R.MODE_VELOCITY, velocity=-0.125, beat=2),
        block(R.MODE_POSITION, position=1.5, speed=0.2, beat=3),
        block(R.MODE_STOP, beat=4),
        block(R.MODE_STOP, control=R.CTRL_ENABLE | R.CTRL_FAULT_RESET, beat=5),
        block(R.MODE_STOP, control=0, beat=6),  # deactivate removes drive power
    ]


def test_modbus_track_heartbeat_wraps():
    link, track = recording_track()
    track._heartbeat = 0xFFFE
    track.stop()
    track.stop()
    assert [w[1][-1] for w in link.writes[-2:]] == [0xFFFF, 0]


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_modbus_track_velocity_limit_on_both_signs(sign):
    link, track = recording_track()
    track.move_velocity(sign * 0.25)  # the limit itself is allowed
    assert link.writes[-1] == block(R.MODE_VELOCITY, velocity=sign * 0.25, beat=2)
    for bad in (sign * 0.2501, float("nan"), sign * float("inf")):
        with pytest.raises(ValueError, match=r"outside ±0\.25 m/s \(max_speed\)"):
            track.move_velocity(bad)
    assert len(link.writes) == 2  # nothing sent for a refused command


def test_modbus_track_move_to_limits_inclusive():
    link, track = recording_track(travel=(-0.5, 2.05))
    track.move_to(-0.5, 0.25)
    track.move_to(2.05, 1e-6)
    assert [w[1][1] for w in link.writes[1:]] == [R.MODE_POSITION] * 2
    for position in (-0.5001, 2.0501, float("nan")):
        with pytest.raises(ValueError, match=r"outside the travel \[-0\.5, 2\.05\] m"):
            track.move_to(position, 0.1)
    for speed in (0.0, -0.1, 0.2501, float("nan")):
        with pytest.raises(ValueError, match=r"must be in \(0, 0\.25\] m/s"):
            track.move_to(1.0, speed)
    assert len(link.writes) == 3


def test_modbus_track_refuses_motion_until_active_but_always_stops():
    link, track = recording_track(active=False)
    for name, call in (
        ("move_velocity", lambda: track.move_velocity(0.1)),
        ("move_to", lambda: track.move_to(1.0, 0.1)),
    ):
        with pytest.raises(
            DeviceError,
            match=rf"recording link: {name} refused: the track is not active \(call activate\(\)\)",
        ):
            call()
    track.stop()
    assert link.writes == [block(R.MODE_STOP, beat=1)]


def status_image(status=0, faults=0, position=0.0, velocity=0.0):
    image = {R.STATUS: status, R.FAULTS: faults}
    for address, value in ((R.ACTUAL_POSITION, position), (R.ACTUAL_VELOCITY, velocity)):
        image[address], image[address + 1] = int32_to_registers(round(value * 1e6))
    return image


@pytest.mark.parametrize(
    ("status", "faults", "fault"),
    [
        (R.ST_MOVING, 0, None),
        (0, 0, None),
        (R.ST_FAULT, R.FAULT_DRIVE, "drive fault"),
        (R.ST_FAULT, 0, "fault (no fault bits given)"),
        (0, R.FAULT_WATCHDOG, "communication watchdog (no request in time)"),
    ],
)
def test_modbus_track_state_decodes_position_velocity_and_faults(status, faults, fault):
    link, track = recording_track()
    link.inputs.update(status_image(status, faults, position=-0.012345, velocity=-0.2))
    state = track.state()
    assert state.position == pytest.approx(-0.012345, abs=1e-9)
    assert state.velocity == pytest.approx(-0.2, abs=1e-9)
    assert state.moving == bool(status & R.ST_MOVING)
    assert state.fault == fault and state.stamp == 7.25


def test_modbus_track_refused_command_names_the_device_fault():
    link, track = recording_track()
    link.inputs.update(status_image(R.ST_FAULT, R.FAULT_SOFT_LIMIT_MAX))
    link.refuse = DeviceFault("exception 4")
    with pytest.raises(DeviceFault, match="track refused the velocity command: soft limit max"):
        track.move_velocity(0.1)
    link.unreadable = DeviceError("no reply")  # the reason cannot be read: the refusal is named
    with pytest.raises(DeviceFault, match="track refused the stop command: exception 4"):
        track.stop()


def test_modbus_track_close_deactivates_an_active_track_only():
    link, track = recording_track()
    track.close()
    assert link.writes[-1] == block(R.MODE_STOP, control=0, beat=2) and link.closed
    link, track = recording_track(active=False)
    track.close()
    assert link.writes == [] and link.closed
    link, track = recording_track()
    link.refuse = DeviceError("gone")
    track.close()  # a failing deactivation does not keep the link open
    assert link.closed
    with pytest.raises(DeviceError, match="not active"):
        track.move_velocity(0.1)


def test_modbus_track_over_tcp_builds_its_link():
    track = ModbusTrack.over_tcp("127.0.0.9", 5998, 3, timeout_s=0.7)
    link = track.link
    assert (link.host, link.port, link.device_id, link.timeout_s) == ("127.0.0.9", 5998, 3, 0.7)
    default = ModbusTrack.over_tcp("127.0.0.9", 5998)
    assert default.link.device_id == 1 and default.link.timeout_s == 0.5


def test_modbus_track_before_connect_checks_only_the_register_range():
    """Limits are the device's: before ``connect`` has read them the driver refuses nothing
    but what its registers cannot hold (µm and µm/s in 32 bits: ±2147 m)."""
    link = RecordingLink()
    track = ModbusTrack(link)
    limits = (track.travel_min, track.travel_max, track.max_speed, track.max_acceleration)
    assert limits == (-math.inf, math.inf, math.inf, math.inf)
    track.activate()
    track.move_velocity(-3.0)
    track.move_to(-5.0, 4.0)
    assert [w[1][1] for w in link.writes] == [R.MODE_STOP, R.MODE_VELOCITY, R.MODE_POSITION]
    for call, name in (
        (lambda: track.move_velocity(3000.0), "velocity"),
        (lambda: track.move_to(-3000.0, 1.0), "position"),
        (lambda: track.move_to(1.0, 3000.0), "speed"),
    ):
        with pytest.raises(ValueError, match=f"^{name} = .* is out of the register range"):
            call()


def test_modbus_track_over_tcp_passes_its_clock():
    track = ModbusTrack.over_tcp("127.0.0.9", 5998, clock=lambda: 4.5)
    track._link = RecordingLink(status_image())  # the same driver on a recording link
    assert track.state().stamp == 4.5


# --- the real track --------------------------------------------------------------------------
@pytest.mark.hardware
@needs("SATGRASP_TRACK", "track's Modbus TCP address")
def test_real_track_reports_plausible_limits_and_no_fault():
    """Read-only: the axis controller answers, its limits make sense, nothing is latched."""
    host, port, unit = modbus_address("SATGRASP_TRACK", device_id=1)
    track = ModbusTrack.over_tcp(host, port, unit, timeout_s=0.5)
    try:
        track.connect()
        state = track.state()
    finally:
        track.close()
    assert track.travel_min < track.travel_max and 0 < track.max_speed <= 2.0
    assert track.travel_min - 0.01 <= state.position <= track.travel_max + 0.01
    assert state.fault is None, f"the track reports {state.fault}: clear it first"


@pytest.mark.hardware
@needs("SATGRASP_TRACK", "track's Modbus TCP address")
def test_real_track_moves_a_centimetre_and_back():
    """Moves the carriage 1 cm at 2 cm/s and back: keep the track clear."""
    host, port, unit = modbus_address("SATGRASP_TRACK", device_id=1)
    track = ModbusTrack.over_tcp(host, port, unit, timeout_s=0.5)
    track.connect()
    try:
        track.activate()
        start = track.state().position
        target = start + 0.01 if start + 0.01 <= track.travel_max else start - 0.01
        for goal in (target, start):
            track.move_to(goal, 0.02)
            deadline = time.monotonic() + 5.0
            while abs(track.state().position - goal) > 0.001 or track.state().moving:
                assert time.monotonic() < deadline, f"not at {goal} m within 5 s"
                time.sleep(0.05)
    finally:
        track.stop()
        track.close()
