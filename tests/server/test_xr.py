"""The WebXR page and its pose stream behind the control center's login (issue 14: one web server).

A real Mosquitto with the webxr rig's ACL; the control center's gateway logs in as ``web`` and the
rig's WebXR device runs in its real device node (``dev-browser``), so every accepted message goes
over the bus to the device and comes out as the device's samples on the rig's topics.
"""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from argon2 import PasswordHasher
from fastapi.testclient import TestClient
from starlette.testclient import WebSocketTestSession
from starlette.websockets import WebSocketDisconnect

from telerig.bus.acl import CLI, STATION, WEB, rig_access_policy
from telerig.bus.base import Message
from telerig.bus.broker import MosquittoBroker
from telerig.bus.mqtt import MqttBus
from telerig.config import load_rig
from telerig.devices.webxr.device import CLOSE_REFUSED, WebXRDevice
from telerig.devices.webxr.fake import XRControllerInput, encode_frame, encode_pong
from telerig.devices.webxr.relay import MESSAGE, OPEN, PAGE_SUBPROTOCOL, encode_event, open_body
from telerig.runtime.device_node import DeviceNode
from telerig.server import routes_xr
from telerig.server.accounts import AccountStore
from telerig.server.app import create_app
from telerig.server.auth import CSRF_HEADER
from telerig.server.gateway import RigGateway

pytestmark = pytest.mark.broker

PASSWORD = "correct horse battery"
FAST = PasswordHasher(time_cost=1, memory_cost=64, parallelism=1)
ORIGIN = "http://testserver"
RIGHT = "telerig/v1/webxr/browser/right_controller"


def wait_for(condition: Callable[[], object], timeout_s: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.02)
    return bool(condition())


class Lab:
    """The webxr rig's broker, its device node, the control center on it, and what the rig's
    right-controller topic carried."""

    def __init__(self, tmp: Path) -> None:
        self.config = load_rig("webxr")
        self.broker = MosquittoBroker(access=rig_access_policy(self.config), owner=STATION).start()
        self.buses: list[MqttBus] = []
        device = self.config.devices[0].build()
        assert isinstance(device, WebXRDevice)
        self.device = device
        self.node = DeviceNode("webxr", self.device, self.bus("dev-browser"), health_period_s=None)
        self.samples: list[Message] = []
        self.bus(STATION).subscribe(RIGHT, self.samples.append)
        self.gateway = RigGateway(self.config, self.broker.url_for(WEB)).start()
        self.accounts = AccountStore.open(tmp, hasher=FAST)
        self.accounts.add_user("otto", "operator", PASSWORD)
        self.accounts.add_user("ada", "admin", PASSWORD)
        self.accounts.add_user("vic", "viewer", PASSWORD)
        self.client = TestClient(create_app(self.accounts, gateway=self.gateway))
        self.node.start()

    def bus(self, principal: str) -> MqttBus:
        bus = MqttBus(self.broker.url_for(principal), client_id=f"{principal}-{len(self.buses)}").connect()
        self.buses.append(bus)
        return bus

    def login(self, user: str, client: TestClient | None = None) -> str:
        reply = (client or self.client).post("/api/login", json={"user": user, "password": PASSWORD})
        assert reply.status_code == 200, reply.text
        csrf: str = reply.json()["csrf"]
        return csrf

    def page(
        self,
        csrf: str,
        *,
        device: str = "browser",
        origin: str | None = ORIGIN,
        client: TestClient | None = None,
    ) -> WebSocketTestSession:
        headers = {} if origin is None else {"origin": origin}
        protocols = [PAGE_SUBPROTOCOL, f"csrf.{csrf}"]
        return (client or self.client).websocket_connect(
            f"/api/xr/{device}", subprotocols=protocols, headers=headers
        )

    def counters(self) -> dict[str, int]:
        reply = self.client.get("/api/xr")
        assert reply.status_code == 200, reply.text
        (device,) = reply.json()
        counters: dict[str, int] = device["counters"]
        return counters

    def close(self) -> None:
        self.client.close()
        self.node.stop()
        self.gateway.close()
        for bus in reversed(self.buses):
            bus.close()
        self.broker.stop()


@pytest.fixture
def lab(tmp_path: Path) -> Iterator[Lab]:
    lab = Lab(tmp_path)
    try:
        yield lab
    finally:
        lab.close()


def _frame(seq: int, **controller: object) -> bytes:
    return encode_frame(seq, time.time_ns() / 1e6, mode="desktop", right=XRControllerInput(**controller))  # type: ignore[arg-type]


def _refused(lab: Lab, open_page: Callable[[], WebSocketTestSession]) -> str:
    with pytest.raises(WebSocketDisconnect) as refused, open_page():
        pass
    assert refused.value.code == 1008
    return str(refused.value.reason)


