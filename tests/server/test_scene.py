"""The operator scene's page, files and WebSocket against a real Mosquitto with the demo rig's ACL (no
browser): who may open it, what it sends, and that garbage from the page or the bus is dropped and
counted while the feed goes on."""

from __future__ import annotations

import json
import math
import os
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

from telerig.bus.acl import CLI, STATION, WEB, rig_access_policy
from telerig.bus.broker import MosquittoBroker
from telerig.bus.mqtt import MqttBus
from telerig.config import load_rig
from telerig.ir import wire
from telerig.ir.types import JointState, Stamp
from telerig.robots.models import arm_model
from telerig.server.accounts import AccountStore
from telerig.server.app import create_app
from telerig.server.gateway import RigGateway
from telerig.server.routes_scene import SCENE_SUBPROTOCOL
from telerig.server.scene import SCENE_HZ, SceneHub
from telerig.voice.dispatch import Dispatcher

pytestmark = [pytest.mark.broker, pytest.mark.sim, pytest.mark.timeout(120)]

PASSWORD = "correct horse battery"
ORIGIN = "http://testserver"
R = "telerig/v1/demo"


def _tick(joint_state: bytes) -> bytes:
    """A control tick carrying ``joint_state`` (what a control node publishes)."""
    return wire.encode_bundle([("joint_state", joint_state)])


UR5E = arm_model("ur5e_robotiq85")


class Lab:
    """The demo rig's broker with its ACL, the control center on it, and the control node's login."""

    def __init__(self, tmp: Path) -> None:
        self.config = load_rig("demo")
        self.broker = MosquittoBroker(access=rig_access_policy(self.config), owner=STATION).start()
        self.gateway = RigGateway(self.config, self.broker.url_for(WEB)).start()
        accounts = AccountStore.open(tmp, hasher=PasswordHasher(time_cost=1, memory_cost=64, parallelism=1))
        accounts.add_user("vic", "viewer", PASSWORD)
        self.client = TestClient(create_app(accounts, gateway=self.gateway))
        self.robot = MqttBus(self.broker.url_for("ctl-arm0"), client_id="ctl-arm0").connect()
        self.seq = 0

    def login(self) -> str:
        reply = self.client.post("/api/login", json={"user": "vic", "password": PASSWORD})
        assert reply.status_code == 200, reply.text
        csrf: str = reply.json()["csrf"]
        return csrf

    def scene(self, csrf: str | None, *, origin: str | None = ORIGIN) -> WebSocketTestSession:
        protocols = [SCENE_SUBPROTOCOL] + ([] if csrf is None else [f"csrf.{csrf}"])
        headers = {} if origin is None else {"origin": origin}
        return self.client.websocket_connect("/api/scene", subprotocols=protocols, headers=headers)

    def joints(self, q: tuple[float, ...], names: tuple[str, ...] = UR5E.joints) -> int:
        """Publish a joint state; returns its stamp's capture_ns [ns]."""
        self.seq += 1
        state = JointState(Stamp.now("arm0", self.seq), names, np.array(q), np.zeros(len(q)))
        self.robot.publish(f"{R}/arm0/tick", _tick(wire.encode(state)))
        return state.stamp.capture_ns

    def hub(self) -> SceneHub:
        hub: SceneHub = self.client.app.state.scene_hub  # type: ignore[attr-defined]
        return hub

    def close(self) -> None:
        self.robot.close()
        self.gateway.close()
        self.broker.stop()


@pytest.fixture
def lab(tmp_path: Path) -> Iterator[Lab]:
    running = Lab(tmp_path)
    try:
        with running.client:
            yield running
    finally:
        running.close()


def refused(open_scene: Callable[[], WebSocketTestSession]) -> str:
    with pytest.raises(WebSocketDisconnect) as caught, open_scene():
        pass
    assert caught.value.code == 1008
    return str(caught.value.reason)


