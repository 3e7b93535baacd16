"""Control node over the in-memory bus: clutched relative arm, published aids, base stop on input loss."""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest

from telerig.bus.base import Message
from telerig.bus.memory import InMemoryBus
from telerig.bus.ticks import TICK, picking
from telerig.bus.topics import Topic
from telerig.ir import wire
from telerig.ir.types import BaseVelocity, ControllerState, Stamp, now_ns
from telerig.retarget.arm_ik import ArmIK
from telerig.retarget.base_drive import BaseDrive
from telerig.retarget.config import ArmPoseConfig, FixtureConfig, FixturesConfig, MotionScaleConfig
from telerig.robots.sim.arm import MujocoArm
from telerig.runtime.control_node import AidBinding, BaseBinding, ControlNode, JointsBinding
from telerig.runtime.session import SessionState, SessionStatus
from telerig.runtime.streams import BASE_SENT
from telerig.safety import SafetyChain

pytestmark = pytest.mark.sim

TOPIC = str(Topic("t", "vr0", "right_controller"))
HAND0 = np.array([0.4, 0.0, 1.1])
IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


class _Publisher:
    def __init__(self, bus: InMemoryBus) -> None:
        self.bus = bus
        self.seq = 0

    def run(
        self, seconds: float, pose: Callable[[float], np.ndarray], buttons: frozenset[str] = frozenset()
    ) -> None:
        t0 = time.monotonic()
        while (t := time.monotonic() - t0) < seconds:
            self.seq += 1
            stamp = Stamp("vr0", self.seq, now_ns(), now_ns())
            sample = ControllerState(stamp, "right", pose(t), IDENTITY, "operator", buttons=buttons)
            self.bus.publish(TOPIC, wire.encode(sample))
            time.sleep(0.01)


