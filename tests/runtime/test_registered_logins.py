"""Devices registered in the control center log in on the embedded broker of ``telerig run``, as a
real Mosquitto enforces it: their issued password works, they publish their own streams and nothing
on another robot's command topic, a revoke cuts them off within the watchdog's period, a device the
station runs itself keeps the station's login, and garbage in the broker folder never crashes the
station nor lets anyone in without a password."""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import paho.mqtt.client as paho
import pytest
import yaml

from telerig.bus.acl import rig_access_policy
from telerig.bus.base import Message
from telerig.bus.mqtt import MqttBus
from telerig.bus.registered import (
    MAX_FILE_BYTES,
    REGISTERED_FILE,
    RegisteredLogins,
    read_registered_logins,
)
from telerig.config.load import load_rig, parse_rig, shipped_rig_path
from telerig.config.schema import RigConfig
from telerig.errors import BusError
from telerig.runtime.broker_supervisor import BrokerSupervisor, station_logins
from telerig.runtime.rig import RigRuntime
from telerig.server.devices import DeviceRegistry

pytestmark = pytest.mark.broker

ROOT = "telerig/v1/fleet"


@pytest.fixture(scope="module")
def rig() -> RigConfig:
    """The fleet rig with a second station that runs the glove and the hand: station0's embedded
    broker serves them, but station0 runs neither (so their registered logins apply there)."""
    data = yaml.safe_load(shipped_rig_path("fleet").read_text())
    data["stations"] = [{"id": "station0"}, {"id": "station1"}]
    for section, node in (("devices", "glove"), ("robots", "hand")):
        next(n for n in data[section] if n["id"] == node)["station"] = "station1"
    return parse_rig(data)


@dataclass
class Station:
    registry: DeviceRegistry
    supervisor: BrokerSupervisor
    folder: Path

    @property
    def port(self) -> int:
        broker = self.supervisor.embedded
        assert broker is not None
        return broker.port

    @property
    def address(self) -> str:
        return f"mqtt://127.0.0.1:{self.port}"

    def start(self) -> None:
        self.supervisor.start()


@pytest.fixture
def station(tmp_path: Path, rig: RigConfig) -> Iterator[Station]:
    root = tmp_path / "data"
    registry = DeviceRegistry.open(root, [rig])
    folder = root / "broker" / rig.name
    supervisor = BrokerSupervisor(
        rig.name,
        rig.broker,
        access=rig_access_policy(rig),
        registered_folder=folder,
        reserved=station_logins(rig, "station0"),
    )
    try:
        yield Station(registry, supervisor, folder)
    finally:
        supervisor.close()
        registry.close()


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


def _arrived(st: Station, username: str, password: str, topics: list[str], root: str = ROOT) -> list[str]:
    """Publish each topic with this login (QoS 1), then a marker as the station; the topics the
    station's subscriber (which reads everything) received."""
    seen = _Seen()
    marker = f"{root}/m/end"
    assert st.supervisor.url is not None
    with MqttBus(st.supervisor.url, client_id="watch") as watcher:
        watcher.subscribe("#", seen, qos=1)
        time.sleep(0.2)
        with MqttBus(st.address, client_id=f"as-{username}", username=username, password=password) as sender:
            for topic in topics:
                sender.publish(topic, b'{"command": "estop"}', qos=1)
            time.sleep(0.1)
        watcher.publish(marker, b"end", qos=1)
        assert seen.wait_for(marker), "the marker never arrived"
    return [t for t in seen.topics if t != marker]


def _refused(st: Station, username: str, password: str) -> bool:
    bus = MqttBus(
        st.address, client_id=f"try-{username}", username=username, password=password, connect_timeout_s=2.0
    )
    try:
        bus.connect()
    except BusError as exc:
        return "refused" in str(exc)
    finally:
        bus.close()
    return False


def _eventually(check: object, timeout_s: float = 3.0) -> bool:
    assert callable(check)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if check():
            return True
        time.sleep(0.1)
    return False


_FORGED = [
    f"{ROOT}/ur5e/joint_command_requested",  # another robot's commands
    f"{ROOT}/ur5e/joint_command_sent",
    f"{ROOT}/ur5e/motion_scale_command",
    f"{ROOT}/hand/joint_command_sent",  # even the robot it drives
    f"{ROOT}/vr_ur5e/command",  # another device's command topic
    f"{ROOT}/vr_ur5e/right_controller",
    f"{ROOT}/safety/command",
    f"{ROOT}/coordinator/command",
    "elsewhere/topic",
]


