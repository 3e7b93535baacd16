"""Device registration as an attacker sees it: the logins the control center issues are what a real
Mosquitto enforces (own streams only; nothing on another device's or robot's topics, nor the safety
or coordinator commands), a revoked login is cut off, only admins register, garbage ids are 422
and the password is in no log, file or later reply."""

from __future__ import annotations

import base64
import hashlib
import logging
import os
import pwd
import shutil
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import paho.mqtt.client as paho
import pytest
from argon2 import PasswordHasher
from fastapi.testclient import TestClient
from tests.ports import MOSQUITTO_RUNNING, on_a_free_port, start_listening

from telerig.bus.base import Message
from telerig.bus.login import BusLogin
from telerig.bus.mqtt import MqttBus
from telerig.cli.main import main as telerig_main
from telerig.config import load_rig
from telerig.config.schema import RigConfig
from telerig.errors import BusError
from telerig.server.accounts import AccountStore
from telerig.server.app import create_app
from telerig.server.auth import CSRF_HEADER, LoginLimiter
from telerig.server.devices import DeviceRegistry

pytestmark = pytest.mark.broker

PASSWORD = "correct horse battery"
FAST = PasswordHasher(time_cost=1, memory_cost=64, parallelism=1)
ROOT = "telerig/v1/fleet"


@pytest.fixture(scope="module")
def fleet() -> RigConfig:
    return load_rig("fleet")


@dataclass
class Lab:
    """A data root with accounts, the fleet rig's broker folder and a real Mosquitto on it."""

    root: Path
    folder: Path
    port: int
    proc: subprocess.Popen[bytes]
    client: TestClient
    registry: DeviceRegistry

    @property
    def address(self) -> str:
        return f"mqtt://127.0.0.1:{self.port}"

    def login(self, user: str = "ada") -> dict[str, str]:
        reply = self.client.post("/api/login", json={"user": user, "password": PASSWORD})
        assert reply.status_code == 200, reply.text
        return {CSRF_HEADER: reply.json()["csrf"]}

    def register(self, kind: str, device: str) -> dict[str, object]:
        headers = self.login()
        reply = self.client.post("/api/devices", json={"kind": kind, "device": device}, headers=headers)
        assert reply.status_code == 201, reply.text
        issued: dict[str, object] = reply.json()
        assert issued["broker"] == {
            "status": "signalled",
            "detail": f"SIGHUP sent to mosquitto (pid {self.proc.pid})",
        }
        time.sleep(0.3)  # the broker rereads its files
        return issued


@pytest.fixture
def lab(tmp_path: Path, fleet: RigConfig) -> Iterator[Lab]:
    root = tmp_path / "data"
    folder = root / "broker" / "fleet"
    pid_file = folder / "mosquitto.pid"
    log = tmp_path / "mosquitto.log"

    def start_mosquitto(port: int) -> tuple[int, subprocess.Popen[bytes]]:
        shutil.rmtree(folder, ignore_errors=True)  # left by an attempt whose port was taken
        log.unlink(missing_ok=True)
        # The station's, cli's and web's logins come from `telerig broker acl`, as a lab sets it up.
        address = f"mqtt://127.0.0.1:{port}"
        assert telerig_main(["broker", "acl", "fleet", "--out", str(folder), "--address", address]) == 0
        conf = tmp_path / "mosquitto.conf"
        conf.write_text(
            f"listener {port} 127.0.0.1\nallow_anonymous false\npersistence false\n"
            f"password_file {folder / 'passwd'}\nacl_file {folder / 'acl'}\npid_file {pid_file}\n"
            f"log_dest file {log}\nlog_type all\n"
            f"user {pwd.getpwuid(os.geteuid()).pw_name}\n"
        )
        return port, start_listening(["mosquitto", "-c", str(conf)], port, log, MOSQUITTO_RUNNING)

    port, proc = on_a_free_port(start_mosquitto)
    accounts = AccountStore.open(root, hasher=FAST)
    registry = DeviceRegistry.open(root, [fleet], reload_pid_file=pid_file)
    try:
        for name, role in (("ada", "admin"), ("otto", "operator"), ("vic", "viewer")):
            accounts.add_user(name, role, PASSWORD)
        app = create_app(accounts, limiter=LoginLimiter(failures=50, window_s=60))
        app.state.devices = registry
        with TestClient(app) as client:
            yield Lab(root, folder, port, proc, client, registry)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=5)
        registry.close()
        accounts.close()


class _Seen:
    def __init__(self) -> None:
        self.topics: list[str] = []
        self._cond = threading.Condition()

    def __call__(self, message: Message) -> None:
        with self._cond:
            self.topics.append(message.topic)
            self._cond.notify_all()

    def wait_for(self, topic: str, timeout_s: float = 3.0) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: topic in self.topics, timeout_s)


