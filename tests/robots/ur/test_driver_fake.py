"""The UR driver against the fake controller over real sockets on 127.0.0.1."""

from __future__ import annotations

import itertools
import socket
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from telerig.errors import RobotError
from telerig.ir.types import GripperCommand, JointCommand, Stamp
from telerig.registry import ROBOTS
from telerig.robots.base import RobotDriver
from telerig.robots.ur import rtde
from telerig.robots.ur.config import URRtdeConfig
from telerig.robots.ur.driver import URRobot
from telerig.robots.ur.fake import FakeURController
from telerig.robots.ur.limits import UR_JOINT_NAMES
from telerig.robots.ur.rtde import Command, RuntimeState, SafetyMode
from telerig.robots.ur.script import ServoProgram

RATE_HZ = 125.0
#: Generous watchdog so a loaded test machine never trips it by accident (0.5 s).
RELAXED = ServoProgram(watchdog_cycles=250)


def _wait(predicate: Callable[[], bool], what: str, timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.005)


def _cmd(positions: object, names: tuple[str, ...] = UR_JOINT_NAMES) -> JointCommand:
    return JointCommand(Stamp.now("test", 0), names, np.asarray(positions, dtype=np.float64))


@pytest.fixture
def fake() -> Iterator[FakeURController]:
    # Wrist 3 starts near its +2 pi limit so clipping tests need only a short move.
    home = (0.0, -np.pi / 2, np.pi / 2, -np.pi / 2, -np.pi / 2, 6.0)
    with FakeURController(rtde_port=0, script_port=0, gripper_port=0, home=home) as running:
        yield running


def _driver(fake: FakeURController, **options: object) -> URRobot:
    kwargs: dict[str, object] = {
        "rtde_port": fake.rtde_port,
        "script_port": fake.script_port,
        "control_rate_hz": RATE_HZ,
        "program": RELAXED,
        "stale_timeout_s": 2.0,
    }
    kwargs.update(options)
    return URRobot("127.0.0.1", name="ur_test", **kwargs)  # type: ignore[arg-type]


@pytest.fixture
def robot(fake: FakeURController) -> Iterator[URRobot]:
    with _driver(fake, gripper_port=fake.gripper_port) as driver:
        yield driver


def test_driver_satisfies_robot_driver_protocol(robot: URRobot) -> None:
    assert isinstance(robot, RobotDriver)
    assert robot.joint_names == UR_JOINT_NAMES
    assert robot.limits.names == UR_JOINT_NAMES


def test_connect_negotiates_and_starts_servo_program(robot: URRobot, fake: FakeURController) -> None:
    assert robot.connected
    assert fake.program_running
    assert ServoProgram.parse(fake.last_program) == RELAXED
    status = robot.status()
    assert status.runtime_state == RuntimeState.PLAYING
    assert status.safety_mode == SafetyMode.NORMAL
    np.testing.assert_allclose(robot.read_state().positions, fake.positions, atol=1e-9)


def test_connect_and_close_are_idempotent(fake: FakeURController) -> None:
    driver = _driver(fake)
    driver.connect()
    driver.connect()
    driver.close()
    driver.close()
    assert not driver.connected
    with pytest.raises(RobotError, match="driver is closed"):
        driver.connect()


def test_controller_refusing_protocol_2_is_one_line_error() -> None:
    with (
        FakeURController(rtde_port=0, script_port=0, protocol_versions=(1,)) as old,
        pytest.raises(RobotError, match="refused RTDE protocol 2; update it to PolyScope") as info,
    ):
        _driver(old).connect()
    assert "\n" not in str(info.value)


def test_unknown_output_variable_is_one_line_error(fake: FakeURController) -> None:
    with pytest.raises(RobotError, match=r"RTDE output setup refused actual_qq \(NOT_FOUND\)") as info:
        _driver(fake, extra_outputs=("speed_scaling", "actual_qq")).connect()
    assert "\n" not in str(info.value)


def test_registers_in_use_by_another_client_is_one_line_error(robot: URRobot, fake: FakeURController) -> None:
    with pytest.raises(RobotError, match=r"input_double_register_0 \(IN_USE\).*register_offset 24"):
        _driver(fake).connect()


def test_unreachable_controller_is_one_line_error() -> None:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    with pytest.raises(RobotError, match="cannot reach the UR controller's RTDE port"):
        URRobot("127.0.0.1", rtde_port=port, timeout_s=0.5).connect()


def test_extra_outputs_are_readable(fake: FakeURController) -> None:
    with _driver(fake, extra_outputs=("speed_scaling", "actual_TCP_pose")) as driver:
        outputs = driver.outputs()
    assert outputs["speed_scaling"] == 1.0
    assert len(outputs["actual_TCP_pose"]) == 6  # type: ignore[arg-type]


