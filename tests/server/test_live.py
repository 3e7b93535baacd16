"""The control center's live link to a rig, against a real Mosquitto with the rig's ACL: the gateway
logs in as the ``web`` principal; the rig's side is what the runtime runs or publishes, each with its
own principal (a real coordinator and clock-sync client, a real stream health monitor, control nodes
that answer e-stops on their status topic)."""

from __future__ import annotations

import argparse
import json
import threading
import time
from collections.abc import Callable, Iterator
from functools import partial
from pathlib import Path

import pytest
from argon2 import PasswordHasher
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from telerig.bus.acl import STATION, WEB, rig_access_policy
from telerig.bus.base import Message
from telerig.bus.broker import MosquittoBroker
from telerig.bus.login import BusLogin, login_path
from telerig.bus.mqtt import MqttBus
from telerig.cli.bus_options import operator_login
from telerig.cli.serve import _gateway as serve_gateway
from telerig.cli.serve import add_arguments
from telerig.config import load_rig
from telerig.config.schema import RigConfig
from telerig.errors import ConfigError
from telerig.record.health import StreamHealthMonitor
from telerig.runtime.clock_sync import ClockSyncClient
from telerig.runtime.device_node import DeviceNode
from telerig.runtime.session import Coordinator
from telerig.server.accounts import AccountStore
from telerig.server.app import create_app
from telerig.server.auth import CSRF_HEADER
from telerig.server.gateway import STATION_RED_S, RigGateway

pytestmark = pytest.mark.broker

PASSWORD = "correct horse battery"
FAST = PasswordHasher(time_cost=1, memory_cost=64, parallelism=1)


def wait_for(condition: Callable[[], object], timeout_s: float = 3.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.02)
    return bool(condition())


class Rig:
    """A rig's broker (its ACL) and connected clients of its principals, closed at the end."""

    def __init__(self, config: RigConfig) -> None:
        self.config = config
        self.broker = MosquittoBroker(access=rig_access_policy(config), owner=STATION).start()
        self.buses: list[MqttBus] = []

    def bus(self, principal: str, client_id: str | None = None) -> MqttBus:
        bus = MqttBus(self.broker.url_for(principal), client_id=client_id or principal).connect()
        self.buses.append(bus)
        return bus

    def close(self) -> None:
        for bus in reversed(self.buses):
            bus.close()
        self.broker.stop()


@pytest.fixture
def accounts(tmp_path: Path) -> AccountStore:
    store = AccountStore.open(tmp_path, hasher=FAST)
    store.add_user("otto", "operator", PASSWORD)
    store.add_user("vic", "viewer", PASSWORD)
    return store


def _serve(rig: Rig, accounts: AccountStore) -> tuple[RigGateway, TestClient]:
    gateway = RigGateway(rig.config, rig.broker.url_for(WEB)).start()
    return gateway, TestClient(create_app(accounts, gateway=gateway))


@pytest.fixture
def demo(accounts: AccountStore) -> Iterator[tuple[Rig, RigGateway, TestClient]]:
    rig = Rig(load_rig("demo"))
    gateway, client = _serve(rig, accounts)
    try:
        with client:
            yield rig, gateway, client
    finally:
        gateway.close()
        rig.close()


def login(client: TestClient, user: str) -> str:
    reply = client.post("/api/login", json={"user": user, "password": PASSWORD})
    assert reply.status_code == 200, reply.text
    csrf: str = reply.json()["csrf"]
    return csrf


