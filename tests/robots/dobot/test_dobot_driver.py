"""Tests of the Dobot driver against the fake controller over real sockets on 127.0.0.1."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from telerig.errors import RobotError
from telerig.ir.types import GripperCommand, JointCommand, Stamp
from telerig.registry import ROBOTS
from telerig.robots.base import RobotDriver
from telerig.robots.dobot.config import DobotConfig
from telerig.robots.dobot.driver import CR5_LIMITS, DobotRobot
from telerig.robots.dobot.fake import FakeDobot
from telerig.robots.dobot.protocol import RobotMode, encode_feedback, parse_command

HOME_DEG = (0.0, 0.0, 90.0, 0.0, -90.0, 0.0)


def _wait(cond: Callable[[], bool], timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError("condition not met in time")
        time.sleep(0.005)


def _cmd(names: tuple[str, ...], positions: object) -> JointCommand:
    return JointCommand(Stamp.now("test", 0), names, np.asarray(positions, dtype=np.float64))


def _servoj_deg(fake: FakeDobot) -> np.ndarray:
    last = next(c for c in reversed(fake.commands) if c.lower().startswith("servoj"))
    return np.array([float(a) for a in parse_command(last).args])


@pytest.fixture
def fake() -> Iterator[FakeDobot]:
    with FakeDobot(dashboard_port=0, motion_port=0, feedback_port=0, clock_offset_ms=-3_600_000) as running:
        yield running


def _driver(fake: FakeDobot, **kw: object) -> DobotRobot:
    options: dict[str, object] = {"stale_timeout_s": 0.3, "timeout_s": 2.0}
    options.update(kw)
    return DobotRobot(
        "127.0.0.1",
        dashboard_port=fake.dashboard_port,
        motion_port=fake.motion_port if fake.protocol == "v3" else None,
        feedback_port=fake.feedback_port,
        protocol=fake.protocol,
        **options,  # type: ignore[arg-type]
    )


@pytest.fixture
def robot(fake: FakeDobot) -> Iterator[DobotRobot]:
    with _driver(fake) as driver:
        yield driver


def test_driver_satisfies_the_robot_driver_protocol(robot: DobotRobot) -> None:
    assert isinstance(robot, RobotDriver)
    assert robot.joint_names == CR5_LIMITS.names
    assert robot.limits is CR5_LIMITS


def test_connect_clears_alarms_enables_and_sets_the_speed_factor(fake: FakeDobot, robot: DobotRobot) -> None:
    assert robot.connected
    assert fake.mode == RobotMode.ENABLE
    assert fake.speed_factor == 50
    names = [c.split("(")[0] for c in fake.commands]
    assert names[:3] == ["ClearError", "EnableRobot", "SpeedFactor"]


def test_connect_and_close_are_idempotent(fake: FakeDobot) -> None:
    driver = _driver(fake)
    driver.connect()
    driver.connect()
    assert sum(c.startswith("EnableRobot") for c in fake.commands) == 1
    driver.close()
    driver.close()
    assert not driver.connected
    assert fake.mode == RobotMode.DISABLED
    with pytest.raises(RobotError, match="closed"):
        driver.connect()


def test_state_is_in_radians_and_stamped_in_host_time(robot: DobotRobot) -> None:
    state = robot.read_state()
    np.testing.assert_allclose(state.positions, np.radians(HOME_DEG))
    assert state.velocities.shape == (6,)
    assert state.efforts.shape == (6,)
    # The fake controller clock runs an hour behind: device time differs, capture does not.
    assert state.stamp.device_ns < state.stamp.arrival_ns - 3_500 * 10**9
    assert 0 <= state.stamp.arrival_ns - state.stamp.capture_ns < 10**9


def test_state_stream_keeps_arriving(robot: DobotRobot) -> None:
    first = robot.read_state().stamp
    packets = robot.stats["packets"]
    _wait(lambda: robot.stats["packets"] > packets + 3)
    later = robot.read_state().stamp
    assert later.arrival_ns > first.arrival_ns
    assert later.device_ns > first.device_ns


def test_send_writes_servoj_in_degrees_and_moves_the_arm(fake: FakeDobot, robot: DobotRobot) -> None:
    target = np.radians(HOME_DEG) + np.array([0.2, -0.1, 0.1, 0.3, 0.0, -0.2])
    sent = robot.send(_cmd(robot.joint_names, target))
    np.testing.assert_allclose(sent.positions, target)
    _wait(lambda: fake.servo_count == 1)
    np.testing.assert_allclose(_servoj_deg(fake), np.degrees(target), atol=1e-6)

    def arrived() -> bool:
        robot.send(_cmd(robot.joint_names, target))
        return bool(np.allclose(robot.read_state().positions, target, atol=1e-3))

    _wait(arrived)


def test_send_clips_to_the_joint_limits(fake: FakeDobot, robot: DobotRobot) -> None:
    sent = robot.send(_cmd(("joint3",), [4.0]))
    assert sent.positions[0] == pytest.approx(2.86)
    _wait(lambda: fake.servo_count == 1)
    assert _servoj_deg(fake)[2] == pytest.approx(math.degrees(2.86), abs=1e-5)


def test_send_of_a_subset_keeps_the_other_joint_targets(fake: FakeDobot, robot: DobotRobot) -> None:
    robot.send(_cmd(("joint1",), [0.5]))
    robot.send(_cmd(("joint6", "joint2"), [-0.25, 0.1]))
    _wait(lambda: fake.servo_count == 2)
    expected = np.array(HOME_DEG) + np.degrees([0.5, 0.1, 0, 0, 0, -0.25])
    np.testing.assert_allclose(_servoj_deg(fake), expected, atol=1e-5)


def test_send_names_an_unknown_joint(robot: DobotRobot) -> None:
    with pytest.raises(RobotError, match=r"'elbow' not found\. Available: joint1"):
        robot.send(_cmd(("elbow",), [0.0]))


def test_estop_latches_and_send_holds_until_reset(fake: FakeDobot, robot: DobotRobot) -> None:
    held = robot.read_state().positions
    robot.estop()
    assert robot.estopped
    assert fake.mode == RobotMode.ERROR
    assert fake.estop_count == 1
    sent = robot.send(_cmd(robot.joint_names, held + 0.5))
    np.testing.assert_allclose(sent.positions, held, atol=1e-9)
    assert fake.servo_count == 0
    assert not any(c.startswith("ServoJ") for c in fake.commands)
    robot.reset_estop()
    assert not robot.estopped
    assert fake.mode == RobotMode.ENABLE
    robot.send(_cmd(robot.joint_names, held + 0.01))
    _wait(lambda: fake.servo_count == 1)


def test_v4_sends_motion_on_the_dashboard_and_releases_estop_explicitly() -> None:
    with (
        FakeDobot(dashboard_port=0, motion_port=0, feedback_port=0, protocol="v4") as fake,
        _driver(fake) as robot,
    ):
        robot.send(_cmd(("joint1",), [0.1]))
        assert fake.servo_count == 1  # the reply was awaited on the dashboard port
        robot.estop()
        assert "EmergencyStop(1)" in fake.commands
        assert fake.mode == RobotMode.ERROR
        robot.reset_estop()
        assert "EmergencyStop(0)" in fake.commands
        assert fake.mode == RobotMode.ENABLE  # type: ignore[comparison-overlap]


def test_peer_death_raises_one_line_robot_error(fake: FakeDobot, robot: DobotRobot) -> None:
    fake.stop()
    _wait(lambda: not robot.connected)
    for call in (robot.read_state, lambda: robot.send(_cmd(("joint1",), [0.0]))):
        with pytest.raises(RobotError) as info:
            call()
        assert "\n" not in str(info.value)
        assert "connect()" in str(info.value)


def test_reconnects_after_the_connection_dropped(fake: FakeDobot, robot: DobotRobot) -> None:
    fake.drop_connections()
    _wait(lambda: not robot.connected)
    robot.connect()
    assert robot.connected
    assert robot.stats["connects"] == 2
    robot.read_state()


def test_silent_feedback_counts_as_lost(fake: FakeDobot, robot: DobotRobot) -> None:
    fake.feedback_paused = True
    time.sleep(0.4)
    with pytest.raises(RobotError, match="no feedback from"):
        robot.read_state()


def test_malformed_feedback_is_counted_and_dropped(fake: FakeDobot, robot: DobotRobot) -> None:
    bad = bytearray(encode_feedback(robot_mode=5, timestamp_ms=1, q_actual=(0.0,) * 6))
    bad[432:440] = b"\xff" * 8  # NaN joint angle
    fake.inject_feedback(b"junk bytes" + bytes(bad))
    _wait(lambda: robot.stats["malformed"] >= 1 and robot.stats["resyncs"] >= 1)
    before = robot.stats["packets"]
    _wait(lambda: robot.stats["packets"] > before + 2)
    np.testing.assert_allclose(robot.read_state().positions, np.radians(HOME_DEG))


def test_malformed_and_refused_motion_replies_are_counted(fake: FakeDobot, robot: DobotRobot) -> None:
    fake.inject_reply("not a reply;-1,{},ServoJ(1,2,3,4,5,6);")
    _wait(lambda: robot.stats["malformed_replies"] == 1 and robot.stats["motion_errors"] == 1)
    assert robot.connected


def test_send_refuses_when_the_robot_is_not_enabled(fake: FakeDobot) -> None:
    with _driver(fake, enable_on_connect=False) as robot, pytest.raises(RobotError, match="not enabled"):
        robot.send(_cmd(("joint1",), [0.0]))


def test_unreachable_controller_gives_one_line_error() -> None:
    with FakeDobot(dashboard_port=0, motion_port=0, feedback_port=0) as fake:
        port = fake.dashboard_port
    with pytest.raises(RobotError, match=r"cannot reach the dashboard port 127\.0\.0\.1:\d+") as info:
        DobotRobot("127.0.0.1", dashboard_port=port, timeout_s=0.5).connect()
    assert "\n" not in str(info.value)


def test_gripper_on_a_tool_output(fake: FakeDobot) -> None:
    with _driver(fake, gripper_tool_do=1) as robot:
        assert robot.send_gripper(GripperCommand(Stamp.now("t", 0), opening=0.2)).opening == 0.0
        assert fake.tool_do == {1: 1}
        assert robot.send_gripper(GripperCommand(Stamp.now("t", 1), opening=0.9)).opening == 1.0
        assert fake.tool_do == {1: 0}


def test_config_is_registered_and_builds_the_driver(fake: FakeDobot) -> None:
    assert ROBOTS.get("dobot") is DobotConfig
    config = ROBOTS.parse_config(
        {
            "type": "dobot",
            "id": "cr5",
            "host": "127.0.0.1",
            "dashboard_port": fake.dashboard_port,
            "motion_port": fake.motion_port,
            "feedback_port": fake.feedback_port,
        },
        "robots[0]",
    )
    with config.build() as robot:
        assert isinstance(robot, DobotRobot)
        assert robot.name == "cr5"
        assert robot.read_state().stamp.source_id == "cr5"