def test_state_stream_arrives_at_requested_rate_and_is_stamped(robot: URRobot) -> None:
    states = []
    first = robot.stats().packages
    _wait(lambda: robot.stats().packages >= first + 10, "10 state packages")
    for _ in range(40):
        states.append(robot.read_state())
        time.sleep(0.002)
    device = sorted({s.stamp.device_ns for s in states})
    assert len(device) >= 2
    period_ns = round(1e9 / RATE_HZ)
    assert all((b - a) % period_ns == 0 for a, b in itertools.pairwise(device))
    seqs = [s.stamp.seq for s in states]
    assert seqs == sorted(seqs)
    assert len(set(seqs)) == len(seqs)
    for state in states:
        assert state.stamp.source_id == "ur_test"
        assert 0 < state.stamp.capture_ns <= state.stamp.arrival_ns


def test_send_returns_clipped_command_and_fake_follows(robot: URRobot, fake: FakeURController) -> None:
    start = robot.read_state().positions
    want = start + np.array([0.1, -0.1, 0.1, -0.1, 0.1, 0.0])
    want[5] = 7.0  # beyond the +2 pi limit of wrist 3
    sent = robot.send(_cmd(want))
    assert sent.names == UR_JOINT_NAMES
    assert sent.positions[5] == pytest.approx(2 * np.pi)
    np.testing.assert_allclose(sent.positions[:5], want[:5])
    assert sent.stamp.capture_ns > 0

    def reached() -> bool:
        robot.send(_cmd(want))
        return bool(np.max(np.abs(fake.positions - sent.positions)) < 1e-3)

    _wait(reached, "the fake arm to reach the target")
    np.testing.assert_allclose(fake.targets, sent.positions)
    np.testing.assert_allclose(robot.status().target_q, sent.positions)


def test_send_subset_keeps_other_joints(robot: URRobot, fake: FakeURController) -> None:
    start = robot.read_state().positions
    sent = robot.send(_cmd([start[2] + 0.05, start[0] - 0.05], ("elbow_joint", "shoulder_pan_joint")))
    np.testing.assert_allclose(sent.positions, [start[2] + 0.05, start[0] - 0.05])
    expected = start.copy()
    expected[2] += 0.05
    expected[0] -= 0.05
    _wait(lambda: bool(np.allclose(fake.targets, expected)), "the fake to take the targets")


def test_send_unknown_joint_raises(robot: URRobot) -> None:
    with pytest.raises(RobotError, match=r"joint 'elbow' not found\. Available: shoulder_pan_joint"):
        robot.send(_cmd([0.0], ("elbow",)))


def test_fake_watchdog_stops_program_when_driver_stops_writing(fake: FakeURController) -> None:
    fast = ServoProgram(watchdog_cycles=25)  # 50 ms
    with _driver(fake, program=fast) as driver:
        q = driver.read_state().positions
        for _ in range(3):
            driver.send(_cmd(q))
        _wait(lambda: not fake.program_running, "the watchdog to stop the program")
        assert fake.watchdog_stops == 1
        _wait(lambda: driver.status().runtime_state == RuntimeState.STOPPED, "the driver to see the stop")
        with pytest.raises(RobotError, match="servo program stopped on the controller"):
            driver.send(_cmd(q))


def test_unarmed_program_waits_for_first_command(fake: FakeURController) -> None:
    with _driver(fake, program=ServoProgram(watchdog_cycles=5)) as driver:
        time.sleep(0.1)  # ten watchdog times without a command: not armed, so still running
        assert fake.program_running
        assert driver.connected


def test_estop_latches_and_reset_restarts(robot: URRobot, fake: FakeURController) -> None:
    q = robot.read_state().positions
    robot.send(_cmd(q + 0.01))
    robot.estop()
    assert robot.estopped
    _wait(lambda: fake.safety_mode == SafetyMode.PROTECTIVE_STOP, "the protective stop")
    assert not fake.program_running
    held = fake.targets
    sent = robot.send(_cmd(q + 0.5))
    np.testing.assert_allclose(sent.positions, q + 0.01)
    assert np.allclose(fake.targets, held)
    with pytest.raises(RobotError, match="robot is in PROTECTIVE_STOP; unlock it on the teach pendant"):
        robot.reset_estop()
    assert robot.estopped
    fake.release()
    _wait(lambda: robot.status().safety_mode == SafetyMode.NORMAL, "the release")
    robot.reset_estop()
    assert not robot.estopped
    assert fake.program_running
    target = robot.read_state().positions + 0.02
    robot.send(_cmd(target))
    _wait(lambda: bool(np.allclose(fake.targets, target)), "servoing after the reset")