def test_the_snapshot_shows_stream_health_alerts_and_a_silent_station_turns_red(
    demo: tuple[Rig, RigGateway, TestClient],
) -> None:
    rig, _, client = demo
    login(client, "vic")
    station = rig.bus(STATION, "station0")
    coordinator = Coordinator(station, "demo", lead_s=0.0).start()
    sync = ClockSyncClient(station, "demo", "station0", rate_hz=2.0).start()
    topic = "telerig/v1/demo/arm0/joint_state"
    monitor = StreamHealthMonitor("demo", "recorder", station, {topic: 100.0}, check_interval_s=None)
    monitor.start()
    try:
        t0 = time.time_ns()
        for i in range(50):  # half a second of a 100 Hz stream
            t = t0 + i * 10_000_000
            monitor.observe(topic, capture_ns=t, seq=i, received_ns=t + (3_000_000 if i % 2 else 1_000_000))
        monitor.tick(t0 + 500_000_000)

        def shown() -> dict[str, object] | None:
            snap = client.get("/api/rig").json()
            streams = {s["topic"]: s for s in snap["streams"]}
            return snap if topic in streams and snap["stations"][0]["light"] == "green" else None

        assert wait_for(shown)
        snap = client.get("/api/rig").json()
        stream = next(s for s in snap["streams"] if s["topic"] == topic)
        assert stream["state"] in ("ok", "degraded")
        assert stream["messages"] == 50
        assert stream["expected_hz"] == 100.0
        assert stream["latency_ms"] == pytest.approx(2.0)  # capture to the recorder's receipt
        assert stream["max_latency_ms"] == pytest.approx(3.0)
        assert snap["session"]["state"] == "idle"
        assert snap["fault_policy"] == "halt_all"
        assert snap["stations"][0]["clock_offset_ms"] is not None
        assert abs(snap["stations"][0]["clock_offset_ms"]) < 100  # one host: offset = one-way delay

        # The stream stops: the monitor raises a stall with its suggested action at once; its next
        # health report is not due yet (one a second), the alert alone turns the stream red.
        monitor.tick(t0 + 900_000_000)

        def stalled() -> bool:
            snap = client.get("/api/rig").json()
            light = next(s for s in snap["streams"] if s["topic"] == topic)["light"]
            return bool(snap["active_alerts"]) and light == "red"

        assert wait_for(stalled)
        snap = client.get("/api/rig").json()
        alert = snap["active_alerts"][0]
        assert (alert["code"], alert["subject"], alert["source"]) == ("stream_stalled", topic, "recorder")
        assert alert["suggested_action"]

        # The station stops pinging: red within 2 s of its last ping.
        sync.close()
        stopped = time.monotonic()
        assert wait_for(lambda: client.get("/api/rig").json()["stations"][0]["light"] == "red", 2.5)
        assert time.monotonic() - stopped < 2.0
        assert client.get("/api/rig").json()["stations"][0]["last_seen_s"] >= STATION_RED_S
    finally:
        monitor.stop()
        sync.close()
        coordinator.close()


def test_session_commands_reach_the_coordinator_and_are_audited(
    demo: tuple[Rig, RigGateway, TestClient], accounts: AccountStore
) -> None:
    rig, _, client = demo
    csrf = login(client, "otto")
    coordinator = Coordinator(rig.bus(STATION, "station0"), "demo", lead_s=0.2).start()
    try:
        assert wait_for(lambda: client.get("/api/rig").json()["session"] is not None)
        headers = {CSRF_HEADER: csrf}
        reply = client.post("/api/session/pause", headers=headers)
        assert reply.status_code == 409, reply.text  # idle: nothing to pause
        assert "idle" in reply.json()["detail"]
        reply = client.post("/api/session/start", json={"task": "pick cube"}, headers=headers)
        assert reply.status_code == 200, reply.text
        assert reply.json()["session"]["state"] in ("armed", "recording")
        assert coordinator.status.task == "pick cube"
        assert coordinator.status.operator == "otto"  # the logged-in user
        assert wait_for(lambda: coordinator.state.value == "recording")
        assert client.post("/api/session/pause", headers=headers).json()["session"]["state"] == "paused"
        assert client.post("/api/session/resume", headers=headers).json()["session"]["state"] == "recording"
        reply = client.post("/api/session/discard", json={"reason": "dropped it"}, headers=headers)
        assert reply.json()["session"]["state"] == "stopped"
        assert coordinator.status.discarded
        reply = client.post("/api/session/mark", json={"outcome": "failure"}, headers=headers)
        assert reply.json()["session"]["outcome"] == "failure"
        assert client.post("/api/session/mark", json={"outcome": "maybe"}, headers=headers).status_code == 422
        first = client.post("/api/session/start", headers=headers).json()["session"]["episode_id"]
        reply = client.post("/api/session/restart", headers=headers).json()["session"]
        assert reply["state"] in ("armed", "recording")  # the new episode, 0.2 s lead
        assert reply["episode_id"] != first
        assert client.post("/api/session/end", headers=headers).json()["session"]["state"] == "idle"
    finally:
        coordinator.close()
    actions = [(e.action, e.user, e.target) for e in accounts.audit_log()]
    for action in ("session_start", "session_pause", "session_resume", "session_discard", "session_mark"):
        assert (action, "otto", "demo") in actions
    assert ("session_pause_refused", "otto", "demo") in actions


