"""Control node over the in-memory bus: malformed input is counted and dropped, stale input stops the arm."""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from telerig.bus.memory import InMemoryBus
from telerig.bus.topics import Topic
from telerig.config.schema import AlignmentConfig
from telerig.devices.scripted import ScriptedVRController
from telerig.ir import wire
from telerig.ir.types import now_ns
from telerig.retarget.alignment import Alignment
from telerig.retarget.arm import AbsolutePoseRetargeter
from telerig.retarget.arm_ik import ArmIK
from telerig.retarget.gripper import TriggerGripper
from telerig.robots.sim.arm import MujocoArm
from telerig.runtime.control_node import ControlNode, GripperBinding, JointsBinding
from telerig.safety import SafetyChain

pytestmark = pytest.mark.sim

TOPIC = str(Topic("t", "vr0", "right_controller"))


@pytest.fixture
def node() -> Iterator[tuple[ControlNode, InMemoryBus, MujocoArm]]:
    arm = MujocoArm(name="arm0")
    arm.connect()
    bus = InMemoryBus()
    ik = ArmIK(arm.scene)
    home_p, _ = ik.forward(arm.scene.home)
    alignment = Alignment.from_config(
        AlignmentConfig(operator_origin=(0.40, 0.0, 1.10), robot_origin=tuple(home_p.tolist()))
    )
    node = ControlNode(
        "t",
        arm,
        SafetyChain.default(arm.limits),
        bus,
        control_rate_hz=100.0,
        joints=JointsBinding(TOPIC, AbsolutePoseRetargeter(alignment, ik, arm.joint_names)),
        gripper=GripperBinding(TOPIC, TriggerGripper()),
    )
    node.start()
    yield node, bus, arm
    node.stop()
    arm.close()


def _wait_until(predicate: Callable[[], bool], timeout_s: float = 3.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return False


def _publish_for(bus: InMemoryBus, device: ScriptedVRController, seconds: float, start_seq: int = 0) -> int:
    seq = start_seq
    t0 = time.monotonic()
    while time.monotonic() - t0 < seconds:
        sample = device.sample_at(0.0, seq=seq)
        t = now_ns()
        stamp = dataclasses.replace(sample.stamp, device_ns=t, capture_ns=t)
        bus.publish(TOPIC, wire.encode(dataclasses.replace(sample, stamp=stamp)))
        seq += 1
        time.sleep(0.01)
    return seq


def test_malformed_message_is_counted_and_dropped(node: tuple[ControlNode, InMemoryBus, MujocoArm]) -> None:
    control, bus, _ = node
    bus.publish(TOPIC, b"\x00\xffnot a protobuf")
    device = ScriptedVRController(home=(0.40, 0.0, 1.10))
    _publish_for(bus, device, 0.3)
    assert _wait_until(lambda: control.stats.applied > 0)
    assert control.stats.decode_errors == 1


def test_fresh_input_drives_the_arm_and_latency_is_measured(
    node: tuple[ControlNode, InMemoryBus, MujocoArm],
) -> None:
    control, bus, _ = node
    _publish_for(bus, ScriptedVRController(home=(0.40, 0.0, 1.10)), 0.5)
    assert control.stats.applied > 20
    summary = control.latency.summary()
    assert summary.count == control.stats.applied
    assert summary.p50_ms > 0


def test_stale_input_stops_the_arm_at_its_measured_position(
    node: tuple[ControlNode, InMemoryBus, MujocoArm],
) -> None:
    control, bus, arm = node
    _publish_for(bus, ScriptedVRController(home=(0.45, 0.05, 1.05)), 0.5)
    assert _wait_until(lambda: control.stats.safety_status == "stopped", timeout_s=1.0)
    held = arm.read_state().positions
    time.sleep(0.3)
    np.testing.assert_allclose(arm.read_state().positions, held, atol=0.01)


def test_estop_latches_the_driver(node: tuple[ControlNode, InMemoryBus, MujocoArm]) -> None:
    control, bus, arm = node
    control.estop("test")
    _publish_for(bus, ScriptedVRController(home=(0.40, 0.0, 1.10)), 0.2)
    assert arm.estopped
    assert control.stats.safety_status == "estopped"


def test_the_ik_residual_is_published_every_tick(node: tuple[ControlNode, InMemoryBus, MujocoArm]) -> None:
    _, bus, _ = node
    records: list[dict[str, float]] = []
    bus.subscribe(str(Topic("t", "arm0", "residual")), lambda m: records.append(json.loads(m.payload)))
    _publish_for(bus, ScriptedVRController(home=(0.40, 0.0, 1.10)), 0.3)
    assert _wait_until(lambda: len(records) >= 10)
    assert set(records[-1]) == {"capture_ns", "flagged", "position_error_m", "orientation_error_rad"}
    assert records[-1]["flagged"] is False
    assert 0.0 <= records[-1]["position_error_m"] < 0.05
