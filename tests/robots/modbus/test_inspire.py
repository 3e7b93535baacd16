"""Tests of the Inspire hand driver against the fake Modbus TCP hand, over real sockets."""

from __future__ import annotations

import math
import socket
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from telerig.errors import RobotError
from telerig.ir.types import GripperCommand, JointCommand, Stamp
from telerig.robots.base import RobotDriver
from telerig.robots.modbus import FakeInspireHand, InspireHand
from telerig.robots.modbus.registers import INSPIRE, INSPIRE_JOINTS, InspireError


def wait_for(predicate: Callable[[], bool], timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError("condition not met within the timeout")
        time.sleep(0.01)


def cmd(names: tuple[str, ...], positions: object) -> JointCommand:
    return JointCommand(Stamp.now("test", 0), names, np.asarray(positions, dtype=np.float64))


@pytest.fixture
def fake() -> Iterator[FakeInspireHand]:
    with FakeInspireHand(full_stroke_s=0.2) as running:
        yield running


@pytest.fixture
def hand(fake: FakeInspireHand) -> Iterator[InspireHand]:
    with InspireHand("127.0.0.1", fake.port, timeout_s=0.25, stale_after_s=1.0) as driver:
        yield driver


def test_is_a_robot_driver(hand: InspireHand) -> None:
    assert isinstance(hand, RobotDriver)


def test_state_reads_open_hand_stamped_at_request(hand: InspireHand) -> None:
    state = hand.read_state()
    assert state.names == ("little", "ring", "middle", "index", "thumb_bend", "thumb_rotation")
    np.testing.assert_allclose(state.positions, [j.angle_at_1000 for j in INSPIRE_JOINTS])
    assert 0 < state.stamp.capture_ns <= state.stamp.arrival_ns
    assert state.efforts.shape == (6,)


def test_connect_and_close_are_idempotent(fake: FakeInspireHand) -> None:
    driver = InspireHand("127.0.0.1", fake.port)
    driver.connect()
    driver.connect()
    assert driver.connected
    driver.close()
    driver.close()
    assert not driver.connected
    with pytest.raises(RobotError, match="closed"):
        driver.read_state()


def test_send_moves_the_fake_finger(hand: InspireHand, fake: FakeInspireHand) -> None:
    sent = hand.send(cmd(("index",), [1.0]))
    target = int(hand.to_units(np.full(6, 1.0))[3])
    wait_for(lambda: fake.angles[3] == target)
    assert fake.angles[:3] == [1000, 1000, 1000]
    wait_for(lambda: abs(hand.read_state().positions[3] - sent.positions[0]) < 1e-9)


def test_units_map_the_manual_ranges_linearly(hand: InspireHand) -> None:
    lo = np.array([j.angle_at_0 for j in INSPIRE_JOINTS])
    hi = np.array([j.angle_at_1000 for j in INSPIRE_JOINTS])
    np.testing.assert_array_equal(hand.to_units(lo), [0] * 6)
    np.testing.assert_array_equal(hand.to_units(hi), [1000] * 6)
    np.testing.assert_array_equal(hand.to_units((lo + hi) / 2), [500] * 6)
    assert hand.to_angles(np.array([0] * 6))[4] == pytest.approx(math.radians(-13.0))


def test_send_returns_the_quantised_target(hand: InspireHand) -> None:
    j = INSPIRE_JOINTS[0]
    step = (j.angle_at_1000 - j.angle_at_0) / INSPIRE.UNIT_MAX
    asked = j.angle_at_0 + 400.4 * step
    sent = hand.send(cmd(("little",), [asked]))
    assert sent.positions[0] == pytest.approx(j.angle_at_0 + 400 * step)
    assert sent.stamp.source_id == "inspire_hand"


def test_send_clips_to_the_limits(hand: InspireHand, fake: FakeInspireHand) -> None:
    sent = hand.send(cmd(("middle", "thumb_rotation"), [-5.0, 10.0]))
    np.testing.assert_allclose(sent.positions, [hand.limits.lower[2], hand.limits.upper[5]])
    wait_for(lambda: fake.angles[2] == 0)


def test_limits_are_exposed_per_joint(hand: InspireHand) -> None:
    limits = hand.limits
    assert limits.names == hand.joint_names
    assert limits.lower[4] == pytest.approx(math.radians(-13.0))
    assert limits.upper[0] == pytest.approx(math.radians(176.7))
    assert np.all(limits.velocity > 0)


def test_unknown_joint_is_rejected_with_the_valid_names(hand: InspireHand) -> None:
    with pytest.raises(RobotError, match=r"joint 'pinky' not found\. Available: little, ring"):
        hand.send(cmd(("pinky",), [1.0]))


def test_error_register_is_surfaced_and_cleared(hand: InspireHand, fake: FakeInspireHand) -> None:
    fake.inject_error(3, InspireError.OVER_CURRENT | InspireError.LOCKED_ROTOR)
    wait_for(lambda: hand.health().faulted)
    health = hand.health()
    assert health.errors == (0, 0, 0, 5, 0, 0)
    assert health.describe(hand.joint_names) == "index: LOCKED_ROTOR|OVER_CURRENT"
    assert health.status[3] == 7
    hand.clear_errors()
    wait_for(lambda: not hand.health().faulted)


def test_force_readback_when_a_finger_is_blocked(hand: InspireHand, fake: FakeInspireHand) -> None:
    fake.block(3, 600)
    hand.send(cmd(("index",), [INSPIRE_JOINTS[3].angle_at_0]))
    wait_for(lambda: hand.read_state().efforts[3] > 0)
    assert hand.read_state().efforts[3] == pytest.approx(500 * INSPIRE.FORCE_UNIT_N)
    assert fake.angles[3] == 600
    assert hand.health().status[3] == 3


def test_gripper_command_closes_fingers_and_keeps_thumb_rotation(
    hand: InspireHand, fake: FakeInspireHand
) -> None:
    applied = hand.send_gripper(GripperCommand(Stamp.now("test", 0), opening=0.25, max_force=2.0))
    assert applied.opening == pytest.approx(0.25)
    assert applied.max_force == pytest.approx(round(2.0 / INSPIRE.FORCE_UNIT_N) * INSPIRE.FORCE_UNIT_N)
    wait_for(lambda: fake.angles == [250, 250, 250, 250, 250, 1000])


def test_estop_holds_position_and_ignores_commands(hand: InspireHand, fake: FakeInspireHand) -> None:
    hand.send(cmd(("index",), [INSPIRE_JOINTS[3].angle_at_0]))
    wait_for(lambda: fake.angles[3] < 900)
    hand.estop()
    assert hand.estopped
    sent = hand.send(cmd(("index",), [INSPIRE_JOINTS[3].angle_at_1000]))
    held = int(hand.to_units(np.full(6, sent.positions[0]))[3])
    assert held < 1000
    wait_for(lambda: fake.angles[3] == held)
    time.sleep(0.2)  # a command that got through would have moved the finger by now
    assert fake.angles[3] == held
    hand.reset_estop()
    hand.send(cmd(("index",), [INSPIRE_JOINTS[3].angle_at_1000]))
    wait_for(lambda: fake.angles[3] == 1000)


def test_exception_responses_are_counted_not_fatal(hand: InspireHand, fake: FakeInspireHand) -> None:
    fake.fail_next(5)
    wait_for(lambda: hand.stats().exception_responses >= 5)
    assert hand.connected
    hand.send(cmd(("ring",), [1.0]))
    wait_for(lambda: fake.angles[1] < 1000)


def test_malformed_frames_are_counted_not_fatal(hand: InspireHand, fake: FakeInspireHand) -> None:
    fake.garble_next(2)
    wait_for(lambda: hand.stats().failures >= 1)
    polls = hand.stats().polls
    wait_for(lambda: hand.stats().polls > polls + 3)
    assert hand.connected


def test_peer_death_raises_one_line_robot_error(hand: InspireHand, fake: FakeInspireHand) -> None:
    fake.stop()
    wait_for(lambda: not hand.connected)
    with pytest.raises(RobotError, match=r"^inspire_hand: device gone: .*connect\(\) again$") as err:
        hand.read_state()
    assert "\n" not in str(err.value)
    with pytest.raises(RobotError, match="device gone"):
        hand.send(cmd(("index",), [1.0]))


def test_connect_to_nothing_raises_one_line_robot_error() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    driver = InspireHand("127.0.0.1", port, timeout_s=0.05)
    with pytest.raises(
        RobotError, match=rf"^inspire_hand: cannot open Inspire hand at 127.0.0.1:{port}"
    ) as err:
        driver.connect()
    assert "\n" not in str(err.value)
    assert not driver.connected


def test_fake_on_a_taken_port_fails_to_start_with_one_robot_error() -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        fake = FakeInspireHand(port=taken.getsockname()[1])
        with pytest.raises(RobotError, match="FakeInspireHand failed to start"):
            fake.start()
        fake.stop()  # idempotent after a failed start
