"""Per-device pause from the control center: operator role and CSRF, audited, through the rig's real
Mosquitto (ACL) to a real coordinator, its state in every client's snapshot."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from argon2 import PasswordHasher
from fastapi.testclient import TestClient

from telerig.bus.acl import STATION, WEB, rig_access_policy
from telerig.bus.base import Message
from telerig.bus.broker import MosquittoBroker
from telerig.bus.mqtt import MqttBus
from telerig.config import load_rig
from telerig.runtime.device_node import DeviceNode
from telerig.runtime.session import Coordinator
from telerig.server.accounts import AccountStore
from telerig.server.app import create_app
from telerig.server.auth import CSRF_HEADER
from telerig.server.gateway import RigGateway

pytestmark = pytest.mark.broker

PASSWORD = "correct horse battery"
FAST = PasswordHasher(time_cost=1, memory_cost=64, parallelism=1)
COMMAND = "telerig/v1/demo/coordinator/command"


def wait_for(condition: Callable[[], object], timeout_s: float = 3.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.02)
    return bool(condition())


@pytest.fixture
def served(tmp_path: Path) -> Iterator[tuple[TestClient, Coordinator, AccountStore, list[bytes]]]:
    accounts = AccountStore.open(tmp_path, hasher=FAST)
    accounts.add_user("otto", "operator", PASSWORD)
    accounts.add_user("vic", "viewer", PASSWORD)
    config = load_rig("demo")
    broker = MosquittoBroker(access=rig_access_policy(config), owner=STATION).start()
    station = MqttBus(broker.url_for(STATION), client_id="station0").connect()
    seen: list[bytes] = []
    station.subscribe(COMMAND, lambda m: seen.append(m.payload), qos=1)
    coordinator = Coordinator(station, "demo", devices=["vr0"]).start()
    gateway = RigGateway(config, broker.url_for(WEB)).start()
    try:
        with TestClient(create_app(accounts, gateway=gateway)) as client:
            assert wait_for(lambda: client.get("/api/rig").json() is not None)
            yield client, coordinator, accounts, seen
    finally:
        gateway.close()
        coordinator.close()
        station.close()
        broker.stop()


def login(client: TestClient, user: str) -> dict[str, str]:
    reply = client.post("/api/login", json={"user": user, "password": PASSWORD})
    assert reply.status_code == 200, reply.text
    return {CSRF_HEADER: reply.json()["csrf"]}


def test_an_operator_pauses_and_resumes_one_device_and_every_client_sees_it(
    served: tuple[TestClient, Coordinator, AccountStore, list[bytes]],
) -> None:
    client, coordinator, accounts, _ = served
    headers = login(client, "otto")
    assert wait_for(lambda: client.get("/api/rig").json()["session"] is not None)
    reply = client.post("/api/rig/devices/vr0/pause", json={"reason": "headset slipped"}, headers=headers)
    assert reply.status_code == 200, reply.text
    assert reply.json()["session"]["paused_devices"] == ["vr0"]
    assert coordinator.status.paused_devices == ("vr0",)
    assert "headset slipped (by otto)" in (coordinator.status.reason or "")
    assert client.get("/api/rig").json()["session"]["paused_devices"] == ["vr0"]
    again = client.post("/api/rig/devices/vr0/pause", headers=headers)
    assert again.status_code == 409, again.text  # already paused: the coordinator refused it
    reply = client.post("/api/rig/devices/vr0/resume", headers=headers)
    assert reply.status_code == 200, reply.text
    assert reply.json()["session"]["paused_devices"] == []
    actions = [(e.action, e.user, e.target, e.detail) for e in accounts.audit_log()]
    assert any(a[:3] == ("session_pause_device", "otto", "demo") and "vr0" in a[3] for a in actions)
    assert any(a[:3] == ("session_resume_device", "otto", "demo") for a in actions)
    assert any(a[:3] == ("session_pause_device_refused", "otto", "demo") for a in actions)


def test_pause_needs_an_operator_a_csrf_token_and_a_device_of_the_rig(
    served: tuple[TestClient, Coordinator, AccountStore, list[bytes]],
) -> None:
    client, coordinator, _, seen = served
    viewer = login(client, "vic")
    assert client.post("/api/rig/devices/vr0/pause", headers=viewer).status_code == 403
    operator = login(client, "otto")
    assert client.post("/api/rig/devices/vr0/pause").status_code == 403  # no CSRF header
    for device in ("nope", "..%2F..%2Fetc", "v" * 300):
        reply = client.post(f"/api/rig/devices/{device}/pause", headers=operator)
        assert reply.status_code == 404, reply.text
    for body in ({"reason": "x" * 501}, {"reason": 7}, {"device": "vr0"}, [1]):
        reply = client.post("/api/rig/devices/vr0/pause", json=body, headers=operator)
        assert reply.status_code == 422, (body, reply.text)
    time.sleep(0.3)
    assert seen == []  # nothing refused reached the bus
    assert coordinator.status.paused_devices == ()


def test_a_device_login_cannot_pause_another_device(
    served: tuple[TestClient, Coordinator, AccountStore, list[bytes]], tmp_path: Path
) -> None:
    _, coordinator, _, seen = served
    # The broker of the fixture is reachable through the coordinator's own bus; a device's login
    # comes from the same policy: publish as dev-vr0 on the coordinator's command topic.
    config = load_rig("demo")
    broker = MosquittoBroker(access=rig_access_policy(config), owner=STATION).start()
    try:
        got: list[Message] = []
        station = MqttBus(broker.url_for(STATION), client_id="s").connect()
        station.subscribe(COMMAND, got.append, qos=1)
        own = Coordinator(station, "demo", devices=["vr0"], serve_clock=False).start()
        device = MqttBus(broker.url_for("dev-vr0"), client_id="d").connect()
        device.publish(COMMAND, b'{"command": "pause_device", "device": "vr0"}', qos=1)
        time.sleep(0.5)
        assert got == []
        assert own.status.paused_devices == ()
        assert own.stats.accepted == 0
        device.close()
        own.close()
        station.close()
    finally:
        broker.stop()
    assert seen == []
    assert coordinator.status.paused_devices == ()


def test_an_operator_launches_a_calibration_where_the_device_runs_and_sees_its_result(
    tmp_path: Path,
) -> None:
    accounts = AccountStore.open(tmp_path, hasher=FAST)
    accounts.add_user("otto", "operator", PASSWORD)
    accounts.add_user("vic", "viewer", PASSWORD)
    config = load_rig("demo")
    broker = MosquittoBroker(access=rig_access_policy(config), owner=STATION).start()
    device_bus = MqttBus(broker.url_for("dev-vr0"), client_id="demo-dev-vr0").connect()
    gateway = RigGateway(config, broker.url_for(WEB)).start()
    # The demo's scripted controller: one hand, no head, so the calibration runs and fails, saying why.
    node = DeviceNode("demo", config.devices[0].build(), device_bus, profile_root=tmp_path)
    try:
        with TestClient(create_app(accounts, gateway=gateway)) as client:
            viewer = login(client, "vic")
            assert client.post("/api/rig/devices/vr0/calibrate", json={}, headers=viewer).status_code == 403
            operator = login(client, "otto")
            assert client.post("/api/rig/devices/vr0/calibrate", json={}).status_code == 403  # no CSRF
            reply = client.post("/api/rig/devices/nope/calibrate", json={}, headers=operator)
            assert reply.status_code == 404
            for body in ({"duration_s": 1e9}, {"operator": "../x"}, {"settle_s": -1}, {"extra": 1}):
                reply = client.post("/api/rig/devices/vr0/calibrate", json=body, headers=operator)
                assert reply.status_code == 422, (body, reply.text)
            reply = client.post(
                "/api/rig/devices/vr0/calibrate", json={"duration_s": 1.0, "settle_s": 0}, headers=operator
            )
            assert reply.status_code == 200, reply.text
            assert reply.json()["operator"] == "otto"  # the logged-in user by default
            assert "calibrating operator otto with vr0" in reply.json()["reply"]

            def calibration() -> str:
                devices = client.get("/api/rig").json()["devices"]
                return str(next(d for d in devices if d["id"] == "vr0")["calibration"])

            assert wait_for(lambda: calibration().startswith("failed: "), 10.0), calibration()
            again = client.post(
                "/api/rig/devices/vr0/calibrate", json={"duration_s": 1.0, "settle_s": 0}, headers=operator
            )
            assert again.status_code == 200
    finally:
        node.calibration.join(10.0)
        gateway.close()
        device_bus.close()
        broker.stop()
    assert node.published == 0  # the calibration's samples never went on the bus
    actions = [(e.action, e.user, e.target) for e in accounts.audit_log()]
    assert actions.count(("calibrate", "otto", "demo/vr0")) == 2
