"""Tests of the Dobot TCP/IP text commands, replies and the 1440-byte feedback packet."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from telerig.errors import WireError
from telerig.robots.dobot.protocol import (
    FEEDBACK_SIZE,
    TEST_VALUE,
    FeedbackFramer,
    RobotMode,
    decode_feedback,
    encode_feedback,
    format_command,
    format_reply,
    parse_command,
    parse_reply,
    split_commands,
    split_replies,
)

Q = (10.0, -20.0, 90.0, 0.5, -90.0, 179.0)


def _packet(**kw: object) -> bytes:
    args: dict[str, object] = {"robot_mode": 5, "timestamp_ms": 1_700_000_000_123, "q_actual": Q}
    args.update(kw)
    return encode_feedback(**args)  # type: ignore[arg-type]


def test_format_command_writes_floats_ints_and_keywords() -> None:
    assert format_command("ServoJ", 1.5, -2.0, t=0.1) == "ServoJ(1.500000,-2.000000,t=0.100000)"
    assert format_command("SpeedFactor", 50) == "SpeedFactor(50)"
    assert format_command("MovJ", joint=(0.0, 1.0)) == "MovJ(joint={0.000000,1.000000})"


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), "a,b"])
def test_format_command_rejects_values_the_protocol_cannot_carry(bad: object) -> None:
    with pytest.raises(ValueError, match=r"finite|must not contain"):
        format_command("ServoJ", bad)  # type: ignore[arg-type]


def test_parse_reply_reads_error_values_and_echo() -> None:
    reply = parse_reply("0,{0.0,0.0,90.0,0.0,-90.0,0.0},GetAngle();")
    assert reply.ok
    assert reply.command == "GetAngle()"
    np.testing.assert_array_equal(reply.floats(), [0, 0, 90, 0, -90, 0])
    empty = parse_reply("-10000,{},Mov(1,2);")
    assert empty.error_id == -10000
    assert empty.values == ()
    assert not empty.ok


def test_parse_reply_keeps_nested_values_whole() -> None:
    reply = parse_reply("0,{[[1,2],[],[3]]},GetErrorID();")
    assert reply.values == ("[[1,2],[],[3]]",)


@pytest.mark.parametrize("bad", ["", "abc,{},X();", "0,X();", "0,{1,2", "0,{1}"])
def test_parse_reply_rejects_malformed_text(bad: str) -> None:
    with pytest.raises(WireError):
        parse_reply(bad)


def test_reply_floats_rejects_non_numbers() -> None:
    with pytest.raises(WireError):
        parse_reply("0,{a},X();").floats()


def test_format_reply_round_trips_through_parse_reply() -> None:
    assert parse_reply(format_reply(0, (5,), "RobotMode()")).values == ("5",)


def test_split_commands_handles_partial_input_and_v4_braces() -> None:
    done, rest = split_commands("EnableRobot()ServoJ(1,2,t=0.1)MovJ(joint={1,2})Speed")
    assert done == ["EnableRobot()", "ServoJ(1,2,t=0.1)", "MovJ(joint={1,2})"]
    assert rest == "Speed"
    cmd = parse_command(done[1])
    assert cmd.name == "ServoJ"
    assert cmd.args == ("1", "2")
    assert cmd.kwargs == {"t": "0.1"}
    assert parse_command(done[2]).kwargs == {"joint": "{1,2}"}


def test_split_replies_keeps_the_unfinished_tail() -> None:
    done, rest = split_replies("0,{},A();0,{1},B();0,{")
    assert done == ["0,{},A();", "0,{1},B();"]
    assert rest == "0,{"


def test_feedback_packet_fields_sit_at_the_documented_offsets() -> None:
    data = _packet(qd_actual=(1, 2, 3, 4, 5, 6))
    assert len(data) == FEEDBACK_SIZE
    assert struct.unpack_from("<H", data, 0)[0] == 1440
    assert struct.unpack_from("<Q", data, 24)[0] == 5  # RobotMode
    assert struct.unpack_from("<Q", data, 32)[0] == 1_700_000_000_123  # TimeStamp [ms]
    assert struct.unpack_from("<Q", data, 48)[0] == TEST_VALUE
    assert struct.unpack_from("<6d", data, 432) == Q  # QActual [deg]
    assert struct.unpack_from("<6d", data, 480) == (1, 2, 3, 4, 5, 6)  # QDActual [deg/s]
    assert data[1026] == 1  # EnableStatus


def test_decode_feedback_round_trips_encode() -> None:
    packet = decode_feedback(_packet(robot_mode=RobotMode.ERROR))
    assert packet.robot_mode == RobotMode.ERROR
    assert packet.error_status == 1
    assert packet.timestamp_ms == 1_700_000_000_123
    np.testing.assert_array_equal(packet.q_actual, Q)


@pytest.mark.parametrize(
    "corrupt",
    [
        lambda b: b[:-1],
        lambda b: b"\x00\x00" + b[2:],
        lambda b: b[:48] + b"\x00" * 8 + b[56:],
        lambda b: b[:432] + struct.pack("<d", float("nan")) + b[440:],
    ],
    ids=["short", "length-field", "test-value", "nan-joint"],
)
def test_decode_feedback_rejects_corrupt_packets(corrupt: object) -> None:
    with pytest.raises(WireError):
        decode_feedback(corrupt(_packet()))  # type: ignore[operator]


def test_framer_reassembles_packets_split_across_reads() -> None:
    framer = FeedbackFramer()
    data = _packet() + _packet(timestamp_ms=2)
    got = [p for i in range(0, len(data), 100) for p in framer.feed(data[i : i + 100])]
    assert [p.timestamp_ms for p in got] == [1_700_000_000_123, 2]


def test_framer_resyncs_after_garbage_and_truncated_packets() -> None:
    framer = FeedbackFramer()
    stream = b"garbage" + _packet(timestamp_ms=1)[:700] + _packet(timestamp_ms=2) + _packet(timestamp_ms=3)
    got = list(framer.feed(stream))
    assert [p.timestamp_ms for p in got] == [2, 3]
    assert framer.resyncs == 1
    assert framer.malformed == 1
    assert framer.skipped_bytes == 7 + 700


def test_framer_counts_and_drops_well_framed_bad_packets() -> None:
    bad = _packet()[:432] + struct.pack("<d", float("inf")) + _packet()[440:]
    framer = FeedbackFramer()
    got = list(framer.feed(bad + _packet(timestamp_ms=9)))
    assert [p.timestamp_ms for p in got] == [9]
    assert framer.malformed == 1
    assert framer.packets == 1
