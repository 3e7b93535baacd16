"""Tests of the DH gripper driver against the fake RTU gripper, over a real pty pair (and RTU over TCP)."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from telerig.errors import RobotError
from telerig.ir.types import GripperCommand, JointCommand, Stamp
from telerig.robots.base import GripperSensor, RobotDriver
from telerig.robots.modbus import DHGripper, FakeDHGripper
from telerig.robots.modbus.registers import DHGripState, DHInitState


def wait_for(predicate: Callable[[], bool], timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError("condition not met within the timeout")
        time.sleep(0.01)


def grip(opening: float, max_force: float = 0.0) -> GripperCommand:
    return GripperCommand(Stamp.now("test", 0), opening, max_force)


@pytest.fixture
def fake() -> Iterator[FakeDHGripper]:
    with FakeDHGripper(full_stroke_s=0.2, init_s=0.05) as running:
        yield running


@pytest.fixture
def gripper(fake: FakeDHGripper) -> Iterator[DHGripper]:
    with DHGripper(device=fake.device, timeout_s=0.25, stale_after_s=1.0, poll_rate_hz=100) as driver:
        wait_for(lambda: driver.status().init_state == DHInitState.INITIALIZED)
        yield driver


def test_is_a_one_dof_robot_driver(gripper: DHGripper) -> None:
    assert isinstance(gripper, RobotDriver)
    assert gripper.joint_names == ("finger",)
    assert gripper.limits.upper[0] == pytest.approx(0.095)


def test_connect_initializes_and_reads_the_open_gripper(gripper: DHGripper, fake: FakeDHGripper) -> None:
    wait_for(lambda: gripper.read_state().positions[0] == pytest.approx(0.095))
    state = gripper.read_state()
    assert state.names == ("finger",)
    assert 0 < state.stamp.capture_ns <= state.stamp.arrival_ns
    assert fake.position == 1000


def test_send_gripper_moves_the_fake_and_quantises_to_permille(
    gripper: DHGripper, fake: FakeDHGripper
) -> None:
    applied = gripper.send_gripper(grip(0.25049))
    assert applied.opening == 0.25
    wait_for(lambda: fake.position == 250)
    wait_for(lambda: gripper.read_state().positions[0] == pytest.approx(0.25 * 0.095))
    assert gripper.status().grip_state == DHGripState.REACHED


def test_joint_command_in_metres_is_clipped_to_the_stroke(gripper: DHGripper, fake: FakeDHGripper) -> None:
    sent = gripper.send(JointCommand(Stamp.now("test", 0), ("finger",), np.array([-0.5])))
    assert sent.positions[0] == 0.0
    wait_for(lambda: fake.position == 0)
    sent = gripper.send(JointCommand(Stamp.now("test", 0), ("finger",), np.array([0.04])))
    assert sent.positions[0] == pytest.approx(421 / 1000 * 0.095)


def test_unknown_joint_is_rejected(gripper: DHGripper) -> None:
    with pytest.raises(RobotError, match=r"joint 'wrist' not found\. Available: finger"):
        gripper.send(JointCommand(Stamp.now("test", 0), ("wrist",), np.array([0.0])))


def test_read_gripper_reports_the_polled_opening(gripper: DHGripper, fake: FakeDHGripper) -> None:
    assert isinstance(gripper, GripperSensor)
    gripper.send_gripper(grip(0.4))
    wait_for(lambda: fake.position == 400)
    wait_for(lambda: gripper.read_gripper().opening == pytest.approx(0.4))
    measured = gripper.read_gripper()
    assert 0 < measured.stamp.capture_ns <= measured.stamp.arrival_ns


def test_max_force_sets_the_force_percentage(gripper: DHGripper) -> None:
    applied = gripper.send_gripper(grip(0.5, max_force=80.0))
    assert applied.max_force == pytest.approx(80.0)
    assert gripper.send_gripper(grip(0.5, max_force=1.0)).max_force == pytest.approx(0.2 * 160.0)


def test_object_caught_is_reported(gripper: DHGripper, fake: FakeDHGripper) -> None:
    fake.place_object(400)
    gripper.send_gripper(grip(0.0))
    wait_for(lambda: gripper.status().object_caught)
    assert fake.position == 400


def test_estop_holds_position_and_ignores_commands(gripper: DHGripper, fake: FakeDHGripper) -> None:
    gripper.send_gripper(grip(0.0))
    wait_for(lambda: fake.position < 900)
    gripper.estop()
    held = gripper.send_gripper(grip(1.0)).opening
    assert held < 1.0
    wait_for(lambda: fake.position == round(held * 1000))
    time.sleep(0.2)  # a command that got through would have moved the fingers by now
    assert fake.position == round(held * 1000)
    gripper.reset_estop()
    gripper.send_gripper(grip(1.0))
    wait_for(lambda: fake.position == 1000)


def test_exception_responses_are_counted_not_fatal(gripper: DHGripper, fake: FakeDHGripper) -> None:
    fake.fail_next(3)
    wait_for(lambda: gripper.stats().exception_responses >= 3)
    gripper.send_gripper(grip(0.5))
    wait_for(lambda: fake.position == 500)
    assert gripper.connected


def test_bad_crc_frames_are_counted_not_fatal(gripper: DHGripper, fake: FakeDHGripper) -> None:
    fake.garble_next(2)
    wait_for(lambda: gripper.stats().failures >= 1)
    gripper.send_gripper(grip(0.3))
    wait_for(lambda: fake.position == 300)
    assert gripper.connected


def test_silent_peer_raises_one_line_robot_error(gripper: DHGripper, fake: FakeDHGripper) -> None:
    fake.stop()
    wait_for(lambda: not gripper.connected)
    with pytest.raises(RobotError, match=r"^dh_gripper: device gone: .*no valid answer for") as err:
        gripper.read_state()
    assert "\n" not in str(err.value)


def test_rtu_over_tcp_gateway() -> None:
    with (
        FakeDHGripper(transport="tcp", device_id=7, full_stroke_s=0.2, init_s=0.05) as fake,
        DHGripper(transport="rtu_over_tcp", port=fake.port, device_id=7, timeout_s=0.25) as driver,
    ):
        wait_for(lambda: driver.status().init_state == DHInitState.INITIALIZED)
        driver.send_gripper(grip(0.6))
        wait_for(lambda: fake.position == 600)


def test_connect_returns_once_the_gripper_is_initialized() -> None:
    with (
        FakeDHGripper(transport="tcp", full_stroke_s=0.2, init_s=0.3) as fake,
        DHGripper(transport="rtu_over_tcp", port=fake.port, timeout_s=0.25) as driver,
    ):
        # Before initialization the gripper reads closed; the first read must be its real opening.
        assert driver.status().init_state == DHInitState.INITIALIZED
        assert driver.read_state().positions[0] == pytest.approx(0.095)


def test_connect_gives_up_on_an_initialization_that_never_ends() -> None:
    with (
        FakeDHGripper(transport="tcp", init_s=30.0) as fake,
        pytest.raises(RobotError, match=r"did not finish initializing within 0\.2 s"),
    ):
        DHGripper(transport="rtu_over_tcp", port=fake.port, timeout_s=0.05, init_timeout_s=0.2).connect()