def test_estop_from_the_api_reaches_every_robot_and_says_which_confirmed(accounts: AccountStore) -> None:
    rig = Rig(load_rig("fleet"))
    gateway, client = _serve(rig, accounts)
    robots = [r.id for r in rig.config.robots]
    dead = robots[-1]  # its control node is not running: it cannot confirm
    commands: list[dict[str, object]] = []
    try:
        controls = {r: rig.bus(f"ctl-{r}") for r in robots if r != dead}
        for r, bus in controls.items():
            bus.publish(f"telerig/v1/fleet/{r}/status", b"ok", qos=1, retain=True)

        def on_command(message: Message) -> None:  # the station's safety listener, as far as the API sees
            command = json.loads(message.payload)
            commands.append(command)
            word = b"estopped" if command["command"] == "estop" else b"ok"
            for r, bus in controls.items():
                if command["robot"] in (None, r):
                    bus.publish(f"telerig/v1/fleet/{r}/status", word, qos=1, retain=True)

        rig.bus(STATION, "station0").subscribe("telerig/v1/fleet/safety/command", on_command, qos=1)
        with client:
            csrf = login(client, "otto")
            assert wait_for(
                lambda: all(r["status"] == "ok" for r in client.get("/api/rig").json()["robots"][:-1])
            )
            reply = client.post(
                "/api/estop", json={"reason": "test", "timeout_s": 1.0}, headers={CSRF_HEADER: csrf}
            )
            assert reply.status_code == 200, reply.text
            result = reply.json()
            assert commands[0] == {
                "command": "estop",
                "robot": None,
                "reason": "test",
                "operator": "otto",
                "source": "web",
            }
            confirmed = {r["robot"]: r["confirmed"] for r in result["robots"]}
            assert confirmed == {r: r != dead for r in robots}
            assert result["confirmed"] is False
            lights = {r["id"]: r["light"] for r in client.get("/api/rig").json()["robots"]}
            assert lights == {r: "grey" if r == dead else "red" for r in robots}
            # One robot's reset.
            reply = client.post("/api/reset", json={"robot": robots[0]}, headers={CSRF_HEADER: csrf})
            assert reply.json()["confirmed"] is True
            assert (
                client.post("/api/estop", json={"robot": "nobody"}, headers={CSRF_HEADER: csrf}).status_code
                == 422
            )
    finally:
        gateway.close()
        rig.close()
    entries = [e for e in accounts.audit_log() if e.action in ("estop", "reset")]
    estop = next(e for e in entries if e.action == "estop")
    assert estop.user == "otto"
    assert estop.target == "fleet/*"
    assert f"not confirmed: {dead}" in estop.detail
    assert any(e.action == "reset" and e.target == f"fleet/{robots[0]}" for e in entries)


def test_a_viewer_cannot_start_a_session_or_estop_and_nothing_is_published(
    demo: tuple[Rig, RigGateway, TestClient],
) -> None:
    rig, _, client = demo
    seen: list[str] = []
    station = rig.bus(STATION, "station0")
    for topic in ("telerig/v1/demo/safety/command", "telerig/v1/demo/coordinator/command"):
        station.subscribe(topic, lambda m: seen.append(m.topic), qos=1)
    csrf = login(client, "vic")
    for path in ("/api/session/start", "/api/session/stop", "/api/estop", "/api/reset"):
        reply = client.post(path, json={}, headers={CSRF_HEADER: csrf})
        assert reply.status_code == 403, (path, reply.text)
        assert "operator" in reply.json()["detail"]
    csrf = login(client, "otto")
    assert client.post("/api/estop", json={}).status_code == 403  # no CSRF header
    time.sleep(0.3)
    assert seen == []


