"""POST /api/voice/say: operator role and CSRF, through the rig's real Mosquitto (ACL, ``web`` login)."""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from argon2 import PasswordHasher
from fastapi.testclient import TestClient

from telerig.bus.acl import STATION, WEB, rig_access_policy
from telerig.bus.broker import MosquittoBroker
from telerig.bus.mqtt import MqttBus
from telerig.config import load_rig
from telerig.runtime.session import EpisodeCommand
from telerig.server.accounts import AccountStore
from telerig.server.app import create_app
from telerig.server.auth import CSRF_HEADER
from telerig.server.gateway import RigGateway

PASSWORD = "correct horse battery"
FAST = PasswordHasher(time_cost=1, memory_cost=64, parallelism=1)
R = "telerig/v1/demo"


def wait_for(condition: Callable[[], object], timeout_s: float = 3.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.02)
    return bool(condition())


@pytest.fixture
def served(tmp_path: Path) -> Iterator[tuple[TestClient, list[tuple[str, bytes]]]]:
    accounts = AccountStore.open(tmp_path, hasher=FAST)
    accounts.add_user("otto", "operator", PASSWORD)
    accounts.add_user("vic", "viewer", PASSWORD)
    config = load_rig("demo")
    robot = config.robots[0].id
    broker = MosquittoBroker(access=rig_access_policy(config), owner=STATION).start()
    station = MqttBus(broker.url_for(STATION), client_id="station0").connect()
    seen: list[tuple[str, bytes]] = []
    station.subscribe(f"{R}/#", lambda m: seen.append((m.topic, m.payload)), qos=1)
    station.publish(f"{R}/{robot}/fixture", b'{"name": "free", "kind": "free"}', qos=1, retain=True)
    gateway = RigGateway(config, broker.url_for(WEB)).start()
    try:
        with TestClient(create_app(accounts, gateway=gateway)) as client:
            yield client, seen
    finally:
        gateway.close()
        station.close()
        broker.stop()


def login(client: TestClient, user: str) -> dict[str, str]:
    reply = client.post("/api/login", json={"user": user, "password": PASSWORD})
    assert reply.status_code == 200, reply.text
    return {CSRF_HEADER: reply.json()["csrf"]}


def _on(seen: list[tuple[str, bytes]], topic: str) -> list[bytes]:
    wait_for(lambda: any(t == topic for t, _ in seen))
    return [p for t, p in seen if t == topic]


def test_operator_text_command_reaches_the_bus(served: tuple[TestClient, list[tuple[str, bytes]]]) -> None:
    client, seen = served
    headers = login(client, "otto")
    reply = client.post("/api/voice/say", json={"text": "pause episode"}, headers=headers)
    assert reply.status_code == 200, reply.text
    assert reply.json()["status"] == "done"
    (payload,) = _on(seen, f"{R}/coordinator/command")
    assert EpisodeCommand.model_validate_json(payload).command == "pause"
    feedback = [json.loads(p) for p in _on(seen, f"{R}/voice/feedback")]
    assert feedback[0]["source"] == "web"
    # The fixture aid through the web principal's ACL, to the robot that publishes fixture state.
    assert (
        client.post("/api/voice/say", json={"text": "limit directions"}, headers=headers).status_code == 200
    )
    assert _on(seen, f"{R}/arm0/fixture_command") == [b"kind:plane"]
    view = client.post("/api/voice/say", json={"text": "top down view"}, headers=headers)
    assert view.status_code == 200
    assert json.loads(_on(seen, f"{R}/voice/view")[0])["view"] == "navigation"
    audit = client.get("/api/audit", headers=headers)
    assert audit.status_code in (200, 403)


def test_login_role_and_csrf_are_required(served: tuple[TestClient, list[tuple[str, bytes]]]) -> None:
    client, _ = served
    assert client.post("/api/voice/say", json={"text": "navigation"}).status_code == 401
    headers = login(client, "otto")
    assert client.post("/api/voice/say", json={"text": "navigation"}).status_code == 403  # no CSRF
    client.post("/api/logout", headers=headers)
    viewer = login(client, "vic")
    assert client.post("/api/voice/say", json={"text": "navigation"}, headers=viewer).status_code == 403


@pytest.mark.parametrize(
    ("body", "code"),
    [
        ({"text": "stop"}, 422),
        ({"text": "open the pod bay doors"}, 422),
        ({"text": "x" * 201}, 422),
        ({"text": ""}, 422),
        ({"text": 5}, 422),
        ({"text": "navigation", "extra": 1}, 422),
        ([1, 2], 422),
    ],
)
def test_garbage_and_oversized_text_is_refused_in_one_line(
    served: tuple[TestClient, list[tuple[str, bytes]]], body: object, code: int
) -> None:
    client, seen = served
    headers = login(client, "otto")
    reply = client.post("/api/voice/say", json=body, headers=headers)
    assert reply.status_code == code, reply.text
    assert not [t for t, _ in seen if t.endswith("command")]


def test_oversized_request_body_is_refused(served: tuple[TestClient, list[tuple[str, bytes]]]) -> None:
    client, _ = served
    headers = login(client, "otto")
    reply = client.post("/api/voice/say", content=b'{"text": "' + b"a" * (2 << 20) + b'"}', headers=headers)
    assert reply.status_code == 422
