import math

import numpy as np
import pytest

from configuration.rig import TrackConfig, load_rig
from drivers.base import DeviceError, DeviceFault
from drivers.modbus_link import int32_to_registers, registers_to_int32
from drivers.track_modbus import ModbusTrack, TrackRegisters
from sim_backends.modbus_server import READ_INPUT, DirectLink, RegisterAccessError
from sim_backends.track import TrackModel

R = TrackRegisters
CONFIG = load_rig().track


def direct_track(config: TrackConfig = CONFIG) -> tuple[TrackModel, ModbusTrack]:
    model = TrackModel(config)
    track = ModbusTrack(DirectLink(model, "track"), clock=lambda: model.time)
    track.connect()
    track.activate()
    return model, track


def run(model: TrackModel, track: ModbusTrack, seconds: float, period: float = 0.02):
    """Step the model, polling the driver like a control loop; returns the sampled states."""
    states = []
    for _ in range(round(seconds / period)):
        model.step(period)
        states.append(track.state())
    return states


def test_track_model_position_move_has_trapezoidal_profile():
    model, track = direct_track()
    track.move_to(1.0, 0.2)
    states = run(model, track, 8.0)
    positions = np.array([s.position for s in states])
    velocities = np.array([s.velocity for s in states])
    assert states[-1].position == pytest.approx(1.0, abs=1e-6)
    assert not states[-1].moving and states[-1].velocity == 0.0
    assert np.max(velocities) == pytest.approx(0.2, abs=1e-6)  # cruise at the profile speed
    assert np.max(np.abs(np.diff(velocities))) <= CONFIG.max_acceleration * 0.02 + 1e-6
    assert np.all(np.diff(positions) >= -1e-9)  # no overshoot back and forth
    assert positions.max() <= 1.0 + 1e-6
    # rest-to-rest time of a trapezoid: d/v + v/a = 5 + 0.4 s
    arrived = next(i for i, s in enumerate(states) if not s.moving and s.position > 0.99)
    assert (arrived + 1) * 0.02 == pytest.approx(5.4, abs=0.1)
    status = model.read_registers(READ_INPUT, R.STATUS, 1)[0]
    assert status & R.ST_IN_POSITION


def test_track_model_velocity_mode_clamps_to_max_speed():
    model, track = direct_track(CONFIG.model_copy(update={"max_speed": 0.1}))
    with pytest.raises(ValueError, match="max_speed"):
        track.move_velocity(0.2)
    # a device asked directly for more than its limit runs at its limit
    model.write_registers(
        R.CONTROL, [R.CTRL_ENABLE, R.MODE_VELOCITY, 0, 0, 0, 0, *int32_to_registers(200_000)]
    )
    states = run(model, track, 1.0)
    assert states[-1].velocity == pytest.approx(0.1)
    assert states[-1].moving


def test_track_model_soft_limit_latches_fault_and_brakes():
    model, track = direct_track()
    track.move_velocity(-0.2)  # from position 0 toward the min limit
    states = run(model, track, 1.0)
    final = states[-1]
    assert final.fault == "soft limit min crossed"
    assert final.velocity == 0.0 and not final.moving
    # overshoot ≤ the braking distance from where it crossed (v ≤ 0.2 m/s): v²/2a = 4 cm
    assert -0.04 - 1e-6 <= final.position < 0.0
    assert model.faults == R.FAULT_SOFT_LIMIT_MIN
    with pytest.raises(DeviceFault, match="soft limit min"):
        track.move_velocity(-0.1)
    track.reset_fault()
    track.move_velocity(0.1)  # back into the travel is allowed
    states = run(model, track, 1.0)
    assert states[-1].fault is None and states[-1].position > 0.0


