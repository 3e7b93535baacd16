"""The control center shows each robot's live input-to-actuation latency against its budget (issue 14),
from the control node's real report publisher (:class:`~telerig.runtime.control_health.ControlHealth`)
through a real Mosquitto with the rig's ACL; forged health reports (garbage, NaN, infinities, huge
numbers, oversized) on every health topic the gateway reads are counted and dropped, and the
WebSocket feed goes on."""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from argon2 import PasswordHasher
from fastapi.testclient import TestClient

from telerig.bus.acl import STATION, WEB, rig_access_policy
from telerig.bus.broker import MosquittoBroker
from telerig.bus.mqtt import MqttBus
from telerig.config import load_rig
from telerig.devices.scripted import ScriptedVRController
from telerig.record.health import StreamHealthMonitor
from telerig.runtime.control_health import ControlHealth
from telerig.runtime.device_node import DeviceNode
from telerig.server.accounts import AccountStore
from telerig.server.app import create_app
from telerig.server.gateway import LATENCY_STALE_S, RigGateway

pytestmark = pytest.mark.broker

PASSWORD = "correct horse battery"
MS = 1_000_000


def _wait_for(condition: Callable[[], object], timeout_s: float = 3.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.02)
    return bool(condition())


class _Lab:
    """The demo rig's broker (its ACL), the gateway as ``web``, the app, and clients of principals."""

    def __init__(self, tmp: Path) -> None:
        self.config = load_rig("demo")
        self.broker = MosquittoBroker(access=rig_access_policy(self.config), owner=STATION).start()
        self.buses: list[MqttBus] = []
        accounts = AccountStore.open(tmp, hasher=PasswordHasher(time_cost=1, memory_cost=64, parallelism=1))
        accounts.add_user("vic", "viewer", PASSWORD)
        self.gateway = RigGateway(self.config, self.broker.url_for(WEB)).start()
        self.client = TestClient(create_app(accounts, gateway=self.gateway))

    def bus(self, principal: str) -> MqttBus:
        bus = MqttBus(self.broker.url_for(principal), client_id=f"{principal}-t").connect()
        self.buses.append(bus)
        return bus

    def robot(self) -> dict[str, Any]:
        robot: dict[str, Any] = self.client.get("/api/rig").json()["robots"][0]
        return robot

    def close(self) -> None:
        for bus in self.buses:
            bus.close()
        self.gateway.close()
        self.broker.stop()


@pytest.fixture
def lab(tmp_path: Path) -> Iterator[_Lab]:
    lab = _Lab(tmp_path)
    try:
        with lab.client:
            reply = lab.client.post("/api/login", json={"user": "vic", "password": PASSWORD})
            assert reply.status_code == 200, reply.text
            yield lab
    finally:
        lab.close()


def _feed(health: ControlHealth, latency_ms: float, n: int = 100) -> None:
    """``n`` applied commands ``latency_ms`` after their input's capture, in the last second."""
    now = time.time_ns()
    for i in range(n):
        tick = now - (n - i) * 10 * MS
        health.sent(tick - round(latency_ms * MS), tick, tick)
        health.measured(tick + 5 * MS, tick + 10 * MS)


def test_a_robots_latency_is_shown_against_its_budget_and_goes_grey_when_its_reports_stop(lab: _Lab) -> None:
    health = ControlHealth("demo", "arm0", lab.bus("ctl-arm0"), budget_ms=20.0, hold_ms=100.0)
    _feed(health, 3.0)
    health.publish()
    assert _wait_for(lambda: lab.robot()["latency"] is not None)
    latency = lab.robot()["latency"]
    assert latency["light"] == "green"
    assert latency["p50_ms"] == pytest.approx(3.0)
    assert latency["p99_ms"] == pytest.approx(3.0)
    assert latency["state_p50_ms"] == pytest.approx(8.0)  # capture -> the state 5 ms after the command
    assert latency["commands"] == 100
    assert (latency["budget_ms"], latency["hold_ms"]) == (20.0, 100.0)

    health.command.reset()
    _feed(health, 60.0)  # over the budget, under the hold time
    health.publish()
    assert _wait_for(lambda: lab.robot()["latency"]["light"] == "amber")
    health.command.reset()
    _feed(health, 150.0)  # past the hold time: the chain holds the robot
    health.publish()
    assert _wait_for(lambda: lab.robot()["latency"]["light"] == "red")
    # No report for longer than LATENCY_STALE_S while no episode records: unknown (grey).
    assert _wait_for(lambda: lab.robot()["latency"]["light"] == "grey", LATENCY_STALE_S + 2.0)
    assert lab.robot()["latency"]["report_age_s"] > LATENCY_STALE_S