def next_state(
    ws: WebSocketTestSession, until: Callable[[dict[str, Any]], bool], timeout_s: float = 10.0
) -> Any:
    """The first state message for which ``until`` holds (the feed resends every second)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        message = json.loads(ws.receive_text())
        assert message["type"] == "state"
        if until(message):
            return message
    raise AssertionError("no such state within the timeout")


def test_the_page_and_its_files_need_a_login_and_name_the_make_target_when_three_is_missing(
    lab: Lab, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    client = lab.client
    assert client.get("/scene", follow_redirects=False).headers["location"] == "/login"
    lab.login()
    page = client.get("/scene")
    assert page.status_code == 200
    assert "'sha256-" in page.headers["content-security-policy"]  # the import map, nothing else inline
    assert '"three": "/scene/three.module.js"' in page.text
    assert client.get("/scene/three.module.js").status_code == 200
    assert "OrbitControls" in client.get("/scene/OrbitControls.js").text
    for bad in ("../app.py", "..%2F..%2Fpyproject.toml", "scene.html", "x" * 5000, "three.module.js%00"):
        assert client.get(f"/scene/{bad}").status_code == 404, bad
    monkeypatch.setenv("TELERIG_NODE_MODULES", str(tmp_path / "empty"))
    missing = client.get("/scene")
    assert missing.status_code == 503
    assert "make scene-js" in missing.json()["detail"]
    assert "\n" not in missing.json()["detail"]
    assert client.get("/scene/three.core.js").status_code == 503


def test_the_websocket_refuses_strangers_and_sends_the_geometry_then_live_poses(lab: Lab) -> None:
    assert "log in" in refused(lambda: lab.scene("whatever"))
    csrf = lab.login()
    assert "origin" in refused(lambda: lab.scene(csrf, origin="http://evil.example"))
    assert "origin" in refused(lambda: lab.scene(csrf, origin=None))  # browsers always send one
    assert "CSRF" in refused(lambda: lab.scene(None))
    assert "CSRF" in refused(lambda: lab.scene("0" * 43))
    with lab.scene(csrf) as ws:
        scene = json.loads(ws.receive_text())
        assert scene["type"] == "scene"
        assert scene["rig"] == "demo"
        assert scene["hz"] == SCENE_HZ
        (robot,) = scene["robots"]
        assert robot["model"] == "ur5e_robotiq85"
        assert robot["joints"] == list(UR5E.joints)
        assert len(robot["geoms"]) > 10
        assert robot["meshes"]
        assert 0.9 < robot["reach_m"] < 1.3  # UR5e: 850 mm from the shoulder, plus gripper and base
        assert scene["cameras"] == ["scene"]
        assert scene["hands"] == [{"device": "vr0", "part": "right_controller", "robot": "arm0"}]
        first = json.loads(ws.receive_text())
        assert first["robots"]["arm0"]["state_ns"] is None  # no joint state yet
        stamp = lab.joints(UR5E.home)
        home = next_state(ws, lambda m: m["robots"]["arm0"]["joint_age_s"] is not None)
        assert home["connected"] is True
        # The stamp of the joint state the poses come from, exact (a string: ns overflow JS numbers).
        assert home["robots"]["arm0"]["state_ns"] == str(stamp)
        q = list(UR5E.home)
        q[0] = 0.9
        turn = lab.joints(tuple(q))
        turned = next_state(ws, lambda m: m["robots"]["arm0"]["ee"] != home["robots"]["arm0"]["ee"])
        assert turned["robots"]["arm0"]["state_ns"] == str(turn)
        ee0, ee1 = home["robots"]["arm0"]["ee"], turned["robots"]["arm0"]["ee"]
        # A turn of the base joint keeps the grasp point's height and its distance from the z axis.
        assert ee1[2] == pytest.approx(ee0[2], abs=1e-4)
        assert math.hypot(*ee1[:2]) == pytest.approx(math.hypot(*ee0[:2]), abs=1e-4)
        assert math.atan2(ee1[1], ee1[0]) - math.atan2(ee0[1], ee0[0]) == pytest.approx(0.9, abs=1e-3)
        assert len(turned["robots"]["arm0"]["poses"]) == 7 * len(robot["bodies"])


def test_garbage_from_the_page_and_the_bus_is_dropped_and_counted_and_the_feed_goes_on(lab: Lab) -> None:
    csrf = lab.login()
    station = MqttBus(lab.broker.url_for(STATION), client_id="station").connect()
    try:
        with lab.scene(csrf) as ws:
            assert json.loads(ws.receive_text())["type"] == "scene"
            lab.joints(UR5E.home)
            good = next_state(ws, lambda m: m["robots"]["arm0"]["joint_age_s"] is not None)
            # From the page: binary noise, text that is not JSON, an oversized frame, a burst.
            rng = np.random.default_rng(7)
            ws.send_bytes(rng.bytes(4096))
            ws.send_text("{not json")
            ws.send_text("x" * (1 << 20))
            for _ in range(200):
                ws.send_bytes(b"\x00")
            # From the bus: garbage, truncated, oversized and unmatched joint states keep the last good
            # pose; extreme but finite angles are drawn; aids that are not JSON objects or carry NaN,
            # long status words and a node the rig does not have are dropped.
            topic = f"{R}/arm0/tick"
            valid = wire.encode(JointState(Stamp.now("arm0", 99), UR5E.joints, np.zeros(6), np.zeros(6)))
            lab.robot.publish(topic, rng.bytes(200))  # not a tick at all
            lab.robot.publish(topic, _tick(rng.bytes(200)))
            lab.robot.publish(topic, _tick(valid[:-5]))
            lab.robot.publish(topic, _tick(b"\x00" * (65 * 1024)))
            lab.joints((0.1,), names=("no_such_joint",))
            station.publish(f"{R}/ghost/tick", _tick(valid))
            kept = next_state(
                ws, lambda m: lab.hub().dropped["unknown_node"] > 0 and m["seq"] > good["seq"] + 2
            )
            assert kept["robots"]["arm0"]["poses"] == good["robots"]["arm0"]["poses"]
            assert kept["robots"]["arm0"]["state_ns"] == good["robots"]["arm0"]["state_ns"]
            lab.joints((1e308, -1e308, 0.0, 0.0, 0.0, 0.0))
            extreme = next_state(
                ws, lambda m: m["robots"]["arm0"]["poses"] != good["robots"]["arm0"]["poses"]
            )
            assert all(math.isfinite(v) for v in extreme["robots"]["arm0"]["poses"])
            lab.robot.publish(f"{R}/arm0/fixture", b"[1, 2, 3]", qos=1)
            lab.robot.publish(
                f"{R}/arm0/fixture", b'{"name": "x", "kind": "axis", "axis": [NaN, 0, 0]}', qos=1
            )
            lab.robot.publish(f"{R}/arm0/motion_scale", b"\xff\xfe not utf-8", qos=1)
            lab.robot.publish(f"{R}/arm0/status", b"estopped" * 200, qos=1)  # over the 1 KiB of text
            lab.robot.publish(f"{R}/arm0/status", b"holding" + b" x" * 400, qos=1)
            lab.joints(UR5E.home)
            after = next_state(ws, lambda m: m["robots"]["arm0"]["status"] is not None)
            arm = after["robots"]["arm0"]
            assert arm["status"].startswith("holding")
            assert len(arm["status"]) <= 200
            assert arm["fixture"] is None  # neither the list nor the NaN document was taken
            assert arm["scale"] is None
            dropped = lab.hub().dropped
            assert dropped["unknown_node"] >= 1
            assert dropped["bad_joint_state"] >= 1 or dropped["oversize"] >= 1
    finally:
        station.close()
    hub = lab.hub()
    assert hub.dropped["oversize"] >= 1, hub.dropped  # 65 KiB > the catalogue's 64 KiB for IR samples
    # A new client after all that gets the scene and a state at once.
    with lab.scene(csrf) as ws:
        assert json.loads(ws.receive_text())["type"] == "scene"
        assert json.loads(ws.receive_text())["type"] == "state"
    assert os.environ.get("TELERIG_NODE_MODULES") is None


def test_a_robot_without_a_model_the_scene_draws_is_named_with_the_fix_and_the_rest_goes_on() -> None:
    gateway = RigGateway(load_rig("gripper"), "mqtt://127.0.0.1:9")  # never started: no broker needed
    hub = SceneHub(gateway)
    hub.start()
    robots = hub.document()["robots"]
    assert isinstance(robots, list)
    (robot,) = robots
    assert isinstance(robot, dict)
    assert "names no model the scene draws" in str(robot["error"])
    assert "mujoco_gripper" in str(robot["error"])
    assert hub.state()["robots"] == {}
    assert hub.state()["connected"] is False  # the page says the rig is not reachable


def test_a_perspective_command_picks_the_view_once_and_its_reply_is_shown(lab: Lab) -> None:
    """``telerig say 'natural perspective'`` (the cli login, through the rig's ACL) reaches the
    scene's state as the view to pick, with an arrival number the page applies once; a rejected
    phrase's reply shows too, and a view name the page does not have is never passed on."""
    cli = MqttBus(lab.broker.url_for(CLI), client_id="cli").connect()
    try:

        def publish(topic: str, payload: bytes, qos: int, retain: bool) -> None:
            cli.publish(topic, payload, qos=qos, retain=retain)

        say = Dispatcher("demo", publish, source="cli")
        csrf = lab.login()
        with lab.scene(csrf) as ws:
            assert json.loads(ws.receive_text())["type"] == "scene"
            first = json.loads(ws.receive_text())
            assert first["voice"] == {"view": None, "view_seq": None, "feedback": None}
            assert say.handle("natural perspective").status == "done"
            picked = next_state(ws, lambda m: m["voice"]["view"] is not None)["voice"]
            assert picked["view"] == "ee"
            assert picked["feedback"] == {
                "heard": "natural perspective",
                "status": "done",
                "say": picked["feedback"]["say"],
            }
            assert say.handle("open the pod bay doors").status == "rejected"
            rejected = next_state(ws, lambda m: (m["voice"]["feedback"] or {}).get("status") == "rejected")
            assert rejected["voice"]["view_seq"] == picked["view_seq"]  # the same choice: not applied again
            assert rejected["voice"]["feedback"]["heard"] == "open the pod bay doors"
            cli.publish(f"{R}/voice/view", json.dumps({"view": "ceiling"}).encode(), qos=1, retain=True)
            odd = next_state(ws, lambda m: m["voice"]["view"] is None)
            assert odd["voice"]["view_seq"] is None
    finally:
        cli.publish(f"{R}/voice/view", b"", qos=1, retain=True)  # no retained view left on the broker
        cli.close()
