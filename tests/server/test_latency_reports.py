"""The pages' latency reports (issue 17): ``/api/latency`` refuses pages without a login, this
server's origin or the CSRF token; garbage, oversized, forged and implausible reports are counted per
reason and dropped while the page goes on; a good ``rendered`` report becomes the robot's browser
stage in the snapshot and on its ``latency_view`` stream (published as ``web`` through the rig's real
Mosquitto ACL), and a camera node's stamped preview gives the video stages once a page reports it
displayed. Forged control-node latency reports are dropped by the gateway."""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from argon2 import PasswordHasher
from fastapi.testclient import TestClient
from starlette.testclient import WebSocketTestSession
from starlette.websockets import WebSocketDisconnect

from telerig.bus.acl import STATION, WEB, rig_access_policy
from telerig.bus.broker import MosquittoBroker
from telerig.bus.mqtt import MqttBus
from telerig.bus.topics import Topic
from telerig.cameras.preview import PreviewPublisher
from telerig.config import load_rig
from telerig.runtime.control_health import ControlHealth
from telerig.server.accounts import AccountStore
from telerig.server.app import create_app
from telerig.server.gateway import RigGateway
from telerig.server.routes_latency import MAX_MESSAGE, SUBPROTOCOL

pytestmark = pytest.mark.broker

PASSWORD = "correct horse battery"
ORIGIN = "http://testserver"
MS = 1_000_000


def wait_for(condition: Callable[[], object], timeout_s: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.02)
    return bool(condition())


class Lab:
    """The demo rig's broker (its ACL), the control center on it as ``web``, clients of principals."""

    def __init__(self, tmp: Path) -> None:
        self.config = load_rig("demo")
        self.broker = MosquittoBroker(access=rig_access_policy(self.config), owner=STATION).start()
        self.buses: list[MqttBus] = []
        self.views: list[dict[str, Any]] = []
        self.bus(STATION).subscribe(
            str(Topic.pattern("demo", "+", "latency_view")),
            lambda m: self.views.append(json.loads(m.payload)),
            qos=1,
        )
        self.gateway = RigGateway(self.config, self.broker.url_for(WEB)).start()
        accounts = AccountStore.open(tmp, hasher=PasswordHasher(time_cost=1, memory_cost=64, parallelism=1))
        accounts.add_user("vic", "viewer", PASSWORD)
        self.client = TestClient(create_app(accounts, gateway=self.gateway))

    def bus(self, principal: str) -> MqttBus:
        bus = MqttBus(self.broker.url_for(principal), client_id=f"{principal}-{len(self.buses)}").connect()
        self.buses.append(bus)
        return bus

    def login(self) -> str:
        reply = self.client.post("/api/login", json={"user": "vic", "password": PASSWORD})
        assert reply.status_code == 200, reply.text
        csrf: str = reply.json()["csrf"]
        return csrf

    def page(self, csrf: str, *, origin: str | None = ORIGIN) -> WebSocketTestSession:
        headers = {} if origin is None else {"origin": origin}
        return self.client.websocket_connect(
            "/api/latency", subprotocols=[SUBPROTOCOL, f"csrf.{csrf}"], headers=headers
        )

    def counters(self) -> dict[str, int]:
        reply = self.client.get("/api/latency")
        assert reply.status_code == 200, reply.text
        counters: dict[str, int] = reply.json()["counters"]
        return counters

    def stages(self, node: str) -> dict[str, dict[str, Any]]:
        snapshot = self.client.get("/api/rig").json()
        (entry,) = [s for s in snapshot["latency_stages"] if s["node"] == node]
        return {s["stage"]: s for s in entry["stages"]}

    def close(self) -> None:
        self.client.close()
        self.gateway.close()
        for bus in reversed(self.buses):
            bus.close()
        self.broker.stop()


@pytest.fixture
def lab(tmp_path: Path) -> Iterator[Lab]:
    lab = Lab(tmp_path)
    try:
        with lab.client:
            yield lab
    finally:
        lab.close()


def _page_ms(ns: int | None = None) -> float:
    return (time.time_ns() if ns is None else ns) / 1e6  # the test's "page" shares the server's clock


