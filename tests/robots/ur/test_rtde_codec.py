"""Pure tests of the RTDE codec, the URScript programs, the clock mapper and the UR limits."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest

from telerig.errors import WireError
from telerig.robots.ur import rtde
from telerig.robots.ur.driver import ClockMapper
from telerig.robots.ur.limits import UR_JOINT_NAMES, ur_limits
from telerig.robots.ur.rtde import (
    Accepted,
    Command,
    ControllerVersion,
    FrameReader,
    InputSetup,
    MessageLevel,
    OutputSetup,
    ProtocolVersionRequest,
    Recipe,
    SetupReply,
    TextMessage,
)
from telerig.robots.ur.script import ServoProgram, stop_program


def _one(data: bytes) -> rtde.Frame:
    frames = FrameReader().feed(data)
    assert len(frames) == 1
    return frames[0]


def test_pack_writes_big_endian_size_including_header_then_type() -> None:
    assert rtde.pack(Command.CONTROL_PACKAGE_START) == b"\x00\x03S"
    assert ProtocolVersionRequest(2).encode() == b"\x00\x05V\x00\x02"


def test_frame_reader_reassembles_packages_split_at_any_byte() -> None:
    stream = (
        ProtocolVersionRequest().encode()
        + TextMessage("hi").encode()
        + rtde.pack(Command.CONTROL_PACKAGE_PAUSE)
    )
    reader = FrameReader()
    frames = []
    for i in range(len(stream)):
        frames += reader.feed(stream[i : i + 1])
    assert [f.command for f in frames] == [Command.REQUEST_PROTOCOL_VERSION, Command.TEXT_MESSAGE, ord("P")]
    assert reader.pending == 0


def test_frame_reader_rejects_size_below_header() -> None:
    with pytest.raises(WireError, match="< 3"):
        FrameReader().feed(b"\x00\x02U")


@pytest.mark.parametrize(
    "message",
    [
        ProtocolVersionRequest(2),
        ControllerVersion(5, 15, 2, 1234),
        TextMessage("servo loop started", "telerig", MessageLevel.WARNING),
        OutputSetup(125.0, ("timestamp", "actual_q")),
        InputSetup(("input_double_register_0", "input_int_register_0")),
    ],
)
def test_messages_round_trip(message: object) -> None:
    frame = _one(message.encode())  # type: ignore[attr-defined]
    assert type(message).decode(frame.payload) == message  # type: ignore[attr-defined]


def test_accepted_and_setup_reply_round_trip() -> None:
    accepted = Accepted(Command.CONTROL_PACKAGE_START, True)
    assert Accepted.decode(Command.CONTROL_PACKAGE_START, _one(accepted.encode()).payload) == accepted
    reply = SetupReply(Command.CONTROL_PACKAGE_SETUP_OUTPUTS, 1, ("DOUBLE", "VECTOR6D"))
    assert SetupReply.decode(Command.CONTROL_PACKAGE_SETUP_OUTPUTS, _one(reply.encode()).payload) == reply


def test_output_setup_payload_is_double_frequency_then_ascii_names() -> None:
    frame = _one(OutputSetup(500.0, ("timestamp", "actual_q")).encode())
    assert frame.payload == struct.pack(">d", 500.0) + b"timestamp,actual_q"


def test_text_message_truncated_raises() -> None:
    with pytest.raises(WireError, match="truncated"):
        TextMessage.decode(b"\x05hi")


def test_setup_reply_names_refused_variables() -> None:
    reply = SetupReply(Command.CONTROL_PACKAGE_SETUP_INPUTS, 0, ("DOUBLE", rtde.NOT_FOUND, rtde.IN_USE))
    problems = reply.problems(["a", "b", "c"])
    assert problems == ["b (NOT_FOUND)", "c (IN_USE)"]
    with pytest.raises(WireError, match=r"b \(NOT_FOUND\), c \(IN_USE\)"):
        Recipe.from_reply(["a", "b", "c"], reply)


def test_recipe_round_trips_every_type() -> None:
    types = tuple(rtde.TYPE_FORMATS)
    names = tuple(f"v{i}" for i in range(len(types)))
    samples: dict[str, rtde.Value] = {
        "BOOL": True,
        "UINT8": 200,
        "UINT32": 4_000_000_000,
        "UINT64": 2**63 + 5,
        "INT32": -7,
        "DOUBLE": math.pi,
        "VECTOR3D": (1.0, -2.0, 3.5),
        "VECTOR6D": (0.1, 0.2, 0.3, 0.4, 0.5, 0.6),
        "VECTOR6INT32": (-1, 2, -3, 4, -5, 6),
        "VECTOR6UINT32": (1, 2, 3, 4, 5, 4_000_000_000),
    }
    recipe = Recipe(7, names, types)
    values = {n: samples[t] for n, t in zip(names, types, strict=True)}
    frame = _one(recipe.encode(values))
    assert frame.command == Command.DATA_PACKAGE
    assert rtde.recipe_id_of(frame.payload) == 7
    assert recipe.decode(frame.payload) == values
    assert len(frame.payload) == recipe.size


def test_recipe_decode_rejects_wrong_size_and_wrong_id() -> None:
    recipe = Recipe(1, ("timestamp",), ("DOUBLE",))
    with pytest.raises(WireError, match="expected 9 bytes, got 2"):
        recipe.decode(b"\x01\x00")
    with pytest.raises(WireError, match="recipe id 2"):
        recipe.decode(b"\x02" + struct.pack(">d", 1.0))


def test_recipe_encode_names_missing_variable_and_bad_vector() -> None:
    recipe = Recipe(1, ("actual_q",), ("VECTOR6D",))
    with pytest.raises(WireError, match="no value for 'actual_q'"):
        recipe.encode({})
    with pytest.raises(WireError, match="expected 6 values, got 2"):
        recipe.encode({"actual_q": (1.0, 2.0)})


def test_recipe_rejects_unknown_type_naming_the_valid_ones() -> None:
    with pytest.raises(WireError, match=r"'x' has type 'NOT_FOUND'\. Valid: BOOL"):
        Recipe(1, ("x",), (rtde.NOT_FOUND,))


def test_catalogue_types_are_all_known() -> None:
    assert set(rtde.OUTPUT_TYPES.values()) <= set(rtde.TYPE_FORMATS)
    assert set(rtde.INPUT_TYPES.values()) <= set(rtde.TYPE_FORMATS)
    assert rtde.INPUT_TYPES["input_double_register_47"] == "DOUBLE"


def test_servo_program_parses_back_to_its_parameters() -> None:
    program = ServoProgram(
        int_register=24, double_register=24, period_s=0.008, lookahead_s=0.05, gain=500, watchdog_cycles=13
    )
    text = program.render()
    assert text.endswith("end\n")
    assert "servoj(q, 0, 0, 0.008, 0.05, 500)" in text
    assert ServoProgram.parse(text) == program


def test_servo_program_parse_refuses_other_programs() -> None:
    assert ServoProgram.parse("def other():\n  movej([0,0,0,0,0,0])\nend\n") is None
    tampered = ServoProgram().render().replace("read_input_float_register(5)", "read_input_float_register(9)")
    assert ServoProgram.parse(tampered) is None


def test_servo_program_validates_servoj_ranges() -> None:
    with pytest.raises(ValueError, match=r"lookahead_s must be in \[0.03, 0.2\]"):
        ServoProgram(lookahead_s=0.5)


def test_stop_programs() -> None:
    assert "protective_stop()" in stop_program("protective_stop")
    assert "stopj(2.5)" in stop_program("stopj", 2.5)


def test_clock_mapper_takes_the_fastest_package_in_the_window() -> None:
    mapper = ClockMapper(window_ns=1000)
    assert mapper.update(0, 500) == 500
    assert mapper.update(100, 580) == 480
    assert mapper.update(200, 750) == 480
    # 480 (at device 100) leaves the window at device 1101; 550 (at 200) is then the minimum.
    assert mapper.update(1150, 1720) == 550
    assert mapper.to_host(2000) == 2550


def test_clock_mapper_follows_drift() -> None:
    mapper = ClockMapper(window_ns=10_000)
    for t in range(0, 100_000, 100):
        mapper.update(t, t + 300 + t // 1000)  # host clock runs 0.1 % fast
    assert mapper.offset_ns == pytest.approx(300 + 90, abs=1)


def test_ur_limits() -> None:
    limits = ur_limits("ur10e")
    assert limits.names == UR_JOINT_NAMES
    np.testing.assert_allclose(limits.velocity[:2], np.deg2rad(120))
    np.testing.assert_allclose(limits.upper, 2 * np.pi)
    with pytest.raises(ValueError, match=r"unknown UR model 'ur7'\. Valid: ur3e, ur5e"):
        ur_limits("ur7")


def test_setup_request_with_trailing_comma_names_its_variables_only() -> None:
    # ur_rtde ends every recipe with a comma; a controller reads "timestamp,actual_q," as two variables.
    payload = struct.pack(">d", 500.0) + b"timestamp,actual_q,"
    assert OutputSetup.decode(payload).names == ("timestamp", "actual_q")
    assert rtde.InputSetup.decode(b"input_int_register_24,").names == ("input_int_register_24",)