def _arrived(lab: Lab, username: str, password: str, topics: list[str]) -> list[str]:
    """Publish on each topic with this login (QoS 1), then a marker as the station; the topics that
    reached the station's subscriber (which may read everything)."""
    station = BusLogin.read(lab.folder / "logins" / "station.json")
    seen = _Seen()
    marker = f"{ROOT}/m/end"
    with MqttBus(station.url, client_id="watch") as watcher:
        watcher.subscribe("#", seen, qos=1)
        time.sleep(0.2)
        with MqttBus(lab.address, client_id=f"as-{username}", username=username, password=password) as sender:
            for topic in topics:
                sender.publish(topic, b'{"command": "estop"}', qos=1)
            time.sleep(0.1)
        watcher.publish(marker, b"end", qos=1)
        assert seen.wait_for(marker), "the marker never arrived"
    return [t for t in seen.topics if t != marker]


def _refused(lab: Lab, username: str, password: str) -> bool:
    bus = MqttBus(
        lab.address, client_id=f"try-{username}", username=username, password=password, connect_timeout_s=2.0
    )
    try:
        bus.connect()
    except BusError as exc:
        return "refused" in str(exc)
    finally:
        bus.close()
    return False


_FORGED = [
    f"{ROOT}/vr_panda/command",  # another device's command topic
    f"{ROOT}/vr_panda/right_controller",  # another device's stream
    f"{ROOT}/panda/joint_command_requested",  # another robot's commands
    f"{ROOT}/panda/joint_command_sent",
    f"{ROOT}/panda/motion_scale_command",
    f"{ROOT}/safety/command",
    f"{ROOT}/coordinator/command",
    f"{ROOT}/coordinator/session",
    "elsewhere/topic",
]


def test_a_registered_device_publishes_its_own_streams_and_nothing_else(lab: Lab) -> None:
    old = BusLogin.read(lab.folder / "logins" / "dev-vr_ur5e.json")  # from `telerig broker acl`
    issued = lab.register("teleoperating", "vr_ur5e")
    assert issued["username"] == "dev-vr_ur5e"
    assert issued["device"]["publishes"] == [f"{ROOT}/vr_ur5e/#"]  # type: ignore[index]
    password = str(issued["password"])
    own = [f"{ROOT}/vr_ur5e/right_controller", f"{ROOT}/vr_ur5e/health"]
    assert _arrived(lab, "dev-vr_ur5e", password, [*_FORGED, f"{ROOT}/ur5e/joint_command_sent", *own]) == own
    # Its earlier login is gone from the broker and its login file removed; the others' are kept.
    assert _refused(lab, "dev-vr_ur5e", old.password)
    assert not (lab.folder / "logins" / "dev-vr_ur5e.json").exists()
    cli = BusLogin.read(lab.folder / "logins" / "cli.json")
    assert _arrived(lab, "cli", cli.password, [f"{ROOT}/safety/command"]) == [f"{ROOT}/safety/command"]


def test_a_registered_robot_publishes_its_robot_and_no_commands(lab: Lab) -> None:
    issued = lab.register("teleoperated", "ur5e")
    assert issued["username"] == "robot-ur5e"
    own = [f"{ROOT}/ur5e/joint_state", f"{ROOT}/ur5e/joint_command_sent"]
    # (R/vr_ur5e/# is its own too: acl.py lets a robot's process host the devices bound to it alone)
    assert _arrived(lab, "robot-ur5e", str(issued["password"]), [*_FORGED, *own]) == own


def test_a_revoked_device_is_cut_off_and_cannot_connect(lab: Lab) -> None:
    password = str(lab.register("teleoperating", "glove")["password"])
    connected, dropped = threading.Event(), threading.Event()
    client = paho.Client(paho.CallbackAPIVersion.VERSION2, client_id="glove")
    client.username_pw_set("dev-glove", password)
    client.reconnect_delay_set(5, 5)
    client.on_connect = lambda _c, _u, _f, reason, _p: reason.is_failure or connected.set()
    client.on_disconnect = lambda *_: dropped.set()
    client.connect("127.0.0.1", lab.port)
    client.loop_start()
    try:
        assert connected.wait(10.0), "the registered device was not let in"
        reply = lab.client.delete("/api/devices/fleet/dev-glove", headers=lab.login())
        assert reply.status_code == 200, reply.text
        assert reply.json()["device"]["active"] is False
        assert reply.json()["broker"]["status"] == "signalled"
        assert dropped.wait(3.0), "the broker kept the revoked device connected"
    finally:
        client.loop_stop()
        client.disconnect()
    assert _refused(lab, "dev-glove", password)
    assert "dev-glove:" not in (lab.folder / "passwd").read_text()
    audit = lab.client.get("/api/audit").json()
    assert [(e["action"], e["user"], e["target"]) for e in audit[:3] if e["action"].startswith("device")] == [
        ("device_revoked", "ada", "fleet/dev-glove"),
        ("device_registered", "ada", "fleet/dev-glove"),
    ]
    # Revoked twice: 404; registered again: a new password, the old one stays refused.
    assert lab.client.delete("/api/devices/fleet/dev-glove", headers=lab.login()).status_code == 404
    again = lab.register("teleoperating", "glove")
    assert again["password"] != password
    assert _refused(lab, "dev-glove", password)
    assert not _refused(lab, "dev-glove", str(again["password"]))