def test_a_registered_device_logs_in_on_the_embedded_broker_and_a_revoke_cuts_it_off(
    station: Station, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING)
    glove = station.registry.register("fleet", "teleoperating", "glove", by="ada")
    assert glove.reload.status == "embedded"
    listing = station.folder / REGISTERED_FILE
    assert listing.stat().st_mode & 0o777 == 0o600
    assert glove.password.encode() not in listing.read_bytes()  # its hash only
    # vr_ur5e runs in station0 itself: its registration is left out there, with one warning.
    vr = station.registry.register("fleet", "teleoperating", "vr_ur5e", by="ada")
    station.start()
    warnings = [r.getMessage() for r in caplog.records if "dev-vr_ur5e" in r.getMessage()]
    assert len(warnings) == 1, warnings
    assert "left out" in warnings[0]
    assert _refused(station, "dev-vr_ur5e", vr.password)
    own_node = station.supervisor.node_url(str(station.supervisor.url), "dev-vr_ur5e")
    with MqttBus(own_node, client_id="dev-vr_ur5e"):  # the station's own node keeps its login
        pass

    own = [f"{ROOT}/glove/hand_pose", f"{ROOT}/glove/health"]
    assert _arrived(station, "dev-glove", glove.password, [*_FORGED, *own]) == own
    assert _refused(station, "dev-glove", "not-the-password")

    dropped = threading.Event()
    client = paho.Client(paho.CallbackAPIVersion.VERSION2, client_id="glove")
    client.username_pw_set("dev-glove", glove.password)
    client.reconnect_delay_set(5, 5)
    client.on_disconnect = lambda *_: dropped.set()
    client.connect("127.0.0.1", station.port)
    client.loop_start()
    try:
        assert _eventually(client.is_connected)
        station.registry.revoke("fleet", "dev-glove", by="ada")
        assert dropped.wait(3.0), "the embedded broker kept the revoked device connected"
    finally:
        client.loop_stop()
        client.disconnect()
    assert _refused(station, "dev-glove", glove.password)

    # Registered again while the station runs: the new password works, the old stays refused.
    again = station.registry.register("fleet", "teleoperating", "glove", by="ada")
    assert _eventually(lambda: not _refused(station, "dev-glove", again.password))
    assert _refused(station, "dev-glove", glove.password)
    # A registered robot the station does not run: its own streams only.
    hand = station.registry.register("fleet", "teleoperated", "hand", by="ada")
    assert _eventually(lambda: not _refused(station, "robot-hand", hand.password))
    mine = [f"{ROOT}/hand/joint_state", f"{ROOT}/hand/joint_command_sent"]
    assert (
        _arrived(station, "robot-hand", hand.password, [*_FORGED[:3], f"{ROOT}/safety/command", *mine])
        == mine
    )


_HASH = "$7$101$c2FsdHNhbHRzYWx0$" + "A" * 86 + "=="


def _logins(logins: object) -> bytes:
    return json.dumps({"logins": logins}).encode()


@pytest.mark.parametrize(
    ("registered", "said"),
    [
        (b"{not json", "not JSON"),
        (b'["dev-glove"]', '"logins"'),
        (_logins(["dev-glove"]), '"logins"'),
        (_logins({"dev-glove": 7}), '"logins"'),
        (_logins({"dev-glove": None}), '"logins"'),
        (b"\xff\xfe garbage", "UTF-8"),
        (_logins({"dev-glove": _HASH}) + b" " * MAX_FILE_BYTES, "over"),
        (_logins({"dev-glove": ""}), "no Mosquitto $7$ hash"),
        (_logins({"dev-glove": "plaintext-password"}), "no Mosquitto $7$ hash"),
        (_logins({"dev-glove": "$7$101$x$y:z"}), "no Mosquitto $7$ hash"),
        (_logins({"dev-glove": _HASH + "\n"}), "no Mosquitto $7$ hash"),
        (_logins({"dev-glove": _HASH + "\nuser evil\ntopic write #"}), "no Mosquitto $7$ hash"),
        (_logins({"dev-glove": "$6$" + _HASH[3:]}), "no Mosquitto $7$ hash"),
        (_logins({"station": _HASH, "root": _HASH, "../x": _HASH, "x" * 10_000: _HASH}), "left out"),
    ],
)
def test_garbage_in_the_folder_is_one_warning_and_no_login(
    tmp_path: Path, rig: RigConfig, registered: bytes, said: str
) -> None:
    (tmp_path / REGISTERED_FILE).write_bytes(registered)
    reserved = station_logins(rig, "station0")
    logins = read_registered_logins(tmp_path, rig_access_policy(rig).principals, reserved)
    assert logins.hashes == {}
    assert logins.warnings
    assert any(said in w for w in logins.warnings), logins.warnings
    assert all("\n" not in w and len(w) < 400 for w in logins.warnings)


def test_a_well_formed_file_gives_its_logins(tmp_path: Path, rig: RigConfig) -> None:
    (tmp_path / REGISTERED_FILE).write_bytes(_logins({"dev-glove": _HASH, "robot-hand": _HASH}))
    logins = read_registered_logins(
        tmp_path, rig_access_policy(rig).principals, station_logins(rig, "station0")
    )
    assert logins == RegisteredLogins({"dev-glove": _HASH, "robot-hand": _HASH}, ())


