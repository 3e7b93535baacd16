"""Gripper and base commands go through the safety layer (issue 11 finding 7), end to end in a control node.

A real MuJoCo arm over the in-memory bus; its driver notes what reached it (the gripper also moves
the simulated fingers) and has a wheeled base that applies what it is sent.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from telerig.bus.base import Message
from telerig.bus.memory import InMemoryBus
from telerig.bus.ticks import TICK, picking
from telerig.bus.topics import Topic
from telerig.config import load_rig
from telerig.config.safety import BaseSafetyConfig, GripperSafetyConfig
from telerig.config.schema import RigConfig
from telerig.ir import wire
from telerig.ir.types import BaseVelocity, ControllerState, GripperCommand, Sample, Stamp, now_ns
from telerig.retarget.base_drive import BaseDrive
from telerig.robots.sim.arm import MujocoArm
from telerig.runtime.control_node import BaseBinding, ControlNode, GripperBinding
from telerig.runtime.rig import RigRuntime
from telerig.runtime.streams import BASE_SENT, GRIPPER_SENT
from telerig.safety import SafetyChain, SafetySupervisor
from telerig.safety.parts import BaseLimit, GripperLimit

pytestmark = pytest.mark.sim

TOPIC = str(Topic("t", "vr0", "right_controller"))


class _Arm(MujocoArm):
    """The sim arm with a wheeled base; notes every gripper and base command that reaches it."""

    def __init__(self) -> None:
        super().__init__(name="arm0")
        self.gripper_in: list[GripperCommand] = []
        self.base_in: list[BaseVelocity] = []
        self.base_fails = False

    def send_gripper(self, command: GripperCommand) -> GripperCommand:
        self.gripper_in.append(command)
        return super().send_gripper(command)

    def send_base(self, command: BaseVelocity) -> BaseVelocity:
        if self.base_fails:
            raise ConnectionError("base controller unreachable")
        self.base_in.append(command)
        return command


class _Grip:
    """A gripper retargeter (a third-party plug-in, say) that emits whatever it is told."""

    def __init__(self, opening: float, max_force: float = 0.0) -> None:
        self.opening = opening
        self.max_force = max_force

    def __call__(self, sample: Sample) -> GripperCommand | None:
        return GripperCommand(sample.stamp, self.opening, self.max_force)


class _NanDrive(BaseDrive):
    """A base drive gone wrong: NaN forward speed while the button is held."""

    def __call__(self, sample: Sample) -> BaseVelocity | None:
        command = super().__call__(sample)
        return (
            None if command is None or command.vx == 0.0 else BaseVelocity(command.stamp, math.nan, 0.0, 0.0)
        )


def _publish(bus: InMemoryBus, seconds: float, buttons: frozenset[str] = frozenset()) -> None:
    t0 = time.monotonic()
    seq = 0
    while time.monotonic() - t0 < seconds:
        seq += 1
        t = now_ns()
        sample = ControllerState(
            Stamp("vr0", seq, t, t),
            "right",
            np.array([0.4, 0.0, 1.1]),
            np.array([1.0, 0, 0, 0]),
            "op",
            buttons=buttons,
        )
        bus.publish(TOPIC, wire.encode(sample))
        time.sleep(0.01)


def _wait_until(predicate: Callable[[], bool], timeout_s: float = 3.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return False


Rig = tuple[ControlNode, InMemoryBus, _Arm, list[Sample]]


@pytest.fixture
def make() -> Iterator[Callable[..., Rig]]:
    nodes: list[tuple[ControlNode, _Arm]] = []

    def build(
        *,
        grip: _Grip | None = None,
        drive: BaseDrive | None = None,
        gripper: GripperLimit | None = None,
        base: BaseLimit | None = None,
    ) -> Rig:
        arm = _Arm()
        arm.connect()
        bus = InMemoryBus()
        sent: list[Sample] = []

        def keep(message: Message) -> None:
            sent.append(wire.decode(message.payload))

        bus.subscribe(str(Topic("t", "arm0", TICK)), picking({GRIPPER_SENT, BASE_SENT}, keep))
        kw = {k: v for k, v in (("gripper", gripper), ("base", base)) if v is not None}
        safety = SafetySupervisor("pause_affected").add("arm0", arm, SafetyChain.default(arm.limits), **kw)
        node = ControlNode(
            "t",
            arm,
            safety,
            bus,
            control_rate_hz=100.0,
            gripper=None if grip is None else GripperBinding(TOPIC, grip),
            base=None if drive is None else BaseBinding(TOPIC, drive),
        )
        node.start()
        nodes.append((node, arm))
        return node, bus, arm, sent

    yield build
    for node, arm in nodes:
        node.stop()
        arm.close()


def _drive(max_linear_m_s: float = 0.3) -> BaseDrive:
    return BaseDrive(
        forward_button="b", backward_button="a", max_linear_m_s=max_linear_m_s, input_timeout_s=0.1
    )


def test_a_nan_gripper_command_is_counted_and_never_reaches_the_gripper(make: Callable[..., Rig]) -> None:
    control, bus, arm, sent = make(grip=_Grip(math.nan))
    _publish(bus, 0.2)
    assert _wait_until(lambda: control.safety.counts["invalid_input"] >= 5)
    assert (arm.gripper_in, sent) == ([], [])


def test_a_gripper_opening_beyond_its_range_is_clamped(make: Callable[..., Rig]) -> None:
    _, bus, arm, sent = make(grip=_Grip(1.7, max_force=-5.0))
    _publish(bus, 0.2)
    assert _wait_until(lambda: len(sent) >= 5)
    assert {(c.opening, c.max_force) for c in arm.gripper_in} == {(1.0, 0.0)}


def test_the_grip_force_is_capped_by_the_robots_gripper_settings(make: Callable[..., Rig]) -> None:
    limit = GripperLimit.from_config(GripperSafetyConfig(max_force_n=40.0))
    _, bus, arm, sent = make(grip=_Grip(0.5, max_force=500.0), gripper=limit)
    _publish(bus, 0.2)
    assert _wait_until(lambda: len(sent) >= 5)
    assert {c.max_force for c in arm.gripper_in} == {40.0}


def test_an_estopped_robot_never_moves_its_gripper(make: Callable[..., Rig]) -> None:
    control, bus, arm, sent = make(grip=_Grip(0.2))
    control.estop("operator")
    _publish(bus, 0.2)
    assert (arm.gripper_in, sent) == ([], [])


def test_the_base_speed_is_limited_to_the_robots_base_settings(make: Callable[..., Rig]) -> None:
    limit = BaseLimit.from_config(BaseSafetyConfig(max_linear_m_s=0.5))
    control, bus, arm, _ = make(drive=_drive(3.0), base=limit)
    _publish(bus, 0.5, frozenset({"b"}))
    assert _wait_until(lambda: len(arm.base_in) > 10)
    assert max(c.vx for c in arm.base_in) == pytest.approx(0.5)
    assert control.safety.counts["velocity_limit"] > 0


def test_the_base_accelerates_within_its_limit(make: Callable[..., Rig]) -> None:
    _, bus, arm, _ = make(drive=_drive(0.8))
    _publish(bus, 0.6, frozenset({"b"}))
    assert _wait_until(lambda: len(arm.base_in) > 10)
    moving = [c.vx for c in arm.base_in if c.vx > 0.0]
    steps = np.diff([0.0, *moving])  # from rest
    # Default 2 m/s^2, credited for at most 0.1 s between commands: 0.2 m/s per command at most.
    assert float(steps.max()) <= 0.2 + 1e-9
    assert moving[-1] == pytest.approx(0.8)


def test_a_nan_base_command_stops_the_base_and_is_counted(make: Callable[..., Rig]) -> None:
    control, bus, arm, _ = make(drive=_NanDrive(forward_button="b", backward_button="a"))
    _publish(bus, 0.2, frozenset({"b"}))
    assert _wait_until(lambda: control.safety.counts["invalid_input"] >= 5)
    assert {(c.vx, c.vy, c.wz) for c in arm.base_in} == {(0.0, 0.0, 0.0)}


def test_a_failing_base_faults_the_robot_naming_its_base(make: Callable[..., Rig]) -> None:
    control, bus, arm, _ = make(drive=_drive())
    arm.base_fails = True
    _publish(bus, 0.2, frozenset({"b"}))
    assert _wait_until(lambda: control.safety.estopped)
    event = control.safety.estop_event
    assert event is not None
    assert (event.code, "base" in event.reason, control.stats.tick_faults) == ("driver_fault", True, 0)


@pytest.mark.broker
@pytest.mark.slow
def test_the_rigs_gripper_and_base_settings_reach_the_robots_safety(tmp_path: Path) -> None:
    raw = load_rig("demo").with_isolation("threads").model_dump(mode="json", exclude_none=True)
    raw["cameras"] = []
    raw["safety"]["robots"] = {"arm0": {"gripper": {"max_force_n": 40.0}, "base": {"max_linear_m_s": 0.4}}}
    with RigRuntime(RigConfig.model_validate(raw), data_root=tmp_path) as runtime:
        assert runtime.supervisor is not None
        robot = runtime.supervisor.robots["arm0"]
        assert (robot.gripper.max_force_n, robot.base.max_linear_m_s) == (40.0, 0.4)