def test_the_websocket_needs_the_login_cookie_and_this_origin(
    demo: tuple[Rig, RigGateway, TestClient],
) -> None:
    rig, _, client = demo
    with pytest.raises(WebSocketDisconnect) as refused, client.websocket_connect("/api/live"):
        pass
    assert refused.value.code == 1008
    login(client, "vic")
    with (
        pytest.raises(WebSocketDisconnect) as foreign,
        client.websocket_connect("/api/live", headers={"origin": "https://evil.example"}),
    ):
        pass
    assert foreign.value.code == 1008
    robot = rig.bus("ctl-arm0")
    with client.websocket_connect("/api/live", headers={"origin": "http://testserver"}) as ws:
        first = ws.receive_json()
        assert first["type"] == "snapshot"
        assert first["rig"] == "demo"
        t0 = time.monotonic()
        robot.publish("telerig/v1/demo/arm0/status", b"estopped", qos=1, retain=True)
        while True:
            delta = ws.receive_json()
            assert delta["type"] == "delta"
            if "robots" in delta["changed"] and delta["changed"]["robots"][0]["status"] == "estopped":
                break
        assert time.monotonic() - t0 < 1.5
        assert delta["changed"]["robots"][0]["light"] == "red"


def test_garbage_on_the_rigs_topics_is_counted_and_dropped(demo: tuple[Rig, RigGateway, TestClient]) -> None:
    rig, gateway, client = demo
    login(client, "vic")
    station = rig.bus(STATION, "station0")
    device = rig.bus("dev-vr0")
    garbage = [
        (station, "telerig/v1/demo/recorder/health", b"\xff\xfe not json"),
        (station, "telerig/v1/demo/recorder/health", b"[" * 5000 + b"]" * 5000),
        (station, "telerig/v1/demo/recorder/health", b'{"streams": 7}'),
        (station, "telerig/v1/demo/recorder/health", b"{" + b" " * (2 << 20) + b"}"),  # 2 MiB
        (station, "telerig/v1/demo/safety/alerts", b'"a string"'),
        (station, "telerig/v1/demo/safety/alerts", json.dumps({"active_alerts": [1, "x", None]}).encode()),
        (station, "telerig/v1/demo/intruder/alerts", b"{}"),
        (station, "telerig/v1/demo/coordinator/session", b'{"state": "exploded"}'),
        (station, "telerig/v1/demo/station0/clock_pong", b'{"t1": "soon"}'),
        (station, "telerig/v1/demo/arm0/status", b"x" * 100_000),
        (device, "telerig/v1/demo/vr0/health", b"\x00" * 1_000_000),
    ]
    for bus, topic, payload in garbage:
        bus.publish(topic, payload, qos=1)
    # Every one is dropped; the 2 MiB one by the broker already (its message_size_limit).
    assert wait_for(lambda: sum(gateway.dropped.values()) == len(garbage) - 1)
    snap = client.get("/api/rig").json()
    dropped = snap["counters"]["dropped"]
    assert dropped == {"malformed": 7, "oversize": 2, "unknown_node": 1}
    assert snap["session"] is None
    assert snap["robots"][0]["status"] is None
    # The gateway still works: a valid report after the garbage is shown.
    report = {
        "type": "stream_health",
        "time_ns": 1,
        "streams": {
            "telerig/v1/demo/vr0/right_controller": {
                "state": "ok",
                "expected_hz": 90.0,
                "measured_hz": 89.5,
                "messages": 450,
                "drops": 0,
            }
        },
    }
    station.publish("telerig/v1/demo/recorder/health", json.dumps(report).encode(), qos=1)
    assert wait_for(lambda: client.get("/api/rig").json()["streams"])
    assert client.get("/api/rig").json()["streams"][0]["light"] == "green"


def test_without_a_rig_the_live_routes_say_how_to_get_one(accounts: AccountStore) -> None:
    with TestClient(create_app(accounts)) as client:
        login(client, "otto")
        reply = client.get("/api/rig")
        assert reply.status_code == 503
        assert "telerig serve --rig" in reply.json()["detail"]


def test_the_openapi_spec_types_every_live_route(accounts: AccountStore) -> None:
    spec = TestClient(create_app(accounts)).get("/openapi.json").json()
    paths = spec["paths"]
    for path in (
        "/api/rig",
        "/api/estop",
        "/api/reset",
        *(f"/api/session/{c}" for c in ("start", "stop", "pause", "resume", "discard")),
    ):
        for op in paths[path].values():
            assert "$ref" in json.dumps(op["responses"]["200"]), path
    assert "RigSnapshot" in spec["components"]["schemas"]
    assert "SafetyResult" in spec["components"]["schemas"]


