"""The RTDE wire codec shared by the UR driver's probe and the UR emulator."""

import struct

import numpy as np
import pytest

from drivers import rtde_protocol as rtde


def test_encode_header_counts_itself_and_is_big_endian():
    message = rtde.encode(rtde.Message.START)
    assert message == b"\x00\x03S"
    message = rtde.encode(rtde.Message.DATA_PACKAGE, b"\x01\x02")
    assert message[:3] == struct.pack(">HB", 5, ord("U"))


def test_message_reader_splits_a_stream_cut_anywhere():
    rng = np.random.default_rng(3)
    messages = [
        (rtde.Message.TEXT_MESSAGE, bytes(rng.integers(0, 255, n, dtype=np.uint8)))
        for n in (0, 1, 40, 300)
    ]
    stream = b"".join(rtde.encode(kind, payload) for kind, payload in messages)
    cuts = sorted(rng.choice(len(stream), 7, replace=False))
    reader, got = rtde.MessageReader(), []
    for start, end in zip([0, *cuts], [*cuts, len(stream)], strict=True):
        got += reader.feed(stream[start:end])
    assert got == [(int(kind), payload) for kind, payload in messages]


def test_message_reader_rejects_a_header_shorter_than_itself():
    with pytest.raises(rtde.RTDEProtocolError, match="announces 2 bytes"):
        rtde.MessageReader().feed(struct.pack(">HB", 2, ord("U")))


def test_recipe_codec_round_trips_every_type():
    types = list(rtde.TYPE_FORMATS)
    values = [
        True,
        200,
        4_000_000_000,
        2**40,
        -5,
        1.25,
        (1.0, 2.0, 3.0),
        tuple(np.linspace(-1, 1, 6)),
        (1, -2, 3, -4, 5, -6),
        (1, 2, 3, 4, 5, 6),
    ]
    codec = rtde.RecipeCodec(types)
    message = codec.pack(7, values)
    ((kind, payload),) = rtde.MessageReader().feed(message)
    assert kind == rtde.Message.DATA_PACKAGE
    recipe_id, decoded = codec.unpack(payload)
    assert recipe_id == 7
    assert decoded == values
    assert codec.size == len(payload)


def test_recipe_codec_rejects_wrong_sizes_and_types():
    codec = rtde.RecipeCodec(["DOUBLE", "INT32"])
    with pytest.raises(rtde.RTDEProtocolError, match="needs 2 values"):
        codec.pack(1, [1.0])
    with pytest.raises(rtde.RTDEProtocolError, match="does not match its recipe"):
        codec.unpack(b"\x01" + b"\x00" * 5)
    with pytest.raises(rtde.RTDEProtocolError, match="unknown RTDE data types"):
        rtde.RecipeCodec(["DOUBLE", "QUATERNION"])


def test_setup_messages_round_trip():
    ((kind, payload),) = rtde.MessageReader().feed(
        rtde.encode_output_setup(500.0, ["timestamp", "actual_q"])
    )
    assert kind == rtde.Message.SETUP_OUTPUTS
    assert rtde.decode_output_setup(payload) == (500.0, ["timestamp", "actual_q"])
    # ur-rtde ends its name lists with a comma
    assert rtde.decode_names(b"input_int_register_0,input_double_register_0,") == [
        "input_int_register_0",
        "input_double_register_0",
    ]
    reply = rtde.encode_setup_reply(rtde.Message.SETUP_OUTPUTS, 3, ["DOUBLE", rtde.NOT_FOUND])
    assert rtde.decode_setup_reply(reply[3:]) == (3, ["DOUBLE", "NOT_FOUND"])
    assert rtde.decode_controller_version(rtde.encode_controller_version((5, 15, 0, 7))[3:]) == (
        5,
        15,
        0,
        7,
    )
    assert rtde.decode_version_request(rtde.encode_version_request()[3:]) == 2
    assert rtde.decode_accepted(rtde.encode_accepted(rtde.Message.START, True)[3:])
