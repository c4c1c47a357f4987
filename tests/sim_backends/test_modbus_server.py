import pytest

from configuration.rig import GripperConfig, load_rig
from drivers.base import DeviceError, DeviceFault, DeviceTimeout
from drivers.modbus_link import ModbusTcpLink, exception_error
from sim_backends.gripper import GripperModel
from sim_backends.modbus_server import DirectLink, ModbusDeviceServer, RegisterDevice
from sim_backends.track import TrackModel


def test_modbus_device_server_serves_loopback_only():
    with pytest.raises(ValueError, match="loopback only"):
        ModbusDeviceServer({1: TrackModel(load_rig().track)}, host="0.0.0.0")
    with pytest.raises(ValueError, match="loopback only"):
        ModbusDeviceServer({1: TrackModel(load_rig().track)}, host="192.168.1.10")


def test_modbus_device_server_two_devices_and_parallel_servers():
    track, gripper = TrackModel(load_rig().track), GripperModel(GripperConfig())
    assert isinstance(track, RegisterDevice) and isinstance(gripper, RegisterDevice)
    with (
        ModbusDeviceServer({1: track, 9: gripper}) as one,
        ModbusDeviceServer({1: TrackModel(load_rig().track)}) as two,
    ):
        assert one.port != two.port
        link_track = ModbusTcpLink("127.0.0.1", one.port, 1)
        link_gripper = ModbusTcpLink("127.0.0.1", one.port, 9)
        link_track.connect()
        link_gripper.connect()
        # soft limit max 2.05 m = 2 050 000 µm = 0x001F_47D0, high word first
        assert link_track.read_input(110, 2) == [0x001F, 0x47D0]
        link_gripper.write(1000, [0x0100, 0, 0])
        assert gripper.read_registers(4, 2000, 1)[0] >> 8 & 0x01  # gACT set
        with pytest.raises(DeviceError, match="exception 2"):
            link_track.read_input(500, 2)  # outside every block
        link_track.close()
        link_gripper.close()
    assert not one.running and not two.running


def test_modbus_device_server_stop_is_idempotent_and_restart_keeps_port():
    server = ModbusDeviceServer({1: TrackModel(load_rig().track)})
    with pytest.raises(RuntimeError, match="not started"):
        _ = server.port
    server.start()
    port = server.port
    server.stop()
    server.stop()
    server.start()
    try:
        assert server.port == port and server.running
    finally:
        server.stop()


def test_direct_link_maps_exceptions_like_tcp():
    link = DirectLink(TrackModel(load_rig().track), "track")
    with pytest.raises(DeviceError, match="not connected"):
        link.read_input(100, 1)
    link.connect()
    with pytest.raises(DeviceError, match="exception 2 \\(illegal data address\\)"):
        link.write(100, [1])
    link.drop()
    with pytest.raises(DeviceTimeout, match="link dropped"):
        link.read_input(100, 1)


def test_exception_error_types():
    assert type(exception_error(2, "x")) is DeviceError
    assert isinstance(exception_error(4, "x"), DeviceFault)
    assert isinstance(exception_error(11, "x"), DeviceTimeout)
    assert "unknown exception" in str(exception_error(99, "x"))