def test_track_model_refuses_targets_beyond_soft_limits():
    model, track = direct_track()
    with pytest.raises(ValueError, match="outside the travel"):
        track.move_to(CONFIG.travel_max + 0.01, 0.1)
    # the device itself refuses too (exception 3), whatever the driver checked
    target = int32_to_registers(round((CONFIG.travel_max + 0.01) * 1e6))
    with pytest.raises(RegisterAccessError) as error:
        model.write_registers(
            R.CONTROL, [R.CTRL_ENABLE, R.MODE_POSITION, *target, *int32_to_registers(100_000)]
        )
    assert error.value.code == 3
    with pytest.raises(RegisterAccessError) as error:
        model.write_registers(R.MODE, [7])
    assert error.value.code == 3
    with pytest.raises(RegisterAccessError) as error:
        model.write_registers(R.STATUS, [0])
    assert error.value.code == 2


def test_track_model_watchdog_stops_silent_host():
    model, track = direct_track()
    track.move_velocity(0.1)
    run(model, track, 0.5)
    assert track.state().fault is None
    model.step(CONFIG.watchdog_s + 0.05)  # nobody polls
    state = track.state()
    assert "watchdog" in state.fault
    model.step(1.0)
    assert model.velocity == 0.0


def test_track_model_drive_fault_and_disable_stop_the_axis():
    model, track = direct_track()
    track.move_velocity(0.2)
    run(model, track, 1.0)
    model.inject_drive_fault()
    states = run(model, track, 1.0)
    assert states[-1].fault == "drive fault" and states[-1].velocity == 0.0
    track.reset_fault()
    track.move_velocity(0.2)
    run(model, track, 1.0)
    track.disable()
    states = run(model, track, 1.0)
    assert states[-1].velocity == 0.0
    status = model.read_registers(READ_INPUT, R.STATUS, 1)[0]
    assert not status & R.ST_ENABLED
    disabled_velocity_command = [0, R.MODE_VELOCITY, 0, 0, 0, 0, *int32_to_registers(100_000)]
    with pytest.raises(DeviceFault, match="device failure"):
        track.link.write(R.CONTROL, disabled_velocity_command)


def test_track_model_heartbeat_counts_device_cycles():
    model, _ = direct_track()
    before = model.read_registers(READ_INPUT, R.HEARTBEAT, 1)[0]
    model.step(0.1)
    after = model.read_registers(READ_INPUT, R.HEARTBEAT, 1)[0]
    assert after - before == round(0.1 * CONFIG.control_rate_hz)


def test_track_model_carries_the_mockup_with_drift():
    config = CONFIG.model_copy(
        update={"drift_velocity_M": (0.0, 0.01, 0.0), "drift_rate_deg_s": (0.0, 0.0, 2.0)}
    )
    model, track = direct_track(config)
    X_WT0 = model.X_WT()
    track.move_to(1.0, 0.25)
    run(model, track, 10.0)
    X_WT = model.X_WT()
    # the carriage moved 1 m along the axis; the mount drifted 0.1 m along M's y in 10 s
    expected_p = X_WT0.p + 1.0 * np.array(config.axis_W) + np.array([0.0, 0.1, 0.0])
    assert X_WT.p == pytest.approx(expected_p, abs=1e-6)
    # and the mock-up turned 20° about its own z (the ring's axis)
    R_rel = X_WT0.R.T @ X_WT.R
    assert math.degrees(math.atan2(R_rel[1, 0], R_rel[0, 0])) == pytest.approx(20.0, abs=1e-6)


def test_direct_link_drop_raises_timeout():
    _, track = direct_track()
    track.link.drop()
    with pytest.raises(DeviceError, match="link dropped"):
        track.state()
    track.link.restore()
    assert track.state().fault is None


def test_int32_registers_round_trip_high_word_first():
    for value in (0, 1, -1, 2_050_000, -123_456_789, 2**31 - 1, -(2**31)):
        assert registers_to_int32(*int32_to_registers(value)) == value
    assert int32_to_registers(0x12345678) == [0x1234, 0x5678]
    assert int32_to_registers(-2) == [0xFFFF, 0xFFFE]
    with pytest.raises(ValueError, match="32-bit"):
        int32_to_registers(2**31)
