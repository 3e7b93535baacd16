"""Safety alerts on the bus: events, retained active alerts, repeats, clearing (memory bus, Mosquitto)."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from telerig.bus.base import Message
from telerig.bus.memory import InMemoryBus
from telerig.bus.mqtt import MqttBus
from telerig.ir.types import JointCommand, JointState, Stamp
from telerig.robots.base import JointLimits
from telerig.safety import SafetyAlerts, SafetyChain, SafetyEvent, SafetyOutput, SafetyStatus

MS = 1_000_000
WS = SafetyEvent("workspace", "tool 3.0 cm outside box 'table'", "move back")
STOP = SafetyEvent("estop", "operator pressed e-stop", "make safe, then reset")
LIMITS = JointLimits(("j1", "j2"), [-1.0, -1.0], [1.0, 1.0], [1.0, 1.0], [10.0, 10.0])


def out(status: SafetyStatus, *events: SafetyEvent) -> SafetyOutput:
    return SafetyOutput(None, status, tuple(events))


class Recorder:
    def __init__(self) -> None:
        self.messages: list[Message] = []
        self.lock = threading.Lock()

    def __call__(self, message: Message) -> None:
        with self.lock:
            self.messages.append(message)

    def docs(self, suffix: str) -> list[dict[str, Any]]:
        with self.lock:
            return [json.loads(m.payload) for m in self.messages if m.topic.endswith(suffix)]


def test_warning_raises_event_and_retained_alert_then_clears_on_tracking() -> None:
    bus = InMemoryBus()
    alerts = SafetyAlerts(bus, "lab")
    rec = Recorder()
    bus.subscribe("telerig/v1/lab/safety/#", rec)
    alerts.update("ur5e", out("holding", WS), 0)
    event = rec.docs("/events")[-1]
    assert {k: event[k] for k in ("code", "robot", "reason", "suggested_action", "severity", "active")} == {
        "code": "workspace",
        "robot": "ur5e",
        "reason": WS.reason,
        "suggested_action": WS.suggested_action,
        "severity": "warning",
        "active": True,
    }
    assert event["time_ns"] == 0
    state = rec.docs("/alerts")[-1]
    assert [a["code"] for a in state["active_alerts"]] == ["workspace"]
    alerts.update("ur5e", out("ok"), 10 * MS)
    assert rec.docs("/events")[-1]["active"] is False
    assert rec.docs("/alerts")[-1]["active_alerts"] == []
    assert alerts.active() == []


def test_active_alert_list_is_retained_for_a_late_subscriber() -> None:
    bus = InMemoryBus()
    alerts = SafetyAlerts(bus, "lab")
    alerts.update("left", out("estopped", STOP), 0)
    rec = Recorder()
    bus.subscribe("telerig/v1/lab/safety/alerts", rec)
    (state,) = rec.docs("/alerts")
    assert [(a["robot"], a["code"], a["severity"]) for a in state["active_alerts"]] == [
        ("left", "estop", "error")
    ]


def test_repeats_are_counted_and_republished_at_most_once_per_interval() -> None:
    bus = InMemoryBus()
    alerts = SafetyAlerts(bus, "lab", repeat_interval_s=1.0)
    rec = Recorder()
    bus.subscribe("telerig/v1/lab/safety/events", rec)
    for k in range(150):  # 1.5 s of refusals at 100 Hz
        alerts.update("ur5e", out("holding", WS), k * 10 * MS)
    docs = rec.docs("/events")
    assert [d["count"] for d in docs] == [1, 101]


def test_error_stays_active_until_reset_and_info_is_not_published() -> None:
    bus = InMemoryBus()
    alerts = SafetyAlerts(bus, "lab")
    rec = Recorder()
    bus.subscribe("telerig/v1/lab/safety/#", rec)
    alerts.update("ur5e", out("limited", SafetyEvent("velocity_limit", "joint speed limited", "none")), 0)
    assert rec.messages == []
    alerts.update("ur5e", out("estopped", STOP), 10 * MS)
    alerts.update("ur5e", out("estopped"), 20 * MS)
    assert [a.code for a in alerts.active()] == ["estop"]
    alerts.update("ur5e", out("stopped"), 30 * MS)  # reset: the chain restarts stopped
    assert alerts.active() == []


def test_chain_watchdog_stop_reaches_the_alerts_topic() -> None:
    bus = InMemoryBus()
    alerts = SafetyAlerts(bus, "lab")
    rec = Recorder()
    bus.subscribe("telerig/v1/lab/safety/events", rec)
    chain = SafetyChain.default(LIMITS, ramp_duration_s=0.0)
    measured = JointState(Stamp("robot", 0, 0, 0), LIMITS.names, np.zeros(2), np.zeros(2))
    t = 1_000 * MS
    for k in range(5):
        t += 10 * MS
        request = JointCommand(Stamp("retarget", k, t, t), LIMITS.names, np.zeros(2))
        alerts.update("arm", chain.step(request, now_ns=t, measured=measured), t)
    for _ in range(30):
        t += 10 * MS
        alerts.update("arm", chain.step(None, now_ns=t, measured=measured), t)
    assert [d["code"] for d in rec.docs("/events")] == ["input_stale", "watchdog_stop"]


def test_alerts_through_a_real_mosquitto(make_bus: Callable[..., MqttBus]) -> None:
    publisher = make_bus("safety-pub")
    alerts = SafetyAlerts(publisher, "lab")
    alerts.update("ur5e", out("estopped", STOP), 0)
    listener = make_bus("dashboard")
    rec = Recorder()
    listener.subscribe("telerig/v1/lab/safety/alerts", rec, qos=1)
    deadline = time.monotonic() + 5.0
    while not rec.docs("/alerts") and time.monotonic() < deadline:
        time.sleep(0.01)
    (state,) = rec.docs("/alerts")
    assert state["type"] == "safety_alerts"
    assert [(a["robot"], a["code"]) for a in state["active_alerts"]] == [("ur5e", "estop")]