def _synced(ws: WebSocketTestSession) -> None:
    sync = ws.receive_json()
    assert sync["t"] == "sync"
    ws.send_json({"t": "sync", "id": sync["id"], "page_ms": _page_ms()})


def test_reports_need_a_login_this_origin_and_the_csrf_token(lab: Lab) -> None:
    assert lab.client.get("/api/latency").status_code == 401
    cases: list[tuple[Callable[[], WebSocketTestSession], str]] = [
        (lambda: lab.page("x"), "log in"),
        (lambda: lab.page(lab.login(), origin="https://evil.example"), "origin"),
        (lambda: lab.page(lab.login(), origin=None), "origin"),
        (lambda: lab.page("wrong" if lab.login() else ""), "CSRF"),
        (
            lambda: lab.client.websocket_connect(
                "/api/latency", headers={"origin": ORIGIN} if lab.login() else {}
            ),
            "CSRF",
        ),
    ]
    for open_page, why in cases:
        with pytest.raises(WebSocketDisconnect) as refused, open_page():
            pass
        assert refused.value.code == 1008
        assert why in str(refused.value.reason)
        lab.client.cookies.clear()  # the next case starts logged out unless it logs in
    lab.login()
    assert lab.counters() == {}  # nothing of the refused pages reached the counters


def test_garbage_reports_are_counted_and_dropped_and_a_good_one_is_the_rendered_stage(lab: Lab) -> None:
    csrf = lab.login()
    now = time.time_ns()
    state = str(now - 7 * MS)  # a joint state measured 7 ms before the page drew it
    with lab.page(csrf) as ws:
        ws.send_json(
            {"t": "rendered", "robot": "arm0", "stamp": state, "page_ms": _page_ms()}
        )  # no clock yet
        _synced(ws)
        garbage: list[tuple[str, str | bytes]] = [
            ("binary", b"\x00\x01"),
            ("size", json.dumps({"t": "rendered", "pad": "x" * MAX_MESSAGE})),
            ("json", "not json {"),
            ("json", "[1, 2]"),
            ("type", json.dumps({"t": "estop"})),
            ("field", json.dumps({"t": "rendered", "robot": "arm0", "page_ms": _page_ms()})),
            ("field", json.dumps({"t": "rendered", "robot": "arm0", "stamp": "12ab", "page_ms": 1.0})),
            ("field", json.dumps({"t": "rendered", "robot": "arm0", "stamp": 2.0**70, "page_ms": 1.0})),
            ("field", '{"t": "rendered", "robot": "arm0", "stamp": NaN, "page_ms": 1.0}'),
            ("field", json.dumps({"t": "rendered", "robot": "arm0", "stamp": state, "page_ms": 1e300})),
            (
                "field",
                json.dumps({"t": "rendered", "robot": ["arm0"], "stamp": state, "page_ms": _page_ms()}),
            ),
            ("field", json.dumps({"t": "sync", "id": 999, "page_ms": _page_ms()})),
            ("node", json.dumps({"t": "rendered", "robot": "ghost", "stamp": state, "page_ms": _page_ms()})),
            ("stale", json.dumps({"t": "rendered", "robot": "arm0", "stamp": "1", "page_ms": _page_ms()})),
            (
                "future",
                json.dumps({"t": "rendered", "robot": "arm0", "stamp": state, "page_ms": _page_ms() + 6e4}),
            ),
            (
                "order",
                json.dumps(
                    {"t": "rendered", "robot": "arm0", "stamp": state, "page_ms": _page_ms(now - 9 * MS)}
                ),
            ),
            (
                "unknown_frame",
                json.dumps({"t": "displayed", "camera": "scene", "stamp": state, "page_ms": _page_ms()}),
            ),
        ]
        for _, message in garbage:
            if isinstance(message, bytes):
                ws.send_bytes(message)
            else:
                ws.send_text(message)
        good = {"t": "rendered", "robot": "arm0", "stamp": state, "page_ms": _page_ms(now)}
        ws.send_json(good)
        ws.send_json(good)  # the same state again: counted once
        expected = {"drop_unsynced": 1, "rendered": 1, "drop_repeat": 1}
        for reason, _ in garbage:
            expected[f"drop_{reason}"] = expected.get(f"drop_{reason}", 0) + 1
        assert wait_for(lambda: {k: lab.counters().get(k) for k in expected} == expected), lab.counters()
        rendered = lab.stages("arm0")["rendered"]
        assert rendered["count"] == 1
        # The page's clock maps to the server's within half the clock exchange's round trip (a few ms
        # through the test client on a loaded host).
        assert rendered["p50_ms"] == pytest.approx(7.0, abs=10.0)
        assert rendered["light"] == "green"  # within the 50 ms default budget
        # Published as web on the robot's latency_view stream (the ACL lets web publish only there).
        assert wait_for(
            lambda: any(v["node"] == "arm0" and v["stages"]["rendered"]["count"] == 1 for v in lab.views)
        )