# --- telerig serve --rig -------------------------------------------------------------------------------


def _serve_args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_arguments(parser.add_subparsers())
    return parser.parse_args(["serve", *argv])


def test_serve_rig_logs_in_as_web_with_the_login_telerig_run_keeps_and_follows_the_runs(
    tmp_path: Path,
) -> None:
    gateway = serve_gateway(_serve_args("--rig", "demo", "--data-root", str(tmp_path)))
    try:
        # Started before the rig: not connected, and it says which login file it waits for.
        snap = gateway.snapshot()
        assert not snap.connected
        assert snap.link_error is not None
        assert ".bus-demo-web.json" in snap.link_error
        for run in range(2):  # two runs of the rig: new broker, port and passwords each time
            rig = Rig(load_rig("demo"))
            try:
                with operator_login(rig.broker, tmp_path, rig.config):
                    web = BusLogin.read(login_path(tmp_path, "demo", WEB), rig="demo")
                    assert web.username == WEB
                    assert wait_for(lambda: gateway.connected, 6.0), gateway.link_error
                    word = "holding" if run == 0 else "estopped"
                    status = "telerig/v1/demo/arm0/status"
                    rig.bus("ctl-arm0").publish(status, word.encode(), qos=1, retain=True)
                    assert wait_for(partial(lambda w: gateway.snapshot().robots[0].status == w, word))
            finally:
                rig.close()
            assert not login_path(tmp_path, "demo", WEB).exists()  # removed when the run ends
            assert wait_for(lambda: not gateway.connected)
    finally:
        gateway.close()


def test_a_takeover_answer_reaches_the_webxr_device_node_and_its_reply_comes_back(
    accounts: AccountStore, tmp_path: Path
) -> None:
    config = load_rig("webxr")
    device = config.devices[0]
    rig = Rig(config)
    gateway, client = _serve(rig, accounts)
    node = DeviceNode(config.name, device.build(), rig.bus(f"dev-{device.id}"), health_period_s=None)
    node.start()
    try:
        with client:
            csrf = login(client, "otto")
            path = f"/api/rig/devices/{device.id}/takeover"
            reply = client.post(path, json={"answer": "confirm"}, headers={CSRF_HEADER: csrf})
            assert reply.status_code == 200, reply.text
            assert reply.json()["reply"] == f"{device.id}: no page is waiting to take over"
            unknown = client.post(
                "/api/rig/devices/nobody/takeover", json={"answer": "deny"}, headers={CSRF_HEADER: csrf}
            )
            assert unknown.status_code == 404
            assert device.id in unknown.json()["detail"]
            alerts = client.get("/api/rig").json()["alerts"]
            assert alerts[0]["code"] == "command_reply"
    finally:
        node.stop()
        gateway.close()
        rig.close()
    entry = next(e for e in accounts.audit_log() if e.action == "takeover_confirm")
    assert (entry.user, entry.target) == ("otto", f"{config.name}/{device.id}")


@pytest.mark.sim
@pytest.mark.slow
def test_a_real_demo_rig_live_and_estopped_from_the_api(accounts: AccountStore, tmp_path: Path) -> None:
    from telerig.runtime.rig import RigRuntime

    raw = load_rig("demo").model_dump(mode="json")
    raw["cameras"] = []
    config = RigConfig.model_validate(raw)
    with RigRuntime(config, data_root=tmp_path / "data") as runtime:
        assert runtime.broker.embedded is not None
        gateway = RigGateway(config, runtime.broker.embedded.url_for(WEB)).start()
        episode = threading.Thread(target=runtime.run_episode, args=(4.0,))
        try:
            with TestClient(create_app(accounts, gateway=gateway)) as client:
                csrf = login(client, "otto")
                episode.start()

                def live() -> bool:
                    snap = client.get("/api/rig").json()
                    lights = {s["topic"].rsplit("/", 1)[-1]: s["light"] for s in snap["streams"]}
                    recording = snap["session"] is not None and snap["session"]["state"] == "recording"
                    # green, or amber when a loaded host keeps the simulation below 80 % of its rate
                    return recording and lights.get("joint_command_sent") in ("green", "amber")

                assert wait_for(live, 10.0)
                snap = client.get("/api/rig").json()
                sent = next(s for s in snap["streams"] if s["topic"].endswith("arm0/joint_command_sent"))
                assert sent["measured_hz"] > 0
                assert sent["expected_hz"] > 0
                assert sent["latency_ms"] is not None
                assert snap["stations"][0]["light"] == "green"
                reply = client.post("/api/estop", json={"reason": "test"}, headers={CSRF_HEADER: csrf})
                assert reply.json()["robots"] == [{"robot": "arm0", "status": "estopped", "confirmed": True}]
                assert wait_for(lambda: client.get("/api/rig").json()["active_alerts"])
                alert = next(
                    a for a in client.get("/api/rig").json()["active_alerts"] if a["code"] == "estop"
                )
                assert alert["subject"] == "arm0"
                assert alert["suggested_action"] == "telerig safety reset --robot arm0"
                reply = client.post("/api/reset", json={"robot": "arm0"}, headers={CSRF_HEADER: csrf})
                assert reply.json()["confirmed"] is True
        finally:
            episode.join(timeout=30)
            gateway.close()


