"""Control node over the in-memory bus: malformed input is counted and dropped, stale input stops the arm."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from telerig.bus.memory import InMemoryBus
from telerig.bus.ticks import TICK, picking, unbundle
from telerig.bus.topics import Topic
from telerig.config.schema import AlignmentConfig
from telerig.devices.scripted import ScriptedVRController
from telerig.ir import wire
from telerig.ir.types import GripperCommand, RetargetResidual, Sample, Stamp, now_ns
from telerig.retarget.alignment import Alignment
from telerig.retarget.arm import AbsolutePoseRetargeter
from telerig.retarget.arm_ik import ArmIK
from telerig.retarget.gripper import TriggerGripper
from telerig.robots.sim.arm import MujocoArm
from telerig.robots.sim.gripper import MujocoGripper
from telerig.runtime.control_node import ControlNode, GripperBinding, JointsBinding
from telerig.safety import SafetyChain, SafetySupervisor

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
    records: list[Sample] = []
    bus.subscribe(
        str(Topic("t", "arm0", TICK)), picking({"residual"}, lambda m: records.append(wire.decode(m.payload)))
    )
    _publish_for(bus, ScriptedVRController(home=(0.40, 0.0, 1.10)), 0.3)
    assert _wait_until(lambda: len(records) >= 10)
    assert all(isinstance(r, RetargetResidual) for r in records), "typed, never the JSON of old"
    last = records[-1]
    assert isinstance(last, RetargetResidual)
    assert last.names == ("position_error_m", "orientation_error_rad")
    assert last.flagged is False
    assert 0.0 <= last.get("position_error_m") < 0.05
    # Stamped by the robot (the recorder's from_owner check), one seq per solve, the input's time.
    seqs = [r.stamp.seq for r in records]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
    assert {r.stamp.source_id for r in records} == {"arm0"}
    captures = [r.stamp.capture_ns for r in records]
    assert captures == sorted(captures)
    assert 0 < captures[0] <= now_ns()


# -- one message never kills the loop (issue 11, findings 1 and 2) ------------------------------


def _publish_until(
    bus: InMemoryBus,
    device: ScriptedVRController,
    done: Callable[[], bool],
    start_seq: int,
    timeout_s: float = 5.0,
) -> tuple[bool, int]:
    """Publish fresh samples at 100 Hz until ``done()`` (True) or ``timeout_s`` passes (False); next seq."""
    seq = start_seq
    deadline = time.monotonic() + timeout_s
    while not done():
        if time.monotonic() > deadline:
            return False, seq
        seq = _publish_for(bus, device, 0.05, start_seq=seq)
    return True, seq


def _sample(**changes: object) -> bytes:
    """A well-formed controller sample at the operator's home, captured now, with ``changes``."""
    sample = ScriptedVRController(home=(0.40, 0.0, 1.10)).sample_at(0.0, seq=10_000)
    t = now_ns()
    stamp = dataclasses.replace(sample.stamp, device_ns=t, capture_ns=t)
    fields = {k: v for k, v in changes.items() if k != "capture_ns"}
    if "capture_ns" in changes:
        stamp = dataclasses.replace(stamp, capture_ns=changes["capture_ns"])
    return wire.encode(dataclasses.replace(sample, stamp=stamp, **fields))  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("changes", "reason"),
    [
        ({"position": np.array([np.nan, 0.0, 1.1])}, "non_finite"),
        ({"position": np.array([np.inf, 0.0, 1.1])}, "non_finite"),
        ({"orientation": np.array([np.nan, 0.0, 0.0, 1.0])}, "non_finite"),
        ({"orientation": np.zeros(4)}, "bad_quaternion"),
        ({"orientation": np.array([1e300, 0.0, 0.0, 0.0])}, "bad_quaternion"),
    ],
    ids=["position-nan", "position-inf", "orientation-nan", "orientation-zero", "orientation-1e300"],
)
def test_an_unusable_sample_is_rejected_and_the_loop_keeps_driving(
    node: tuple[ControlNode, InMemoryBus, MujocoArm], changes: dict[str, object], reason: str
) -> None:
    control, bus, arm = node
    device = ScriptedVRController(home=(0.40, 0.0, 1.10))
    seq = _publish_for(bus, device, 0.3)
    bus.publish(TOPIC, _sample(**changes))
    time.sleep(0.05)  # a tick of its own (a newer sample in the same tick would replace it)
    applied = control.stats.applied
    flowing, _ = _publish_until(bus, device, lambda: control.stats.applied > applied + 10, seq + 1)
    assert flowing  # commands kept flowing after the bad sample
    assert not arm.estopped
    assert control.stats.rejected[reason] == 1
    assert control.stats.tick_faults == 0


