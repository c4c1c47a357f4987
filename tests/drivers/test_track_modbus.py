"""The track driver through the real pymodbus client against the real pymodbus server on
127.0.0.1 (each test starts and stops its own server); and the real track when SATGRASP_TRACK is
set (hardware)."""

import socket
import threading
import time

import numpy as np
import pytest

from configuration.rig import load_rig
from drivers.base import DeviceError, DeviceFault, DeviceTimeout, Track
from drivers.track_modbus import ModbusTrack, TrackRegisters, describe_faults
from sim_backends.modbus_server import ModbusDeviceServer
from sim_backends.track import TrackModel
from tests.drivers.hardware import modbus_address, needs

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