def test_commands_without_the_rigs_broker_are_refused_and_audited(accounts: AccountStore) -> None:
    def no_login() -> tuple[str, None]:
        raise ConfigError("no bus login at /nowhere/.bus-demo-web.json")

    gateway = RigGateway(load_rig("demo"), login=no_login, retry_s=60).start()
    try:
        with TestClient(create_app(accounts, gateway=gateway)) as client:
            csrf = login(client, "otto")
            snap = client.get("/api/rig").json()
            assert snap["connected"] is False
            assert snap["link_error"] == "no bus login at /nowhere/.bus-demo-web.json"
            reply = client.post("/api/estop", json={}, headers={CSRF_HEADER: csrf})
            assert reply.status_code == 503
            assert "hardware e-stop" in reply.json()["detail"]
            assert client.post("/api/session/stop", headers={CSRF_HEADER: csrf}).status_code == 503
    finally:
        gateway.close()
    actions = {e.action for e in accounts.audit_log()}
    assert {"estop_failed", "session_stop_failed"} <= actions


def test_a_cameras_jpeg_preview_is_served_to_a_viewer(demo: tuple[Rig, RigGateway, TestClient]) -> None:
    import numpy as np

    from telerig.cameras.preview import PreviewPublisher

    rig, _, client = demo
    login(client, "vic")
    assert client.get("/api/rig/cameras/scene/preview").status_code == 404  # none yet
    previews = PreviewPublisher(rig.bus("cam-scene"), "demo", "scene", max_width=160, max_height=120)
    image = np.zeros((480, 640, 3), np.uint8)
    image[:, :320] = (255, 0, 0)
    try:
        previews.offer(image, time.time_ns())
    finally:
        previews.close()
    assert wait_for(lambda: client.get("/api/rig/cameras/scene/preview").status_code == 200)
    reply = client.get("/api/rig/cameras/scene/preview")
    assert reply.headers["content-type"] == "image/jpeg"
    assert reply.content.startswith(b"\xff\xd8\xff")
    camera = client.get("/api/rig").json()["cameras"][0]
    assert (camera["id"], camera["light"], camera["preview_bytes"]) == ("scene", "green", len(reply.content))
    assert client.get("/api/rig/cameras/nope/preview").status_code == 404
    # A camera principal publishing something that is not a JPEG is counted, the last good one kept.
    rig.bus("cam-scene", "cam-scene-2").publish("telerig/v1/demo/scene/preview", b"GIF89a...", qos=1)
    assert wait_for(lambda: client.get("/api/rig").json()["counters"]["dropped"].get("malformed") == 1)
    assert client.get("/api/rig/cameras/scene/preview").content == reply.content


def test_serve_rig_finds_an_external_brokers_web_login_in_the_broker_folder(tmp_path: Path) -> None:
    rig = Rig(load_rig("demo"))
    try:
        folder = tmp_path / "broker" / "demo" / "logins"  # as `telerig broker acl demo --out` writes it
        folder.mkdir(parents=True)
        BusLogin(rig.broker.address, WEB, rig.broker.access.password(WEB), "demo").write(folder / "web.json")
        gateway = serve_gateway(_serve_args("--rig", "demo", "--data-root", str(tmp_path)))
        try:
            assert gateway.connected, gateway.link_error
        finally:
            gateway.close()
    finally:
        rig.close()