def test_garbage_written_while_the_station_runs_drops_the_logins_and_keeps_the_station(
    station: Station, caplog: pytest.LogCaptureFixture
) -> None:
    glove = station.registry.register("fleet", "teleoperating", "glove", by="ada")
    written = (station.folder / REGISTERED_FILE).read_bytes()
    (station.folder / REGISTERED_FILE).write_bytes(written[: len(written) // 2])  # a torn write
    station.start()  # garbage at start: no registered login, no crash
    assert _refused(station, "dev-glove", glove.password)
    (station.folder / REGISTERED_FILE).write_bytes(written)
    assert _eventually(lambda: not _refused(station, "dev-glove", glove.password))
    caplog.set_level(logging.WARNING)
    (station.folder / REGISTERED_FILE).write_bytes(b"\0" * (MAX_FILE_BYTES + 1))
    assert _eventually(lambda: _refused(station, "dev-glove", glove.password))
    assert any("over" in r.getMessage() for r in caplog.records)
    broker = station.supervisor.embedded
    assert broker is not None
    assert broker.running
    assert station.supervisor.url is not None
    with MqttBus(station.supervisor.url, client_id="still-the-station"):
        pass


def test_a_node_of_the_station_takes_its_login_back_from_a_registration(
    tmp_path: Path, rig: RigConfig, caplog: pytest.LogCaptureFixture
) -> None:
    # A supervisor told of no reserved logins (as if station_logins missed one): the glove's
    # registration is added at start, and the station's own glove node, when it logs in, takes the
    # login back (a warning), so the station is never locked out by a registration.
    root = tmp_path / "data"
    registry = DeviceRegistry.open(root, [rig])
    supervisor = BrokerSupervisor(
        rig.name, rig.broker, access=rig_access_policy(rig), registered_folder=root / "broker" / rig.name
    )
    try:
        glove = registry.register("fleet", "teleoperating", "glove", by="ada")
        st = Station(registry, supervisor, root / "broker" / rig.name)
        st.start()
        assert not _refused(st, "dev-glove", glove.password)
        caplog.set_level(logging.WARNING)
        with MqttBus(supervisor.node_url(str(supervisor.url), "dev-glove"), client_id="dev-glove"):
            pass
        assert _refused(st, "dev-glove", glove.password)
        assert any("dev-glove" in r.getMessage() and "left out" in r.getMessage() for r in caplog.records)
        registry.revoke("fleet", "dev-glove", by="ada")
        registry.register("fleet", "teleoperating", "glove", by="ada")  # the watchdog keeps it out
        time.sleep(0.6)
        with MqttBus(supervisor.node_url(str(supervisor.url), "dev-glove"), client_id="dev-glove-2"):
            pass
    finally:
        supervisor.close()
        registry.close()


@pytest.mark.sim
@pytest.mark.slow
def test_telerig_run_adds_the_registered_logins_of_its_data_root(tmp_path: Path) -> None:
    # The demo rig with a second input device on a second station: station0's `telerig run` adds
    # vr1's registration (no node of station0 uses it) and leaves out vr0's (its own node's).
    # vr0's node in station0's own process, logged in as itself (not as its robot's process).
    data = load_rig("demo").with_isolation("threads").model_dump(mode="json")
    data["cameras"] = []
    data["stations"] = [{"id": "station0"}, {"id": "station1"}]
    vr1 = next(d for d in data["devices"] if d["id"] == "vr0") | {"id": "vr1", "station": "station1"}
    data["devices"].append(vr1)
    rig = parse_rig(data)
    registry = DeviceRegistry.open(tmp_path, [rig])
    try:
        mine = registry.register("demo", "teleoperating", "vr1", by="ada")
        theirs = registry.register("demo", "teleoperating", "vr0", by="ada")
        with RigRuntime(rig, data_root=tmp_path) as runtime:
            broker = runtime.broker.embedded
            assert broker is not None
            assert set(broker.registered) == {"dev-vr1"}
            st = Station(registry, runtime.broker, tmp_path / "broker" / "demo")
            topic = "telerig/v1/demo/vr1/pose"
            # (topics the running station publishes nothing on: its own traffic is filtered out)
            forged = ["telerig/v1/demo/arm0/forged_command", "telerig/v1/demo/vr0/forged"]
            arrived = _arrived(st, "dev-vr1", mine.password, [*forged, topic], root="telerig/v1/demo")
            assert [t for t in arrived if t in (*forged, topic)] == [topic]
            assert _refused(st, "dev-vr0", theirs.password)
            assert broker.log_path is not None
            assert "u'dev-vr0'" in broker.log_path.read_text()  # the station's own vr0 node logged in
    finally:
        registry.close()