def _wait_until(predicate: Callable[[], bool], timeout_s: float = 3.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return False


@pytest.fixture
def relative() -> Iterator[tuple[ControlNode, InMemoryBus, MujocoArm, dict[str, Any]]]:
    arm = MujocoArm(name="arm0")
    arm.connect()
    bus = InMemoryBus()
    retargeter = ArmPoseConfig(
        mode="relative",
        clutch_button="grip",
        scale=MotionScaleConfig(up_button="b", down_button="a"),
        fixtures=FixturesConfig(
            options=[
                FixtureConfig(name="free", kind="free"),
                FixtureConfig(name="lift", kind="axis", axis=(0, 0, 1)),
            ],
            cycle_button="thumbstick",
        ),
    ).build(ArmIK(arm.scene), arm.joint_names, frame="arm0/base")
    assert retargeter.motion_scale is not None
    assert retargeter.fixtures is not None
    published: dict[str, Any] = {}

    def keep(message: Message) -> None:
        published[message.topic.rsplit("/", 1)[1]] = json.loads(message.payload)

    bus.subscribe(str(Topic("t", "arm0", "motion_scale")), keep)
    bus.subscribe(str(Topic("t", "arm0", "fixture")), keep)
    node = ControlNode(
        "t",
        arm,
        SafetyChain.default(arm.limits),
        bus,
        control_rate_hz=100.0,
        joints=JointsBinding(TOPIC, retargeter),
        aids=[AidBinding(TOPIC, retargeter.motion_scale), AidBinding(TOPIC, retargeter.fixtures)],
    )
    node.start()
    yield node, bus, arm, published
    node.stop()
    arm.close()


def test_clutch_moves_the_sim_arm_only_while_held(
    relative: tuple[ControlNode, InMemoryBus, MujocoArm, dict[str, Any]],
) -> None:
    control, bus, arm, _ = relative
    fk = ArmIK(arm.scene)  # the node's IK belongs to the control thread

    def ee() -> np.ndarray:
        return fk.forward(arm.read_state().positions)[0]

    home = ee()
    pub = _Publisher(bus)
    pub.run(0.4, lambda t: HAND0 + np.array([0.0, 0.0, 0.3 * t]))  # clutch up: hand motion is ignored
    np.testing.assert_allclose(ee(), home, atol=0.003)

    grip = frozenset({"grip"})
    pub.run(0.5, lambda t: HAND0 + np.array([0.0, 0.0, 0.1 * min(t, 0.4)]), grip)
    pub.run(1.0, lambda t: HAND0 + np.array([0.0, 0.0, 0.04]), grip)
    np.testing.assert_allclose(ee(), home + np.array([0.0, 0.0, 0.04]), atol=0.004)
    assert control.stats.applied > 100

    held = ee()
    pub.run(0.5, lambda t: HAND0 + np.array([0.1, 0.0, 0.04 + 0.2 * t]))  # released: repositioning the hand
    np.testing.assert_allclose(ee(), held, atol=0.003)


def test_aids_publish_their_state_and_follow_buttons_and_commands(
    relative: tuple[ControlNode, InMemoryBus, MujocoArm, dict[str, Any]],
) -> None:
    control, bus, _, published = relative
    assert _wait_until(lambda: "motion_scale" in published and "fixture" in published)
    assert published["motion_scale"]["scale"] == 1.0
    assert published["fixture"]["name"] == "free"
    pub = _Publisher(bus)
    pub.run(0.05, lambda t: HAND0, frozenset({"b"}))
    pub.run(0.05, lambda t: HAND0)
    pub.run(0.05, lambda t: HAND0, frozenset({"b"}))
    assert _wait_until(lambda: published["motion_scale"]["scale"] == 4.0)
    bus.publish(str(Topic("t", "arm0", "fixture_command")), b"lift")
    pub.run(0.05, lambda t: HAND0)
    assert _wait_until(lambda: published["fixture"]["name"] == "lift")
    assert published["fixture"]["axis"] == [0.0, 0.0, 1.0]
    assert published["fixture"]["frame"] == "arm0/base"
    bus.publish(str(Topic("t", "arm0", "fixture_command")), b"sideways")
    pub.run(0.05, lambda t: HAND0)
    assert _wait_until(lambda: control.stats.bad_commands == 1)


class _MobileArm(MujocoArm):
    """The sim arm with a recording wheeled base (the MobileBase capability)."""

    def __init__(self) -> None:
        super().__init__(name="mobile0")
        self.base_commands: list[BaseVelocity] = []

    def send_base(self, command: BaseVelocity) -> BaseVelocity:
        self.base_commands.append(command)
        return command


@pytest.fixture
def mobile() -> Iterator[tuple[ControlNode, InMemoryBus, _MobileArm, list[BaseVelocity]]]:
    robot = _MobileArm()
    robot.connect()
    bus = InMemoryBus()
    sent: list[BaseVelocity] = []

    def keep(message: Message) -> None:
        sample = wire.decode(message.payload)
        assert isinstance(sample, BaseVelocity)
        sent.append(sample)

    bus.subscribe(str(Topic("t", "mobile0", TICK)), picking({BASE_SENT}, keep))
    drive = BaseDrive(forward_button="b", backward_button="a", max_linear_m_s=0.3, input_timeout_s=0.1)
    node = ControlNode(
        "t",
        robot,
        SafetyChain.default(robot.limits),
        bus,
        control_rate_hz=100.0,
        base=BaseBinding(TOPIC, drive),
    )
    node.start()
    yield node, bus, robot, sent
    node.stop()
    robot.close()


def test_buttons_drive_the_base_and_input_loss_zeroes_it(
    mobile: tuple[ControlNode, InMemoryBus, _MobileArm, list[BaseVelocity]],
) -> None:
    control, bus, robot, sent = mobile
    _Publisher(bus).run(0.2, lambda t: HAND0, frozenset({"b"}))
    assert _wait_until(lambda: len(robot.base_commands) > 5)
    assert robot.base_commands[-1].vx == pytest.approx(0.3)
    assert _wait_until(lambda: robot.base_commands[-1].vx == 0.0, timeout_s=2.0)
    last = robot.base_commands[-1]
    assert (last.vx, last.vy, last.wz) == (0.0, 0.0, 0.0)
    assert control.stats.base_stops == 1
    assert _wait_until(lambda: bool(sent) and sent[-1].vx == 0.0)


def test_estop_zeroes_the_base(
    mobile: tuple[ControlNode, InMemoryBus, _MobileArm, list[BaseVelocity]],
) -> None:
    control, bus, robot, _ = mobile
    pub = _Publisher(bus)
    pub.run(0.15, lambda t: HAND0, frozenset({"b"}))
    control.estop("test")
    pub.run(0.15, lambda t: HAND0, frozenset({"b"}))
    assert robot.base_commands[-1].vx == 0.0
    assert all(c.vx == 0.0 for c in robot.base_commands[-5:])


def test_base_binding_needs_a_mobile_base() -> None:
    arm = MujocoArm(name="arm0")
    drive = BaseDrive(forward_button="b", backward_button="a")
    with pytest.raises(ValueError, match="has no mobile base"):
        ControlNode(
            "t",
            arm,
            SafetyChain.default(arm.limits),
            InMemoryBus(),
            control_rate_hz=100.0,
            base=BaseBinding(TOPIC, drive),
        )


def test_a_paused_device_holds_the_arm_and_its_resume_re_anchors_where_the_arm_is(
    relative: tuple[ControlNode, InMemoryBus, MujocoArm, dict[str, Any]],
) -> None:
    control, bus, arm, _ = relative
    fk = ArmIK(arm.scene)

    def ee() -> np.ndarray:
        return fk.forward(arm.read_state().positions)[0]

    def session(paused: tuple[str, ...]) -> None:
        status = SessionStatus(rig="t", state=SessionState.RECORDING, session_id="s", paused_devices=paused)
        bus.publish(str(Topic("t", "coordinator", "session")), status.model_dump_json().encode())

    home = ee()
    grip = frozenset({"grip"})
    pub = _Publisher(bus)
    pub.run(0.6, lambda t: HAND0 + np.array([0.0, 0.0, 0.05 * min(t / 0.3, 1.0)]), grip)
    np.testing.assert_allclose(ee(), home + np.array([0.0, 0.0, 0.05]), atol=0.004)
    held = ee()
    session(("vr0",))
    assert _wait_until(lambda: bool(control.paused_topics))
    # Paused with the clutch still held: the hand goes 10 cm further up, the arm holds.
    pub.run(0.6, lambda t: HAND0 + np.array([0.0, 0.0, 0.05 + 0.1 * min(t / 0.3, 1.0)]), grip)
    np.testing.assert_allclose(ee(), held, atol=0.003)
    assert control.safety.status in ("ok", "limited")  # held as fresh input, not a watchdog stop
    session(())
    assert _wait_until(lambda: not control.paused_topics)
    # Resumed, clutch still held: re-anchored where the arm is (no jump to the hand's new height),
    # then the arm follows the hand's motion from there.
    pub.run(0.8, lambda t: HAND0 + np.array([0.0, 0.0, 0.15]), grip)
    np.testing.assert_allclose(ee(), held, atol=0.003)
    pub.run(1.2, lambda t: HAND0 + np.array([0.0, 0.0, 0.15 - 0.04 * min(t / 0.3, 1.0)]), grip)
    np.testing.assert_allclose(ee(), held - np.array([0.0, 0.0, 0.04]), atol=0.005)
    assert control.stats.paused_inputs > 20
