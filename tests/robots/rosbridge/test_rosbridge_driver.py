"""Tests of the rosbridge driver against the fake rosbridge over a real WebSocket on 127.0.0.1."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest
from pydantic import ValidationError

from telerig.errors import RobotError
from telerig.ir.types import JointCommand, Stamp
from telerig.registry import ROBOTS
from telerig.robots.base import JointLimits, RobotDriver
from telerig.robots.rosbridge.config import RosbridgeConfig
from telerig.robots.rosbridge.driver import RosbridgeRobot
from telerig.robots.rosbridge.fake import FakeRosbridge
from telerig.robots.rosbridge.protocol import CommandType

NAMES = ("shoulder", "elbow", "wrist")
LIMITS = JointLimits(NAMES, np.full(3, -2.0), np.full(3, 2.0), np.full(3, 2.0), np.full(3, 10.0))
ESTOP = "/telerig/estop"


def _wait(cond: Callable[[], bool], timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError("condition not met in time")
        time.sleep(0.005)


def _cmd(names: tuple[str, ...], positions: object) -> JointCommand:
    return JointCommand(Stamp.now("test", 0), names, np.asarray(positions, dtype=np.float64))


def _ops(fake: FakeRosbridge, op: str, topic: str | None = None) -> list[dict[str, object]]:
    return [m for m in list(fake.received) if m["op"] == op and (topic is None or m.get("topic") == topic)]


@pytest.fixture
def fake() -> Iterator[FakeRosbridge]:
    # Extra joint "gripper" is published but not commanded; the robot clock runs a day ahead.
    with FakeRosbridge(
        NAMES, extra_joints=("gripper",), max_velocity=2.0, clock_offset_ns=86_400 * 10**9
    ) as running:
        yield running


def _driver(fake: FakeRosbridge, **kw: object) -> RosbridgeRobot:
    options: dict[str, object] = {"estop_topic": ESTOP, "stale_timeout_s": 0.3, "reconnect_s": 0.1}
    options.update(kw)
    return RosbridgeRobot(fake.url, LIMITS, **options)  # type: ignore[arg-type]


@pytest.fixture
def robot(fake: FakeRosbridge) -> Iterator[RosbridgeRobot]:
    with _driver(fake) as driver:
        yield driver


def test_driver_satisfies_the_robot_driver_protocol(robot: RosbridgeRobot) -> None:
    assert isinstance(robot, RobotDriver)
    assert robot.joint_names == NAMES
    assert robot.limits is LIMITS


def test_connect_advertises_and_subscribes(fake: FakeRosbridge, robot: RosbridgeRobot) -> None:
    assert robot.connected
    (adv,) = _ops(fake, "advertise", robot.command_topic)
    assert adv["type"] == "trajectory_msgs/JointTrajectory"
    assert _ops(fake, "advertise", ESTOP)[0]["type"] == "std_msgs/Bool"
    assert _ops(fake, "subscribe", "/joint_states")[0]["type"] == "sensor_msgs/JointState"


def test_connect_and_close_are_idempotent(fake: FakeRosbridge) -> None:
    driver = _driver(fake)
    driver.connect()
    driver.connect()
    assert fake.connections == 1
    driver.close()
    driver.close()
    assert not driver.connected
    _wait(lambda: len(_ops(fake, "unsubscribe")) == 1)
    with pytest.raises(RobotError, match="closed"):
        driver.connect()


def test_state_maps_joint_order_and_is_stamped_in_host_time(
    fake: FakeRosbridge, robot: RosbridgeRobot
) -> None:
    states = robot.stats["states"]
    state = robot.read_state()
    assert state.names == NAMES
    assert state.positions.shape == (3,)
    assert state.stamp.device_ns > state.stamp.arrival_ns + 86_000 * 10**9  # the robot's clock
    assert 0 <= state.stamp.arrival_ns - state.stamp.capture_ns < 10**9
    _wait(lambda: robot.stats["states"] > states + 3)


@pytest.mark.parametrize("kind", ["trajectory_msgs/JointTrajectory", "std_msgs/Float64MultiArray"])
def test_send_moves_the_robot_toward_the_target(kind: CommandType) -> None:
    with (
        FakeRosbridge(NAMES, command_type=kind, command_topic="/cmd") as fake,
        _driver(fake, command_type=kind, command_topic="/cmd") as robot,
    ):
        target = np.array([0.3, -0.2, 0.1])
        sent = robot.send(_cmd(NAMES, target))
        np.testing.assert_allclose(sent.positions, target)
        _wait(lambda: np.allclose(robot.read_state().positions, target, atol=1e-6))
        assert fake.commands == 1


def test_send_clips_and_keeps_unsent_joint_targets(fake: FakeRosbridge, robot: RosbridgeRobot) -> None:
    robot.send(_cmd(("elbow",), [0.5]))
    sent = robot.send(_cmd(("wrist",), [3.0]))
    assert sent.positions[0] == pytest.approx(2.0)
    _wait(lambda: fake.commands == 2)
    msg = _ops(fake, "publish", robot.command_topic)[-1]["msg"]
    assert msg["points"][0]["positions"] == [0.0, 0.5, 2.0]  # type: ignore[index]


def test_send_names_an_unknown_joint(robot: RosbridgeRobot) -> None:
    with pytest.raises(RobotError, match=r"'gripper' not found\. Available: shoulder, elbow, wrist"):
        robot.send(_cmd(("gripper",), [0.0]))


def test_estop_holds_latches_and_resets(fake: FakeRosbridge, robot: RosbridgeRobot) -> None:
    robot.send(_cmd(NAMES, [1.0, 1.0, 1.0]))
    _wait(lambda: robot.read_state().positions[0] > 0.05)
    robot.estop()
    _wait(lambda: fake.estopped)
    held = robot.send(_cmd(NAMES, [-1.0, -1.0, -1.0])).positions
    published = len(_ops(fake, "publish", robot.command_topic))
    assert robot.send(_cmd(NAMES, [0.0, 0.0, 0.0])).positions.tolist() == held.tolist()
    time.sleep(0.05)
    assert len(_ops(fake, "publish", robot.command_topic)) == published  # nothing after the hold
    assert robot.estopped
    robot.reset_estop()
    _wait(lambda: not fake.estopped)
    robot.send(_cmd(NAMES, [0.0, 0.0, 0.0]))
    _wait(lambda: len(_ops(fake, "publish", robot.command_topic)) == published + 1)


def test_missing_joint_at_connect_is_named(fake: FakeRosbridge) -> None:
    fake.omit_joint = "elbow"
    with pytest.raises(RobotError, match="joint 'elbow' missing from /joint_states") as info:
        _driver(fake, timeout_s=0.5).connect()
    assert "\n" not in str(info.value)


def test_missing_joint_while_running_is_named(fake: FakeRosbridge, robot: RosbridgeRobot) -> None:
    fake.omit_joint = "wrist"
    _wait(lambda: robot.stats["partial"] > 0)
    time.sleep(0.4)
    with pytest.raises(RobotError, match="joint 'wrist' missing"):
        robot.read_state()


def test_peer_death_raises_one_line_error_and_reconnects(fake: FakeRosbridge, robot: RosbridgeRobot) -> None:
    fake.stop()
    _wait(lambda: not robot.connected)
    with pytest.raises(RobotError, match="reconnecting every") as info:
        robot.read_state()
    assert "\n" not in str(info.value)
    with pytest.raises(RobotError):
        robot.send(_cmd(NAMES, [0.0, 0.0, 0.0]))
    fake.start()  # same port
    robot.connect()  # waits for the background reconnection
    assert robot.connected
    assert robot.stats["connects"] == 2
    robot.read_state()


def test_malformed_messages_are_counted_and_dropped(fake: FakeRosbridge, robot: RosbridgeRobot) -> None:
    fake.inject("{not json")
    fake.inject('{"op": "publish", "topic": "/joint_states", "msg": {"name": ["shoulder"], "position": "x"}}')
    fake.inject('{"op": "status", "level": "error", "msg": "publish /x: topic not advertised"}')
    _wait(lambda: robot.stats["malformed"] == 2 and robot.stats["status_errors"] == 1)
    states = robot.stats["states"]
    _wait(lambda: robot.stats["states"] > states + 2)


def test_unreachable_rosbridge_gives_one_line_error() -> None:
    with FakeRosbridge(NAMES) as fake:
        url = fake.url
    with pytest.raises(RobotError, match=r"cannot reach rosbridge at ws://127\.0\.0\.1") as info:
        RosbridgeRobot(url, LIMITS, timeout_s=0.3).connect()
    assert "\n" not in str(info.value)


def _config(base_url: str, **kw: object) -> dict[str, object]:
    raw: dict[str, object] = {
        "type": "rosbridge",
        "id": "arm",
        "url": base_url,
        "joint_names": list(NAMES),
        "lower": [-2.0] * 3,
        "upper": [2.0] * 3,
        "velocity": 2.0,
        "acceleration": [10.0, 10.0, 10.0],
    }
    raw.update(kw)
    return raw


def test_config_is_registered_and_builds_the_driver(fake: FakeRosbridge) -> None:
    assert ROBOTS.get("rosbridge") is RosbridgeConfig
    config = ROBOTS.parse_config(_config(fake.url), "robots[0]")
    with config.build() as robot:
        assert isinstance(robot, RosbridgeRobot)
        assert robot.name == "arm"
        np.testing.assert_array_equal(robot.limits.velocity, [2.0, 2.0, 2.0])
        robot.read_state()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"upper": [2.0, 2.0]}, "upper has 2 values for 3 joint_names"),
        ({"url": "http://x:9090"}, "url must start with ws://"),
        ({"lower": [3.0] * 3}, "lower limits must not exceed upper"),
    ],
)
def test_config_errors_name_the_field(change: dict[str, object], message: str) -> None:
    with pytest.raises(ValidationError, match=message):
        RosbridgeConfig.model_validate(_config("ws://127.0.0.1:9090", **change))


def test_a_ros2_robot_without_effort_and_velocity_interfaces_connects() -> None:
    # joint_state_broadcaster fills them with NaN, which rosbridge sends as null (issue 11, finding 11).
    with (
        FakeRosbridge(NAMES, null_fields=("velocity", "effort")) as fake,
        _driver(fake, timeout_s=2.0) as robot,
    ):
        state = robot.read_state()
        assert state.efforts.size == 0  # not reported by the robot
        np.testing.assert_array_equal(state.velocities, np.zeros(3))  # not measured: zeros, as documented
        assert robot.stats["malformed"] == 0


def test_connect_says_what_it_received_and_why_it_was_rejected() -> None:
    with FakeRosbridge(NAMES, null_fields=("position",)) as fake, pytest.raises(RobotError) as info:
        _driver(fake, timeout_s=0.5).connect()
    message = str(info.value)
    assert "\n" not in message
    assert "no sensor_msgs/JointState on /joint_states within 0.5 s" in message
    assert "rejected" in message
    assert "JointState.position[0] ('shoulder') is null" in message