def test_the_page_needs_a_login_and_the_operator_role(lab: Lab) -> None:
    client = lab.client
    assert client.get("/xr", follow_redirects=False).headers["location"] == "/login"
    assert client.get("/api/xr").status_code == 401
    lab.login("vic")
    viewer = client.get("/xr")
    assert viewer.status_code == 403
    assert "operator" in viewer.json()["detail"]
    assert client.get("/api/xr").json()[0]["device"] == "browser"  # a viewer may read the counters
    lab.login("otto")
    page = client.get("/xr")
    assert page.status_code == 200
    assert "/xr/telerig-xr.js" in page.text
    assert "default-src 'self'" in page.headers["content-security-policy"]
    assert client.get("/xr/telerig-xr.js").headers["content-type"].startswith("text/javascript")
    assert client.get("/xr/telerig-xr.css").status_code == 200
    for path in ("/xr/index.html", "/xr/fake-xr.js", "/xr/..%2Fdevice.py", "/xr/%2e%2e%2fconfig.py"):
        assert client.get(path).status_code == 404, path


def test_the_websocket_refuses_no_login_a_viewer_a_foreign_origin_and_a_missing_csrf_token(lab: Lab) -> None:
    anonymous = TestClient(lab.client.app)
    assert "log in" in _refused(lab, lambda: lab.page("x", client=anonymous))
    csrf = lab.login("vic")
    assert "operator" in _refused(lab, lambda: lab.page(csrf))
    csrf = lab.login("otto")
    assert "origin" in _refused(lab, lambda: lab.page(csrf, origin="https://evil.example"))
    assert "origin" in _refused(lab, lambda: lab.page(csrf, origin=None))  # this route moves a robot
    assert "CSRF" in _refused(lab, lambda: lab.page("wrong"))
    assert "CSRF" in _refused(
        lab, lambda: lab.client.websocket_connect("/api/xr/browser", headers={"origin": ORIGIN})
    )
    assert "no WebXR device" in _refused(lab, lambda: lab.page(csrf, device="nobody"))
    assert lab.counters().get("connections", 0) == 0
    assert lab.device.stats.get("connections", 0) == 0


