"""The Robotiq driver through the real pymodbus client against the real pymodbus server on
127.0.0.1, serving the simulated 2F-85 (each test starts and stops its own server); and the real
gripper when SATGRASP_GRIPPER is set (hardware)."""

import time

import pytest

from configuration.rig import GripperConfig
from drivers.base import DeviceError, Gripper
from drivers.gripper_robotiq import RobotiqGripper, RobotiqRegisters, command_registers, fault_name
from sim_backends.gripper import GripperModel
from sim_backends.modbus_server import ModbusDeviceServer
from tests.drivers.hardware import modbus_address, needs
from tests.drivers.register_fakes import RecordingLink

CONFIG = GripperConfig(activation_s=0.5)


@pytest.fixture
def served_gripper():
    model = GripperModel(CONFIG)
    with ModbusDeviceServer({9: model}) as server:
        gripper = RobotiqGripper.over_tcp("127.0.0.1", server.port, timeout_s=1.0)
        gripper.connect()
        yield model, gripper
        gripper.close()


def run(model, gripper, seconds, period=0.05):
    for _ in range(round(seconds / period)):
        model.step(period)
    return gripper.state()


def activated(model, gripper):
    gripper.activate()
    state = run(model, gripper, CONFIG.activation_s + 0.1)
    assert state.activated
    return state


def test_robotiq_command_registers_match_the_manual():
    close_full = command_registers(
        RobotiqRegisters.rACT | RobotiqRegisters.rGTO, position=255, speed=255, force=255
    )
    assert close_full == [0x0900, 0x00FF, 0xFFFF]
    with pytest.raises(ValueError, match="speed request 300"):
        command_registers(0x09, speed=300)


def test_robotiq_gripper_activation(served_gripper):
    model, gripper = served_gripper
    assert isinstance(gripper, Gripper)
    assert not gripper.state().activated
    gripper.activate()
    model.step(0.2)
    state = gripper.state()
    assert not state.activated and state.moving  # activation in progress (gSTA = 1)
    status = gripper.link.read_input(RobotiqRegisters.INPUT, 1)[0] >> 8
    assert (status >> 4) & 0b11 == RobotiqRegisters.STA_ACTIVATING
    state = run(model, gripper, 0.4)
    assert state.activated and not state.moving and state.fault is None


def test_robotiq_gripper_close_on_object_detects_it(served_gripper):
    model, gripper = served_gripper
    activated(model, gripper)
    model.set_object(0.040)
    gripper.grip()
    model.step(0.05)
    assert gripper.state().moving
    state = run(model, gripper, 1.0)
    assert state.object_detected and not state.moving
    # stopped where the fingers meet the object: 40 mm of the 85 mm stroke
    assert model.opening == pytest.approx(0.040, abs=1e-9)
    assert state.position == pytest.approx(round(255 * (1 - 0.040 / 0.085)) / 255)
    status = gripper.link.read_input(RobotiqRegisters.INPUT, 3)
    assert status[0] >> 14 == RobotiqRegisters.OBJ_CONTACT_CLOSING  # gOBJ = 2
    assert status[1] & 0xFF == 255  # rPR echoed
    assert status[2] & 0xFF > 0  # current while squeezing


def test_robotiq_gripper_close_without_object_reaches_position(served_gripper):
    model, gripper = served_gripper
    activated(model, gripper)
    gripper.grip()
    # full stroke at full speed: 0.085 m / 0.15 m/s ≈ 0.57 s
    state = run(model, gripper, 0.5)
    assert state.moving and not state.object_detected
    state = run(model, gripper, 0.2)
    assert state.position == 1.0 and not state.moving and not state.object_detected
    status = gripper.link.read_input(RobotiqRegisters.INPUT, 1)[0]
    assert status >> 14 == RobotiqRegisters.OBJ_AT_POSITION  # gOBJ = 3
    gripper.open()
    state = run(model, gripper, 1.0)
    assert state.position == 0.0 and model.opening == pytest.approx(0.085)


def test_robotiq_gripper_move_before_activation_is_a_minor_fault(served_gripper):
    model, gripper = served_gripper
    gripper.link.write(RobotiqRegisters.OUTPUT, command_registers(RobotiqRegisters.rGTO, 255))
    state = gripper.state()
    assert state.fault == "the activation bit must be set prior to action"
    activated(model, gripper)
    assert gripper.state().fault is None


