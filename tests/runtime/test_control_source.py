"""The control node's per-tick record of who drove (``control_source``): a typed ControlSource from
the robot, one per tick in sequence, naming nobody, the policy, a paused source and homing in turn
(in-memory bus, MuJoCo arm, the real handover, passthrough and safety chain; a few seconds)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np
import pytest

from telerig.bus.base import Message
from telerig.bus.memory import InMemoryBus
from telerig.bus.ticks import TICK, picking
from telerig.bus.topics import Topic
from telerig.ir import wire
from telerig.ir.types import ControlSource, JointCommand, Stamp, now_ns
from telerig.retarget.joints.passthrough import JointPassthrough
from telerig.robots.sim.arm import MujocoArm
from telerig.runtime.control_node import ControlNode
from telerig.runtime.handover import Handover, Source
from telerig.runtime.session import SessionState, SessionStatus
from telerig.safety import SafetyChain

pytestmark = pytest.mark.sim

ACTIONS = str(Topic("t", "pi0", "joints"))
TICK_TOPIC = str(Topic("t", "arm0", TICK))  # control_source travels in the tick


class _Records:
    """Every control_source message, decoded (a payload that is not a ControlSource fails the test)."""

    def __init__(self) -> None:
        self.items: list[ControlSource] = []
        self.lock = threading.Lock()

    def __call__(self, message: Message) -> None:
        sample = wire.decode(message.payload)
        assert isinstance(sample, ControlSource)
        with self.lock:
            self.items.append(sample)

    def kinds_since(self, n: int) -> set[str]:
        with self.lock:
            return {s.kind for s in self.items[n:]}

    def __len__(self) -> int:
        with self.lock:
            return len(self.items)


def _wait_until(predicate: Callable[[], bool], timeout_s: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return False


def test_every_tick_says_who_drove_as_a_typed_sample() -> None:
    arm = MujocoArm(name="arm0")
    arm.connect()
    bus = InMemoryBus()
    records = _Records()
    bus.subscribe(TICK_TOPIC, picking({"control_source"}, records))
    policy = Source(
        ACTIONS, "pi0", "policy", 0, joints=JointPassthrough("arm0", arm.joint_names, blend_s=0.0)
    )
    home = np.array(arm.scene.home, dtype=np.float64)
    home[0] += 0.2  # away from where the arm starts, so homing takes some ticks
    node = ControlNode(
        "t",
        arm,
        SafetyChain.default(arm.limits),
        bus,
        control_rate_hz=100.0,
        handover=Handover([policy]),
        home=home,
    )
    seq = [0]

    def act() -> None:  # the policy's action: hold where the arm is
        seq[0] += 1
        t = now_ns()
        q = arm.read_state().positions
        bus.publish(ACTIONS, wire.encode(JointCommand(Stamp("pi0/joints", seq[0], t, t), arm.joint_names, q)))

    def session(paused: tuple[str, ...]) -> None:
        status = SessionStatus(rig="t", state=SessionState.RECORDING, session_id="s", paused_devices=paused)
        bus.publish(str(Topic("t", "coordinator", "session")), status.model_dump_json().encode())

    node.start()
    try:
        assert _wait_until(lambda: len(records) >= 5)
        assert records.kinds_since(0) == {"none"}  # nobody acted yet

        def acting(until: Callable[[], bool]) -> bool:
            deadline = time.monotonic() + 5.0
            while time.monotonic() < deadline:
                act()
                time.sleep(0.01)
                if until():
                    return True
            return False

        n = len(records)
        assert acting(lambda: "policy" in records.kinds_since(n))
        session(("pi0",))
        n = len(records)
        assert acting(lambda: "paused" in records.kinds_since(n))
        session(())
        n = len(records)
        assert acting(lambda: "policy" in records.kinds_since(n))
        homing = threading.Thread(target=node.go_home, kwargs={"timeout_s": 0.3})
        n = len(records)
        homing.start()
        homing.join()
        assert "home" in records.kinds_since(n)
    finally:
        node.stop()
        arm.close()
    with records.lock:
        items = list(records.items)
    assert {s.stamp.source_id for s in items} == {"arm0"}
    assert [s.stamp.seq for s in items] == list(range(1, len(items) + 1))  # one per tick, none lost
    assert all(s.stamp.capture_ns == s.stamp.device_ns > 0 for s in items)
    drivers = {(s.source, s.kind, s.mode) for s in items}
    assert drivers == {
        (None, "none", "auto"),
        ("pi0", "policy", "auto"),
        ("pi0", "paused", "auto"),
        ("home", "home", "auto"),
    }
    assert node.stats.tick_faults == 0