def test_frames_reach_the_device_and_garbage_oversized_and_extreme_ones_are_counted_and_dropped(
    lab: Lab, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A rate limit this loaded host cannot outrun by itself: 20 messages, then 2 a second.
    monkeypatch.setattr(routes_xr, "_BURST", 20.0)
    monkeypatch.setattr(routes_xr, "MAX_RATE_HZ", 2.0)
    csrf = lab.login("otto")
    with lab.page(csrf) as ws:
        assert ws.accepted_subprotocol == PAGE_SUBPROTOCOL
        ws.send_bytes(_frame(0, trigger=0.25))
        assert wait_for(lambda: lab.samples), "the relayed frame never became a sample on the rig's bus"
        ping = ws.receive_bytes()  # the device's clock ping, relayed back
        assert (len(ping), ping[:2], ping[3]) == (8, b"TX", 3)
        ws.send_bytes(encode_pong(struct.unpack_from("<I", ping, 4)[0], time.time_ns() / 1e6))
        ws.send_text("hello")
        ws.send_bytes(b"\x00garbage")
        ws.send_bytes(b"TX\x01\x01" + b"\x00" * (64 << 10))  # oversized
        ws.send_bytes(_frame(1, position=(1e30, 0.0, 0.0)))
        ws.send_bytes(_frame(2, position=(float("nan"), 1.0, 0.0)))
        ws.send_bytes(_frame(3, orientation=(0.0, 0.0, 0.0, 7.0)))
        ws.send_bytes(_frame(4, trigger=3.0))
        ws.send_bytes(_frame(5, thumbstick=(float("inf"), 0.0)))
        ws.send_bytes(_frame(6)[:-3])  # truncated
        ws.send_bytes(b"")
        for seq in range(7, 7 + 100):  # a flood, beyond the rate limit
            ws.send_bytes(_frame(seq))
    counted = lab.counters()
    assert counted["drop_text"] == 1
    assert counted["drop_magic"] == 1
    assert counted["drop_size"] >= 3  # oversized, truncated, empty
    assert counted["drop_position"] == 2
    assert counted["drop_orientation"] == 1
    assert counted["drop_analog"] == 2
    assert counted["drop_rate"] > 60
    assert counted["pongs"] == 1
    assert wait_for(lambda: lab.device.stats.get("frames") == counted["frames"])
    stats = lab.device.stats
    assert not {k for k in stats if k.startswith("drop_")}, stats  # nothing bad crossed the bus
    assert wait_for(lambda: len(lab.samples) == lab.node.published)  # what the node's validator passed
    assert wait_for(lambda: lab.device.active_user is None)  # the page's close reached the device
    actions = [(e.action, e.user, e.target) for e in lab.accounts.audit_log()]
    assert ("xr_connect", "otto", "webxr/browser") in actions
    disconnect = next(e for e in lab.accounts.audit_log() if e.action == "xr_disconnect")
    assert "drop_rate" in disconnect.detail


def test_only_the_web_server_may_relay_a_page(lab: Lab) -> None:
    # The operator command line's principal publishes a page and a frame on the device's page_in:
    # the broker's ACL drops them, so nothing reaches the device without the web login.
    cli = lab.bus(CLI)
    topic = "telerig/v1/webxr/browser/page_in"
    cli.publish(topic, encode_event(OPEN, 1, open_body("mallory", "x")), qos=1)
    cli.publish(topic, encode_event(MESSAGE, 1, _frame(0)), qos=1)
    csrf = lab.login("otto")
    with lab.page(csrf) as ws:  # a page through the server afterwards does arrive
        ws.send_bytes(_frame(0))
        assert wait_for(lambda: lab.samples)
    assert lab.device.stats["connections"] == 1
    assert lab.device.stats["frames"] == 1


def test_a_second_page_waits_for_the_operators_answer_and_a_denial_closes_it(lab: Lab) -> None:
    # The shipped webxr rig holds a second page until the operator answers (takeover: confirm).
    csrf = lab.login("otto")
    second_client = TestClient(lab.client.app)
    second_csrf = lab.login("ada", second_client)
    with lab.page(csrf) as first:
        first.send_bytes(_frame(0))
        assert wait_for(lambda: lab.device.active_user is not None)
        with lab.page(second_csrf, client=second_client) as second:
            assert wait_for(lambda: lab.device.pending_takeover is not None)
            assert "ada" in str(lab.device.pending_takeover)
            answer = lab.client.post(
                "/api/rig/devices/browser/takeover", json={"answer": "deny"}, headers={CSRF_HEADER: csrf}
            )
            assert answer.status_code == 200, answer.text
            closed: list[int] = []

            def read() -> None:
                try:
                    while True:
                        second.receive_bytes()
                except WebSocketDisconnect as exc:
                    closed.append(exc.code)

            reader = threading.Thread(target=read, daemon=True)
            reader.start()
            reader.join(5.0)
            assert closed == [CLOSE_REFUSED]
    assert lab.device.stats["refused_takeover"] == 1


def test_a_logout_ends_the_stream(lab: Lab, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(routes_xr, "RECHECK_S", 0.0)
    csrf = lab.login("otto")
    with lab.page(csrf) as ws:
        ws.send_bytes(_frame(0))
        assert wait_for(lambda: lab.samples)
        assert lab.client.post("/api/logout", headers={CSRF_HEADER: csrf}).status_code == 204
        ws.send_bytes(_frame(1))  # the next message finds the login gone
        with pytest.raises(WebSocketDisconnect) as ended:
            _read_until_closed(ws)
        assert ended.value.code == 1008


def _read_until_closed(ws: WebSocketTestSession) -> None:
    while True:  # pings until the close
        ws.receive_bytes()


def test_telerig_serve_prints_the_xr_page_and_its_qr_code_for_a_headset_on_the_lan(
    capsys: pytest.CaptureFixture[str],
) -> None:
    from telerig.cli.serve import _print_xr_page
    from telerig.devices.webxr.pairing import lan_url_host

    _print_xr_page(load_rig("webxr"), "https", "0.0.0.0", 8443)
    out = capsys.readouterr().out
    assert f"https://{lan_url_host('0.0.0.0')}:8443/xr" in out
    assert "\u2580" in out or "\u2584" in out or "\u2588" in out  # the QR code, in half blocks
    _print_xr_page(load_rig("webxr"), "https", "127.0.0.1", 8443)
    assert capsys.readouterr().out.strip().endswith("https://127.0.0.1:8443/xr")  # no QR on loopback
    _print_xr_page(load_rig("demo"), "https", "127.0.0.1", 8443)
    assert capsys.readouterr().out == ""  # no WebXR device


def test_a_page_is_told_when_the_rig_is_not_reachable(lab: Lab) -> None:
    csrf = lab.login("otto")
    lab.gateway.close()  # the rig's broker is gone (telerig run stopped)
    with lab.page(csrf) as ws, pytest.raises(WebSocketDisconnect) as closed:
        ws.receive_bytes()
    assert closed.value.code == 1013
    assert "not running" in str(closed.value.reason)