def test_robotiq_gripper_injected_fault_stops_until_reactivated(served_gripper):
    model, gripper = served_gripper
    activated(model, gripper)
    gripper.grip()
    model.step(0.2)
    model.inject_fault(0x0E)
    position = gripper.state().position
    state = run(model, gripper, 1.0)
    assert state.fault == "overcurrent triggered" and state.position == position
    gripper.grip()  # refused while the major fault stands
    assert run(model, gripper, 0.5).position == position
    activated(model, gripper)  # reset + activation clears it
    gripper.grip()
    assert run(model, gripper, 1.0).position == 1.0


def test_robotiq_gripper_releases_when_object_removed(served_gripper):
    model, gripper = served_gripper
    activated(model, gripper)
    model.set_object(0.03)
    gripper.grip()
    assert run(model, gripper, 1.0).object_detected
    model.set_object(None)
    state = run(model, gripper, 1.0)
    assert not state.object_detected and state.position == 1.0


# --- the driver's encodings, word by word (in-process) ----------------------------------------


def recording_gripper(status=(0, 0, 0), **options):
    link = RecordingLink(dict(zip((2000, 2001, 2002), status, strict=True)))
    return link, RobotiqGripper(link, clock=lambda: 12.5, **options)


@pytest.mark.parametrize("name", ["speed", "force"])
def test_robotiq_gripper_speed_and_force_bounds_inclusive(name):
    for value in (0.0, 1.0):
        link, gripper = recording_gripper(**{name: value})
        gripper.grip()
        word = link.writes[-1][1][2]
        byte = word >> 8 if name == "speed" else word & 0xFF
        assert byte == round(255 * value)
    for value in (-0.001, 1.001):
        with pytest.raises(ValueError, match=f"gripper {name} must be in \\[0, 1\\]; got {value}"):
            recording_gripper(**{name: value})


def test_robotiq_gripper_move_open_grip_write_the_request():
    link, gripper = recording_gripper(speed=0.5, force=0.2)
    gripper.grip()
    gripper.open()
    gripper.move(100)
    action = (RobotiqRegisters.rACT | RobotiqRegisters.rGTO) << 8
    speed_force = (round(255 * 0.5) << 8) | round(255 * 0.2)
    assert link.writes == [
        (1000, [action, 255, speed_force]),
        (1000, [action, 0, speed_force]),
        (1000, [action, 100, speed_force]),
    ]


def test_robotiq_gripper_activate_resets_then_requests_activation():
    link, gripper = recording_gripper()
    gripper.activate()
    assert link.writes == [(1000, [0, 0, 0]), (1000, [RobotiqRegisters.rACT << 8, 0, 0])]
    gripper.deactivate()  # keeps the fingers where they are: writes nothing
    assert len(link.writes) == 2


def test_robotiq_gripper_connect_reads_status_and_close_closes():
    link, gripper = recording_gripper()
    gripper.connect()
    assert link.connected
    gripper.close()
    assert link.closed

    class Short(RecordingLink):
        def read_input(self, address, count):
            return [0] * (count - 1)

    with pytest.raises(DeviceError, match=r"short status read \(2 registers\)"):
        RobotiqGripper(Short()).connect()


def status_word(sta=0, obj=0, go=False, active=True):
    bits = (sta << 4) | (obj << 6) | (RobotiqRegisters.gGTO if go else 0)
    return (bits | (RobotiqRegisters.gACT if active else 0)) << 8


@pytest.mark.parametrize(
    ("sta", "obj", "go", "activated", "moving", "detected"),
    [
        (0, 0, False, False, False, False),
        (1, 0, False, False, True, False),  # activating
        (3, 0, True, True, True, False),  # going, no object yet
        (3, 0, False, True, False, False),
        (3, 1, True, True, False, True),  # stopped on an object while opening
        (3, 2, True, True, False, True),  # … while closing
        (3, 3, True, True, False, False),  # at the requested position, nothing there
    ],
)
def test_robotiq_gripper_state_decodes_the_status(sta, obj, go, activated, moving, detected):
    status = (status_word(sta, obj, go), 0x0E00 | 0x7F, (200 << 8) | 12)
    _, gripper = recording_gripper(status)
    state = gripper.state()
    assert (state.activated, state.moving, state.object_detected) == (activated, moving, detected)
    assert state.position == pytest.approx(200 / 255)
    assert state.fault == "overcurrent triggered"
    assert state.stamp == 12.5


