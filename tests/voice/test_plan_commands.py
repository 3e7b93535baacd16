"""Plan commands through the grammar (real Mosquitto): 'plan reach' plans and stages the execution,
'robot please execute' sends the staged plan's id, 'cancel' reaches the planner, garbage plan
states are counted and never trusted."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable

import pytest

from telerig.bus.base import Message
from telerig.bus.mqtt import MqttBus
from telerig.voice.dispatch import Dispatcher
from telerig.voice.node import connect_dispatcher

R = "telerig/v1/demo"


class _Seen:
    def __init__(self) -> None:
        self.payloads: list[bytes] = []
        self._lock = threading.Lock()

    def __call__(self, message: Message) -> None:
        with self._lock:
            self.payloads.append(message.payload)

    def wait(self, n: int, timeout_s: float = 3.0) -> list[bytes]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self._lock:
                if len(self.payloads) >= n:
                    return list(self.payloads)
            time.sleep(0.02)
        with self._lock:
            return list(self.payloads)


def _plan_state(robot: MqttBus, status: str, plan_id: str | None) -> None:
    doc = {"id": plan_id, "status": status, "reason": ""}
    robot.publish(f"{R}/tiago0/plan", json.dumps(doc).encode(), qos=1, retain=True)


@pytest.fixture
def setup(make_bus: Callable[..., MqttBus]) -> tuple[MqttBus, _Seen, Dispatcher]:
    robot = make_bus("tiago0")
    _plan_state(robot, "none", None)
    seen = _Seen()
    robot.subscribe(f"{R}/tiago0/plan_command", seen, qos=1)
    dispatcher = connect_dispatcher(make_bus("operator"), "demo", source="cli")
    return robot, seen, dispatcher


def _settle(dispatcher: Dispatcher, plan_id: str | None, status: str) -> None:
    deadline = time.monotonic() + 3
    while time.monotonic() < deadline and dispatcher._plans.get("tiago0") != (plan_id, status):
        time.sleep(0.02)
    assert dispatcher._plans.get("tiago0") == (plan_id, status)


def test_plan_reach_then_confirmation_executes_the_staged_plan(setup) -> None:  # type: ignore[no-untyped-def]
    robot, seen, dispatcher = setup
    reply = dispatcher.handle("plan here")
    assert reply.status == "staged"
    assert "robot please execute" in reply.say
    assert seen.wait(1) == [b"plan"]
    _plan_state(robot, "staged", "3-0a1b2c3d")
    _settle(dispatcher, "3-0a1b2c3d", "staged")
    assert dispatcher.handle("robot please execute").status == "done"
    assert seen.wait(2)[1] == b"execute 3-0a1b2c3d"
    _plan_state(robot, "executing", "3-0a1b2c3d")
    _settle(dispatcher, "3-0a1b2c3d", "executing")
    assert dispatcher.handle("cancel").status == "cancelled"
    assert seen.wait(3)[2] == b"cancel"


def test_execute_needs_a_staged_plan_and_the_confirmation(setup) -> None:  # type: ignore[no-untyped-def]
    robot, seen, dispatcher = setup
    assert dispatcher.handle("execute the plan").status == "staged"  # critical: only staged
    reply = dispatcher.handle("robot please execute")
    assert reply.status == "rejected"
    assert "no plan is staged" in reply.say
    _plan_state(robot, "staged", "4-ffff0000")
    _settle(dispatcher, "4-ffff0000", "staged")
    assert dispatcher.handle("run the plan").status == "staged"
    assert dispatcher.handle("navigation").status in ("done", "rejected")  # any other phrase drops it
    assert dispatcher.handle("robot please execute").status == "rejected"
    assert seen.wait(1, timeout_s=0.5) == []  # nothing was ever sent to the planner


@pytest.mark.parametrize(
    "payload",
    [
        b"not json",
        b"[]",
        b'{"id": 5, "status": "staged"}',
        b'{"id": "x/../y", "status": "staged"}',
        b'{"id": "' + b"a" * 100 + b'", "status": "staged"}',
        b'{"status": null}',
        b"{" * 5000,
    ],
)
def test_garbage_plan_states_are_counted_and_never_executed(setup, payload: bytes) -> None:  # type: ignore[no-untyped-def]
    robot, seen, dispatcher = setup
    before = dispatcher.stats.malformed
    robot.publish(f"{R}/tiago0/plan", payload, qos=1, retain=True)
    deadline = time.monotonic() + 3
    while time.monotonic() < deadline and dispatcher.stats.malformed == before:
        time.sleep(0.02)
    assert dispatcher.stats.malformed == before + 1
    assert dispatcher.handle("execute plan").status == "staged"
    assert dispatcher.handle("robot please execute").status == "rejected"
    assert seen.wait(1, timeout_s=0.3) == []