@pytest.mark.parametrize("ahead_ns", [3600 * 10**9, 2**62], ids=["1h", "2^62ns"])
def test_a_far_future_sample_does_not_freeze_the_arm(
    node: tuple[ControlNode, InMemoryBus, MujocoArm], ahead_ns: int, caplog: pytest.LogCaptureFixture
) -> None:
    control, bus, _ = node
    device = ScriptedVRController(home=(0.40, 0.0, 1.10))
    seq = _publish_for(bus, device, 0.3)
    with caplog.at_level("WARNING"):
        bus.publish(TOPIC, _sample(capture_ns=min(now_ns() + ahead_ns, 2**63 - 1)))
        time.sleep(0.05)
        applied = control.stats.applied
        flowing, _ = _publish_until(bus, device, lambda: control.stats.applied > applied + 15, seq + 1)
    assert flowing
    assert control.stats.rejected["non_monotonic"] == 0  # no real sample after it was refused
    assert control.stats.safety_status in ("ok", "limited")
    assert control.stats.rejected["future_stamp"] == 1
    assert control.safety.counts["invalid_input"] == 0
    assert any("future_stamp" in r.getMessage() and "vr0/right" in r.getMessage() for r in caplog.records)


class _FailingRetargeter:
    """An arm retargeter that raises on samples with ``trigger == 0.625`` (a bug in a plug-in)."""

    def __init__(self, inner: AbsolutePoseRetargeter) -> None:
        self.inner = inner
        self.accepts = inner.accepts

    def __call__(self, sample: object, q_current: np.ndarray, dt: float) -> tuple[object, object]:
        if getattr(sample, "trigger", None) == 0.625:
            raise RuntimeError("plug-in bug")
        return self.inner(sample, q_current, dt)  # type: ignore[arg-type]

    def reset(self) -> None:
        self.inner.reset()


def test_an_exception_in_a_tick_is_a_counted_fault_and_reset_resumes_control() -> None:
    arm = MujocoArm(name="arm0")
    arm.connect()
    bus = InMemoryBus()
    ik = ArmIK(arm.scene)
    home_p, _ = ik.forward(arm.scene.home)
    alignment = Alignment.from_config(
        AlignmentConfig(operator_origin=(0.40, 0.0, 1.10), robot_origin=tuple(home_p.tolist()))
    )
    supervisor = SafetySupervisor("pause_affected")
    retargeter = _FailingRetargeter(AbsolutePoseRetargeter(alignment, ik, arm.joint_names))
    control = ControlNode(
        "t",
        arm,
        supervisor.add("arm0", arm, SafetyChain.default(arm.limits)),
        bus,
        control_rate_hz=100.0,
        joints=JointsBinding(TOPIC, retargeter),  # type: ignore[arg-type]
    )
    control.start()
    try:
        device = ScriptedVRController(home=(0.40, 0.0, 1.10))
        seq = _publish_for(bus, device, 0.3)
        bus.publish(TOPIC, _sample(trigger=0.625))
        time.sleep(0.05)
        assert _wait_until(lambda: control.stats.safety_status == "estopped")
        seq = _publish_for(bus, device, 0.2, start_seq=seq + 1)
        assert arm.estopped
        assert control.safety.counts["driver_fault"] == 1  # what the manifest reads
        supervisor.reset("arm0")
        applied = control.stats.applied
        resumed, _ = _publish_until(bus, device, lambda: control.stats.applied > applied + 10, seq)
        assert resumed  # the loop is alive and control resumed
        assert control.stats.safety_status in ("ok", "limited")
        assert control.stats.tick_faults == 1
    finally:
        control.stop()
        arm.close()