def test_forged_health_reports_are_counted_and_dropped_and_the_live_feed_goes_on(lab: _Lab) -> None:
    robot, station, device = lab.bus("ctl-arm0"), lab.bus(STATION), lab.bus("dev-vr0")
    good = ControlHealth("demo", "arm0", robot).report()
    good["input_to_command"] = {"count": 10, "p50_ms": 2.0, "p99_ms": 4.0, "max_ms": 5.0}

    def forged(**change: object) -> bytes:
        doc = json.loads(json.dumps(good))
        doc["input_to_command"].update(change)
        return json.dumps(doc).encode()  # Python writes NaN and Infinity, as a forger may

    arm = "telerig/v1/demo/arm0/health"
    garbage = [
        (robot, arm, b"\xff\xfe not json"),
        (robot, arm, b"[" * 5000 + b"]" * 5000),
        (robot, arm, b'{"type": "stream_health", "streams": {}}'),  # not a latency report
        (robot, arm, forged(p50_ms=float("nan"))),
        (robot, arm, forged(p99_ms=float("inf"))),
        (robot, arm, forged(max_ms=1e300)),
        (robot, arm, forged(count=10**30)),
        (robot, arm, forged(count=-1)),
        (robot, arm, forged(p50_ms="fast")),
        (robot, arm, json.dumps({**good, "budget_ms": [1, 2]}).encode()),
        (robot, arm, b'{"type": "control_latency", "input_to_command": {"count": 1, "p50_ms": NaN}}'),
        (robot, arm, b"{" + b" " * 100_000 + b"}"),  # over the stream's 64 KiB
        (station, "telerig/v1/demo/recorder/health", b'{"streams": {}, "x": Infinity}'),
        (device, "telerig/v1/demo/vr0/health", b'{"rate_hz": NaN, "received": 1}'),
    ]
    with lab.client.websocket_connect("/api/live", headers={"origin": "http://testserver"}) as ws:
        assert ws.receive_json()["type"] == "snapshot"
        for bus, topic, payload in garbage:
            bus.publish(topic, payload, qos=1)
        assert _wait_for(lambda: sum(lab.gateway.dropped.values()) == len(garbage))
        snap = lab.client.get("/api/rig").json()
        assert snap["counters"]["dropped"] == {"malformed": len(garbage) - 1, "oversize": 1}
        assert snap["robots"][0]["latency"] is None
        assert snap["devices"][0]["rate_hz"] is None
        # The feed still carries a valid report published after the garbage.
        robot.publish(arm, json.dumps(good).encode(), qos=1, retain=True)
        deadline = time.monotonic() + 5.0
        shown = None
        while shown is None and time.monotonic() < deadline:
            message = ws.receive_json()
            robots = message.get("changed", {}).get("robots") or message.get("robots") or []
            if robots and robots[0]["latency"] is not None:
                shown = robots[0]["latency"]
        assert shown is not None, "the live feed stopped after the forged reports"
        assert (shown["p50_ms"], shown["p99_ms"], shown["light"]) == (2.0, 4.0, "green")


def test_a_device_whose_stream_stalls_is_red_at_the_alert_not_at_its_next_report(lab: _Lab) -> None:
    station = lab.bus(STATION)
    topic = "telerig/v1/demo/vr0/right_controller"
    monitor = StreamHealthMonitor("demo", "recorder", station, {topic: 100.0}, check_interval_s=None)
    node = DeviceNode("demo", ScriptedVRController("vr0"), lab.bus("dev-vr0"), health_period_s=None)
    monitor.start()
    try:
        t0 = time.time_ns()
        for i in range(50):
            monitor.observe(topic, capture_ns=t0 + i * 10 * MS, seq=i, received_ns=t0 + i * 10 * MS)
        node.published = 50  # what its health report says it published since the last
        node.publish_health()
        monitor.tick(t0 + 500 * MS)
        assert _wait_for(lambda: lab.client.get("/api/rig").json()["devices"][0]["light"] == "green")
        # The stream stops: the recorder's stall alert turns the device red before its next report.
        monitor.tick(t0 + 900 * MS)
        assert _wait_for(lambda: lab.client.get("/api/rig").json()["devices"][0]["light"] == "red")
        device = lab.client.get("/api/rig").json()["devices"][0]
        assert device["report_age_s"] < 3.0  # not stale: the alert did it
    finally:
        monitor.stop()
