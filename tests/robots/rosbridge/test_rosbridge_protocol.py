"""Tests of the rosbridge v2 operations and the JointState / command messages."""

from __future__ import annotations

import json

import numpy as np
import pytest

from telerig.errors import WireError
from telerig.robots.rosbridge.protocol import (
    FLOAT64_MULTI_ARRAY,
    JOINT_TRAJECTORY,
    CommandType,
    advertise,
    canonical_type,
    command_msg,
    decode,
    encode,
    joint_state,
    parse_command,
    parse_joint_state,
    publish,
    subscribe,
)

NAMES = ("a", "b", "c")


def test_operations_have_the_rosbridge_v2_fields() -> None:
    assert decode(encode(advertise("/cmd", JOINT_TRAJECTORY, "x"))) == {
        "op": "advertise",
        "id": "x",
        "topic": "/cmd",
        "type": "trajectory_msgs/JointTrajectory",
    }
    sub = subscribe("/joint_states", "sensor_msgs/JointState", "s")
    assert sub["op"] == "subscribe"
    assert sub["queue_length"] == 1
    assert sub["throttle_rate"] == 0
    assert publish("/t", {"data": True}) == {"op": "publish", "topic": "/t", "msg": {"data": True}}


def test_encode_refuses_nan() -> None:
    with pytest.raises(WireError):
        encode(publish("/t", {"data": [float("nan")]}))


@pytest.mark.parametrize("bad", ["{not json", "[1, 2]", '{"topic": "/x"}', '{"op": 3}', b"\xff"])
def test_decode_rejects_what_is_not_an_operation(bad: str | bytes) -> None:
    with pytest.raises(WireError):
        decode(bad)


def test_canonical_type_accepts_the_ros2_spelling() -> None:
    assert canonical_type("sensor_msgs/msg/JointState") == "sensor_msgs/JointState"
    assert canonical_type("sensor_msgs/JointState") == "sensor_msgs/JointState"


def test_joint_state_round_trips_with_ros2_stamp() -> None:
    msg = joint_state(NAMES, [1, 2, 3], [0.1, 0.2, 0.3], stamp_ns=1_700_000_000_123_456_789)
    assert msg["header"]["stamp"] == {"sec": 1_700_000_000, "nanosec": 123_456_789}
    parsed = parse_joint_state(msg)
    assert parsed.names == NAMES
    assert parsed.stamp_ns == 1_700_000_000_123_456_789
    np.testing.assert_array_equal(parsed.positions, [1, 2, 3])
    assert parsed.efforts.size == 0


def test_joint_state_reads_ros1_stamps() -> None:
    msg = {"header": {"stamp": {"secs": 5, "nsecs": 7}}, "name": ["a"], "position": [0.5]}
    assert parse_joint_state(msg).stamp_ns == 5_000_000_007


@pytest.mark.parametrize(
    "msg",
    [
        {"name": ["a", "b"], "position": [1.0]},
        {"name": ["a"], "position": ["x"]},
        {"name": ["a"], "position": [1.0], "velocity": [1.0, 2.0]},
        {"name": ["a"], "position": [float("nan")]},
        {"name": "a", "position": [1.0]},
        {"name": ["a"], "position": [1.0], "header": {"stamp": {"sec": -1, "nanosec": 0}}},
        [1, 2],
    ],
    ids=[
        "short-position",
        "string-value",
        "velocity-length",
        "nan",
        "name-not-list",
        "bad-stamp",
        "not-object",
    ],
)
def test_parse_joint_state_rejects_malformed_messages(msg: object) -> None:
    with pytest.raises(WireError):
        parse_joint_state(msg)


@pytest.mark.parametrize("kind", [JOINT_TRAJECTORY, FLOAT64_MULTI_ARRAY])
def test_command_messages_round_trip(kind: CommandType) -> None:
    msg = command_msg(kind, NAMES, np.array([0.1, -0.2, 0.3]), 0.25)
    np.testing.assert_allclose(parse_command(kind, msg, NAMES), [0.1, -0.2, 0.3])


def test_trajectory_has_one_point_reached_after_time_from_start() -> None:
    msg = command_msg("trajectory_msgs/JointTrajectory", NAMES, [0.0, 0.0, 0.0], 1.25)
    assert msg["joint_names"] == list(NAMES)
    assert msg["points"][0]["time_from_start"] == {"sec": 1, "nanosec": 250_000_000}


def test_trajectory_is_read_by_joint_name() -> None:
    msg = command_msg("trajectory_msgs/JointTrajectory", ("c", "a", "b"), [3.0, 1.0, 2.0], 0.1)
    np.testing.assert_array_equal(parse_command(JOINT_TRAJECTORY, msg, NAMES), [1.0, 2.0, 3.0])
    with pytest.raises(WireError, match="lacks joints"):
        parse_command(JOINT_TRAJECTORY, msg, (*NAMES, "d"))


def test_null_effort_and_velocity_are_read_as_nan() -> None:
    # rosbridge writes NaN as JSON null; ROS 2's joint_state_broadcaster fills the velocity and
    # effort of joints without such an interface with NaN (issue 11, finding 11).
    text = '{"name": ["a", "b"], "position": [0.5, -0.5], "velocity": [null, 1.5], "effort": [null, null]}'
    state = parse_joint_state(json.loads(text))
    np.testing.assert_array_equal(state.positions, [0.5, -0.5])
    assert np.isnan(state.velocities[0])
    assert state.velocities[1] == 1.5
    assert np.isnan(state.efforts).all()


def test_a_null_position_is_refused_naming_the_joint() -> None:
    with pytest.raises(WireError, match=r"JointState\.position\[1\] \('b'\) is null"):
        parse_joint_state({"name": ["a", "b"], "position": [0.5, None]})