def test_only_an_admin_registers_or_revokes(lab: Lab) -> None:
    body = {"kind": "teleoperating", "device": "glove"}
    for user in ("vic", "otto"):
        headers = lab.login(user)
        assert lab.client.post("/api/devices", json=body, headers=headers).status_code == 403
        assert lab.client.get("/api/devices").status_code == 200  # but they may look
    lab.register("teleoperating", "glove")
    for user in ("vic", "otto"):
        assert lab.client.delete("/api/devices/fleet/dev-glove", headers=lab.login(user)).status_code == 403
    lab.login("ada")
    assert lab.client.post("/api/devices", json=body).status_code == 403  # no CSRF header
    assert lab.client.post("/api/devices", json=body, headers=lab.login()).status_code == 409  # registered
    assert [d["principal"] for d in lab.client.get("/api/devices?active=true").json()] == ["dev-glove"]


def test_every_device_route_needs_a_login(lab: Lab) -> None:
    spec = lab.client.get("/openapi.json").json()
    routes = [
        (method, path.replace("{rig}", "fleet").replace("{principal}", "dev-glove"))
        for path, operations in spec["paths"].items()
        if path.startswith("/api/devices")
        for method in operations
    ]
    assert len(routes) == 5
    for method, path in routes:
        assert lab.client.request(method, path, json={}).status_code == 401, (method, path)
    page = lab.client.get("/devices", follow_redirects=False)
    assert (page.status_code, page.headers["location"]) == (303, "/login")


_GARBAGE = [
    {"kind": "teleoperating", "device": "../../etc/passwd"},
    {"kind": "teleoperating", "device": "..%2f..%2fpasswd"},
    {"kind": "teleoperating", "device": ".."},
    {"kind": "teleoperating", "device": "x" * 10_240},
    {"kind": "teleoperating", "device": "glöve"},
    {"kind": "teleoperating", "device": "glove\nuser evil"},
    {"kind": "teleoperating", "device": "glove:x"},
    {"kind": "teleoperating", "device": ""},
    {"kind": "teleoperating", "device": 7},
    {"kind": "teleoperating", "device": "nope"},  # a valid identifier, but no device of the rig
    {"kind": "teleoperating", "device": "ur5e"},  # a robot, not an input device
    {"kind": "teleoperated", "device": "glove"},  # an input device, not a robot
    {"kind": "camera", "device": "glove"},
    {"kind": "teleoperating", "device": "glove", "rig": "../fleet"},
    {"kind": "teleoperating", "device": "glove", "rig": "demo"},  # not served here
    {"kind": "teleoperating", "device": "glove", "extra": "x"},
]


def test_garbage_is_422_and_touches_no_file(lab: Lab) -> None:
    before = {p.name: p.read_bytes() for p in lab.folder.iterdir() if p.is_file()}
    headers = lab.login()
    for body in _GARBAGE:
        reply = lab.client.post("/api/devices", json=body, headers=headers)
        assert reply.status_code == 422, (body, reply.text)
    # ("/api/devices/fleet/.." never reaches the server as such: the client resolves the dots.)
    for principal in ["dev-..", "dev-" + "x" * 10_240, "dev-glöve", "glove", "dev-a%20b", "station"]:
        assert lab.client.delete(f"/api/devices/fleet/{principal}", headers=headers).status_code == 422, (
            principal
        )
        assert lab.client.get(f"/api/devices/fleet/{principal}").status_code == 422, principal
    assert lab.client.get(f"/api/devices/{'r' * 10_240}/dev-glove").status_code == 422
    assert lab.client.get("/api/devices?rig=..%2f..").status_code == 422
    assert lab.client.get("/api/devices/fleet/dev-glove").status_code == 404  # well-formed, not registered
    assert {p.name: p.read_bytes() for p in lab.folder.iterdir() if p.is_file()} == before
    assert lab.client.get("/api/devices").json() == []