def test_estop_stopj_action_leaves_robot_ready(fake: FakeURController) -> None:
    with _driver(fake, estop_action="stopj") as driver:
        driver.estop()
        _wait(lambda: not fake.program_running, "the stop program")
        assert "stopj(" in fake.last_program
        assert fake.safety_mode == SafetyMode.NORMAL


def test_robot_side_protective_stop_makes_send_raise(robot: URRobot, fake: FakeURController) -> None:
    fake.protective_stop()
    _wait(lambda: robot.status().safety_mode == SafetyMode.PROTECTIVE_STOP, "the stop to be reported")
    with pytest.raises(RobotError, match="robot is in PROTECTIVE_STOP"):
        robot.send(_cmd(robot.read_state().positions))


def test_fake_dying_raises_one_line_error_and_disconnects(fake: FakeURController) -> None:
    driver = _driver(fake)
    driver.connect()
    fake.close()
    _wait(lambda: not driver.connected, "the driver to notice")
    with pytest.raises(RobotError, match="closed the RTDE connection") as info:
        driver.read_state()
    assert "\n" not in str(info.value)
    with pytest.raises(RobotError):
        driver.send(_cmd(np.zeros(6)))
    driver.estop()  # must not raise without a connection
    driver.close()


def test_malformed_packages_from_controller_are_counted_and_dropped(
    robot: URRobot, fake: FakeURController
) -> None:
    fake.inject(rtde.pack(Command.DATA_PACKAGE, b"\x01\x02\x03"))  # wrong size for the recipe
    fake.inject(rtde.pack(0x42, b"junk"))  # no such package type
    _wait(lambda: robot.stats().malformed == 2, "both packages to be counted")
    packages = robot.stats().packages
    _wait(lambda: robot.stats().packages > packages, "the stream to go on")
    assert robot.connected
    robot.read_state()


def test_malformed_packages_to_controller_are_counted_and_dropped(fake: FakeURController) -> None:
    with socket.create_connection(("127.0.0.1", fake.rtde_port), timeout=2.0) as raw:
        raw.sendall(rtde.ProtocolVersionRequest().encode())
        reader = rtde.FrameReader()
        raw.sendall(rtde.pack(Command.DATA_PACKAGE, b"\x09\x00"))  # recipe 9 was never set up
        frames: list[rtde.Frame] = []
        while len(frames) < 2:
            frames += reader.feed(raw.recv(4096))
    assert frames[0].command == Command.REQUEST_PROTOCOL_VERSION
    error = rtde.TextMessage.decode(frames[1].payload)
    assert "unknown input recipe 9" in error.message
    assert fake.malformed_packets == 1
    assert fake.program_running is False


def test_gripper_moves_and_returns_applied_command(robot: URRobot, fake: FakeURController) -> None:
    applied = robot.send_gripper(GripperCommand(Stamp.now("test", 0), opening=0.2, max_force=235.0))
    assert applied.opening == pytest.approx(1 - 204 / 255)
    assert applied.max_force == pytest.approx(235.0)
    _wait(lambda: fake.gripper_position == 204, "the fingers to close")
    clipped = robot.send_gripper(GripperCommand(Stamp.now("test", 1), opening=1.7))
    assert clipped.opening == 1.0
    assert clipped.max_force == 0.0


def test_send_gripper_without_gripper_says_so(fake: FakeURController) -> None:
    with _driver(fake) as driver, pytest.raises(RobotError, match="no gripper on this robot"):
        driver.send_gripper(GripperCommand(Stamp.now("test", 0), opening=0.5))


def test_config_is_registered_and_builds_a_working_driver(fake: FakeURController) -> None:
    assert ROBOTS.get("ur_rtde") is URRtdeConfig
    config = ROBOTS.parse_config(
        {
            "type": "ur_rtde",
            "id": "left_arm",
            "host": "127.0.0.1",
            "rtde_port": fake.rtde_port,
            "script_port": fake.script_port,
            "watchdog_s": 0.5,
            "stale_timeout_s": 2.0,
        },
        "robots[0]",
    )
    with config.build() as driver:
        assert driver.name == "left_arm"
        assert driver.read_state().stamp.source_id == "left_arm"
    assert ServoProgram.parse(fake.last_program) == ServoProgram(watchdog_cycles=250)


def test_config_rejects_watchdog_shorter_than_two_periods() -> None:
    with pytest.raises(ValueError, match=r"watchdog_s \(0.003\) must be at least two servo periods"):
        ROBOTS.parse_config({"type": "ur_rtde", "id": "a", "host": "h", "watchdog_s": 0.003}, "robots[0]")