def test_robotiq_fault_names():
    assert fault_name(0) is None
    assert fault_name(0x05) == "action delayed: activation must complete first"
    assert fault_name(0x0F) == "automatic release completed"
    assert fault_name(0x42) == "fault 0x42"
    assert fault_name(0x01) == "fault 0x01"


@pytest.mark.parametrize("name", ["position", "speed", "force"])
def test_robotiq_command_registers_range_on_both_ends(name):
    for value in (0, 255):
        registers = command_registers(0xFF, **{name: value})
        word = {"position": registers[1], "speed": registers[2] >> 8, "force": registers[2] & 0xFF}
        assert word[name] == value
    for value in (-1, 256):
        with pytest.raises(ValueError, match=f"gripper {name} request {value} is outside 0…255"):
            command_registers(0, **{name: value})
    assert command_registers(0x1FF)[0] == 0xFF00  # the action request is one byte


def test_robotiq_gripper_over_tcp_builds_its_link():
    gripper = RobotiqGripper.over_tcp("127.0.0.9", 5999, timeout_s=0.7)
    link = gripper.link
    assert (link.host, link.port, link.device_id, link.timeout_s) == ("127.0.0.9", 5999, 9, 0.7)
    other = RobotiqGripper.over_tcp("127.0.0.9", 5999, 4)
    assert other.link.device_id == 4 and other.link.timeout_s == 0.5


def test_robotiq_gripper_over_tcp_passes_speed_force_and_clock():
    gripper = RobotiqGripper.over_tcp("127.0.0.9", 5999, speed=0.2, force=0.4, clock=lambda: 3.5)
    link = RecordingLink({2000: status_word(3, 3)})
    gripper._link = link  # the same driver on a recording link: what it would send
    gripper.grip()
    assert link.writes[-1][1][2] == (round(255 * 0.2) << 8) | round(255 * 0.4)
    assert gripper.state().stamp == 3.5


# --- the real gripper ------------------------------------------------------------------------
@pytest.mark.hardware
@needs("SATGRASP_GRIPPER", "gripper's Modbus TCP address (a gateway to its RTU)")
def test_real_gripper_answers_its_status_without_a_fault():
    """Read-only: the gripper (through its gateway) answers status reads, no fault."""
    host, port, unit = modbus_address("SATGRASP_GRIPPER", device_id=9)
    gripper = RobotiqGripper.over_tcp(host, port, unit, timeout_s=0.5)
    try:
        gripper.connect()
        state = gripper.state()
    finally:
        gripper.close()
    assert 0.0 <= state.position <= 1.0
    assert state.fault is None, f"the gripper reports {state.fault}"


@pytest.mark.hardware
@needs("SATGRASP_GRIPPER", "gripper's Modbus TCP address (a gateway to its RTU)")
def test_real_gripper_activates_closes_and_opens():
    """Moves the fingers (activation, close, open): keep them clear."""
    host, port, unit = modbus_address("SATGRASP_GRIPPER", device_id=9)
    gripper = RobotiqGripper.over_tcp(host, port, unit, timeout_s=0.5, speed=0.5, force=0.2)
    gripper.connect()
    try:
        gripper.activate()
        _wait(lambda: gripper.state().activated, 10.0, "activated")
        for command, closed in ((gripper.grip, True), (gripper.open, False)):
            command()
            _wait(lambda: not gripper.state().moving, 5.0, "at rest")
            state = gripper.state()
            assert state.fault is None and (state.position > 0.8) == closed, state
    finally:
        gripper.close()


def _wait(condition, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    time.sleep(0.1)  # the status shows the new request after the device's next cycle
    while not condition():
        assert time.monotonic() < deadline, f"the gripper was not {what} within {timeout_s} s"
        time.sleep(0.05)