def test_the_password_is_in_no_log_file_or_later_reply(lab: Lab, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG)
    issued = lab.register("teleoperating", "vr_panda")
    password = str(issued["password"])
    assert len(password) >= 32
    assert _arrived(lab, "dev-vr_panda", password, [f"{ROOT}/vr_panda/a"]) == [f"{ROOT}/vr_panda/a"]
    later = [
        lab.client.get("/api/devices"),
        lab.client.get("/api/devices/fleet/dev-vr_panda"),
        lab.client.get("/api/devices/rigs"),
        lab.client.get("/api/audit"),
        lab.client.get("/openapi.json"),
        lab.client.delete("/api/devices/fleet/dev-vr_panda", headers=lab.login()),
        lab.client.get("/api/devices"),
    ]
    for reply in later:
        assert reply.status_code == 200, reply.text
        assert password not in reply.text
    assert caplog.records, "nothing was logged: the check would be empty"
    for record in caplog.records:
        assert password not in record.getMessage()
    for path in [*lab.root.rglob("*"), *lab.root.parent.glob("mosquitto.*")]:
        if path.is_file():
            assert password.encode() not in path.read_bytes(), path


def test_the_openapi_spec_describes_every_device_route(lab: Lab) -> None:
    spec = lab.client.get("/openapi.json").json()
    for path in ("/api/devices", "/api/devices/rigs", "/api/devices/{rig}/{principal}"):
        for method, operation in spec["paths"][path].items():
            ok = operation["responses"]["201" if method == "post" else "200"]
            assert "$ref" in str(ok["content"]["application/json"]["schema"]), (method, path)
    assert {"RegisteredDevice", "IssuedOut", "RevokedOut", "RegisterRequest"} <= set(
        spec["components"]["schemas"]
    )
    lab.login("vic")
    page = lab.client.get("/devices")
    assert page.status_code == 200
    assert "devices.js" in page.text


def _verifies(line: str, password: str) -> bool:
    """Whether a Mosquitto ``user:$7$iterations$salt$hash`` line accepts ``password``."""
    _, _, iterations, salt, digest = line.split(":", 1)[1].split("$")
    mine = hashlib.pbkdf2_hmac("sha512", password.encode(), base64.b64decode(salt), int(iterations), dklen=64)
    return base64.b64encode(mine).decode() == digest


def test_serve_start_puts_registered_logins_back_after_a_rotation(tmp_path: Path, fleet: RigConfig) -> None:
    root = tmp_path / "data"
    folder = root / "broker" / "fleet"
    assert telerig_main(["broker", "acl", "fleet", "--out", str(folder), "--address", "mqtt://h:1883"]) == 0
    registry = DeviceRegistry.open(root, [fleet])  # no pid file: nothing to signal
    try:
        glove = registry.register("fleet", "teleoperating", "glove", by="ada")
        assert glove.reload.status == "embedded"  # the fleet rig file embeds its broker: said so
        assert "external Mosquitto" in glove.reload.detail
        registry.register("fleet", "teleoperating", "vr_panda", by="ada")
        registry.revoke("fleet", "dev-vr_panda", by="ada")
        # `telerig broker acl` again (password rotation) writes every principal afresh ...
        shutil.rmtree(folder)
        assert (
            telerig_main(["broker", "acl", "fleet", "--out", str(folder), "--address", "mqtt://h:1883"]) == 0
        )
        rotated = {line.split(":", 1)[0]: line for line in (folder / "passwd").read_text().splitlines()}
        assert _verifies(rotated["dev-glove"], BusLogin.read(folder / "logins" / "dev-glove.json").password)
        # ... and the server's start puts the registrations back: the issued login, no revoked one.
        result = registry.sync("fleet")
        assert result is not None
        assert result.status == "embedded"
        synced = {line.split(":", 1)[0]: line for line in (folder / "passwd").read_text().splitlines()}
        assert _verifies(synced["dev-glove"], glove.password)
        assert "dev-vr_panda" not in synced
        assert {u: line for u, line in synced.items() if u != "dev-glove"} == {
            u: line for u, line in rotated.items() if u not in ("dev-glove", "dev-vr_panda")
        }
        assert not (folder / "logins" / "dev-glove.json").exists()
        assert not (folder / "logins" / "dev-vr_panda.json").exists()
        assert (folder / "logins" / "station.json").exists()
        for name in ("passwd", "acl"):
            assert (folder / name).stat().st_mode & 0o777 == 0o600
        assert registry.sync("fleet") is None  # current: no rewrite reported, no reload
    finally:
        registry.close()