def test_a_task_reset_opens_the_gripper_on_the_way_home() -> None:
    arm = MujocoArm(name="arm0")
    arm.connect()
    bus = InMemoryBus()
    requested: list[GripperCommand] = []
    bus.subscribe(
        str(Topic("t", "arm0", TICK)),
        picking({"gripper_command_requested"}, lambda m: requested.append(wire.decode(m.payload))),
    )
    node = ControlNode(
        "t", arm, SafetyChain.default(arm.limits), bus, control_rate_hz=100.0, home=arm.scene.home
    )
    node.start()
    try:
        # The last episode ended holding: the gripper is closed.
        arm.send_gripper(GripperCommand(Stamp("op", 0, now_ns(), now_ns()), opening=0.0))
        assert _wait_until(lambda: arm.read_gripper().opening < 0.05)
        assert node.go_home(timeout_s=5.0)  # an operator's reset: the gripper keeps what it holds
        assert arm.read_gripper().opening < 0.05
        assert not requested
        assert node.go_home(timeout_s=5.0, open_gripper=True)
        assert arm.read_gripper().opening >= 0.95  # go_home waited for it
        assert requested
        assert {c.stamp.source_id for c in requested} == {"arm0/home"}
        assert {c.opening for c in requested} == {1.0}
    finally:
        node.stop()
        arm.close()


def test_a_tick_that_raises_still_publishes_the_command_it_applied(
    node: tuple[ControlNode, InMemoryBus, MujocoArm], monkeypatch: pytest.MonkeyPatch
) -> None:
    control, bus, _ = node
    ticks: list[list[str]] = []
    bus.subscribe(
        str(Topic("t", "arm0", TICK)),
        lambda m: ticks.append([p.topic.rsplit("/", 1)[1] for p in unbundle(m)]),
    )

    def broken() -> None:  # after the command was applied and collected, before the sensors
        raise RuntimeError("a bug in the tick")

    monkeypatch.setattr(control, "_publish_sensed", broken)
    _publish_for(bus, ScriptedVRController(home=(0.40, 0.0, 1.10)), 0.2)
    assert _wait_until(lambda: control.stats.tick_faults >= 1)
    # Published when the tick failed, on its own: the applied command and the state, no sensors.
    assert _wait_until(lambda: any("joint_command_sent" in t for t in ticks))
    failed = next(t for t in ticks if "joint_command_sent" in t)
    assert failed.count("joint_state") == 1
    assert control.sensed_streams  # the arm measures its gripper (and more): those never came
    assert not set(control.sensed_streams) & set(failed)


def test_a_gripper_alone_keeps_its_grip_while_the_trigger_is_quiet() -> None:
    # A gripper alone: its one joint is the gripper's, and nothing drives it as a joint. Each tick
    # without a fresh trigger sample used to send the joint chain's stop command (the position it
    # measured at start: open) to that joint, and the fingers let go of what they held.
    gripper = MujocoGripper(name="gripper0")
    gripper.connect()
    bus = InMemoryBus()
    node = ControlNode(
        "t",
        gripper,
        SafetyChain.default(gripper.limits),
        bus,
        control_rate_hz=100.0,
        gripper=GripperBinding(TOPIC, TriggerGripper()),
    )
    node.start()
    try:
        for _ in range(100):  # 1 s of a pulled trigger
            bus.publish(TOPIC, _sample(trigger=1.0))
            time.sleep(0.01)
        closed = float(gripper.read_state().positions[0])
        assert closed > 0.3  # [rad]: the fingers swung in
        time.sleep(0.3)  # the trigger goes quiet; the loop ticks on
        assert float(gripper.read_state().positions[0]) > closed - 0.02
        assert node.stats.ticks > 100
    finally:
        node.stop()
        gripper.close()