def test_a_stamped_preview_gives_the_video_stages_when_a_page_displays_it(lab: Lab) -> None:
    camera_bus = lab.bus("cam-scene")
    capture = time.time_ns() - 30 * MS  # a frame captured 30 ms ago
    with PreviewPublisher(camera_bus, "demo", "scene", rate_hz=2.0) as preview:
        assert preview.offer(np.zeros((120, 160, 3), np.uint8), capture)
    assert wait_for(lambda: lab.gateway.preview_capture_ns("scene") == capture)
    csrf = lab.login()
    reply = lab.client.get("/api/rig/cameras/scene/preview")
    assert reply.status_code == 200
    assert reply.headers["x-capture-ns"] == str(capture)
    with lab.page(csrf) as ws:
        _synced(ws)
        # A browser's number carries 53 bits: the stamp arrives a few hundred ns off, and still matches.
        ws.send_json({"t": "displayed", "camera": "scene", "stamp": float(capture), "page_ms": _page_ms()})
        assert wait_for(lambda: lab.counters().get("displayed") == 1), lab.counters()
    stages = lab.stages("scene")
    assert list(stages) == ["video_encode", "video_deliver", "video_display"]
    assert all(s["count"] == 1 for s in stages.values())
    total = sum(s["p50_ms"] for s in stages.values())
    assert 30.0 <= total < 2000.0
    assert stages["video_encode"]["p50_ms"] >= 30.0  # captured 30 ms before it was offered


def test_forged_control_node_latency_reports_are_dropped_and_a_real_one_shows(lab: Lab) -> None:
    lab.login()
    bus = lab.bus("ctl-arm0")
    topic = str(Topic("demo", "arm0", "latency"))
    forged = [
        b"\xff\xfe",
        b"[]",
        json.dumps({"type": "latency_stages", "stages": {}, "end_to_end": {}, "out_of_order": 0}).encode(),
        json.dumps({"type": "latency_stages", "stages": {"bus": {"count": 1}}}).encode(),
        b'{"type": "latency_stages", "stages": {"receive": {"count": 1, "p50_ms": Infinity}}}',
        b"{" + b" " * (70 * 1024) + b"}",
    ]
    before = sum(lab.gateway.dropped.values())
    for payload in forged:
        bus.publish(topic, payload, qos=1)
    assert wait_for(lambda: sum(lab.gateway.dropped.values()) - before == len(forged)), lab.gateway.dropped
    health = ControlHealth("demo", "arm0", bus, clock=lambda: now)
    now = time.time_ns()
    for i in range(20):
        c = now - 100 * MS + i * MS
        health.sent(
            c, c + 4 * MS, c + 2 * MS, arrival_ns=c + MS, received_ns=c + 2 * MS, retargeted_ns=c + 3 * MS
        )
        health.measured(c + 6 * MS, c + 6 * MS)
    health.publish()
    assert wait_for(lambda: "bus" in lab.stages("arm0")), lab.client.get("/api/rig").json()["latency_stages"]
    stages = lab.stages("arm0")
    assert [s for s in stages if s != "rendered"] == ["receive", "bus", "queue", "retarget", "apply", "state"]
    assert stages["state"]["p50_ms"] == pytest.approx(2.0)
    snapshot = lab.client.get("/api/rig").json()
    (arm,) = [s for s in snapshot["latency_stages"] if s["node"] == "arm0"]
    assert arm["end_to_end"]["p50_ms"] == pytest.approx(6.0)
