"""The bus has an owner: logins, a per-rig ACL and a size limit, enforced by a real Mosquitto."""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest

from telerig.bus.acl import (
    CLI,
    STATION,
    AccessPolicy,
    Principal,
    new_password,
    rig_access_policy,
    robot_process_principal,
)
from telerig.bus.base import Message
from telerig.bus.broker import DEFAULT_MESSAGE_SIZE_LIMIT, MosquittoBroker
from telerig.bus.mqtt import MqttBus
from telerig.config import load_rig
from telerig.config.schema import RigConfig
from telerig.errors import BusError

pytestmark = pytest.mark.broker


class _Collector:
    """Every message of a subscription, with a wait for the next one."""

    def __init__(self) -> None:
        self.messages: list[Message] = []
        self._cond = threading.Condition()

    def __call__(self, message: Message) -> None:
        with self._cond:
            self.messages.append(message)
            self._cond.notify_all()

    def topics(self) -> list[str]:
        with self._cond:
            return [m.topic for m in self.messages]

    def wait_for(self, topic: str, timeout_s: float = 3.0) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: topic in [m.topic for m in self.messages], timeout_s)


@pytest.fixture(scope="module")
def fleet() -> RigConfig:
    return load_rig("fleet")


@pytest.fixture
def fleet_broker(fleet: RigConfig) -> Iterator[MosquittoBroker]:
    with MosquittoBroker(access=rig_access_policy(fleet), owner=STATION) as broker:
        yield broker


def _client(broker: MosquittoBroker, principal: str, buses: list[MqttBus]) -> MqttBus:
    bus = MqttBus(broker.url_for(principal), client_id=f"test-{principal}").connect()
    buses.append(bus)
    return bus


def _published_through(
    broker: MosquittoBroker, publisher: str, topics: list[str], *, marker: str
) -> list[str]:
    """Publish on each topic as ``publisher`` (QoS 1), then a marker; return the topics that arrived."""
    buses: list[MqttBus] = []
    try:
        seen = _Collector()
        watcher = _client(broker, STATION, buses)
        watcher.subscribe("telerig/v1/#", seen, qos=1)
        time.sleep(0.2)  # the SUBACK before the first publish
        sender = _client(broker, publisher, buses)
        for topic in topics:
            sender.publish(topic, b'{"command": "estop"}', qos=1)
        watcher.publish(marker, b"end", qos=1)
        assert seen.wait_for(marker), "the marker never arrived"
        time.sleep(0.1)
        return [t for t in seen.topics() if t != marker]
    finally:
        for bus in buses:
            bus.close()


def test_an_anonymous_client_is_refused(broker: MosquittoBroker) -> None:
    anonymous = MqttBus(broker.address, client_id="anonymous")
    with pytest.raises(BusError, match=r"refused client 'anonymous'"):
        anonymous.connect()
    anonymous.close()


def test_a_wrong_password_is_refused(fleet_broker: MosquittoBroker) -> None:
    bus = MqttBus(fleet_broker.address, client_id="guess", username=CLI, password="guess")
    with pytest.raises(BusError, match=r"refused client 'guess'.*user and password"):
        bus.connect()
    bus.close()


def test_a_device_publishes_its_own_streams_and_nothing_else(fleet_broker: MosquittoBroker) -> None:
    root = "telerig/v1/fleet"
    own = f"{root}/vr_ur5e/right_controller"
    forged = [
        f"{root}/panda/joint_command_sent",  # another robot's command
        f"{root}/ur5e/joint_command_sent",  # even the robot it drives
        f"{root}/safety/command",
        f"{root}/safety/halt",
        f"{root}/coordinator/command",
        f"{root}/coordinator/session",
        f"{root}/vr_panda/right_controller",  # another device
        "elsewhere/topic",
    ]
    arrived = _published_through(fleet_broker, "dev-vr_ur5e", [*forged, own], marker=f"{root}/m/end")
    assert arrived == [own]


def test_operators_publish_commands_but_not_robot_streams(fleet_broker: MosquittoBroker) -> None:
    root = "telerig/v1/fleet"
    allowed = [
        f"{root}/safety/command",
        f"{root}/coordinator/command",
        f"{root}/ur5e/motion_scale_command",
        f"{root}/vr_ur5e/command",  # a device's operator command (a WebXR takeover's confirmation)
    ]
    forged = [f"{root}/safety/halt", f"{root}/ur5e/joint_command_sent", f"{root}/coordinator/session"]
    arrived = _published_through(fleet_broker, CLI, [*forged, *allowed], marker=f"{root}/m/end")
    assert arrived == allowed


def test_a_robot_process_publishes_its_robot_devices_and_halts_only(fleet_broker: MosquittoBroker) -> None:
    root = "telerig/v1/fleet"
    allowed = [
        f"{root}/ur5e/joint_command_sent",
        f"{root}/vr_ur5e/right_controller",  # the device it hosts
        f"{root}/safety-ur5e/alerts",
        f"{root}/safety/halt",
    ]
    forged = [f"{root}/panda/joint_state", f"{root}/safety/command", f"{root}/coordinator/command"]
    arrived = _published_through(
        fleet_broker, robot_process_principal("ur5e"), [*forged, *allowed], marker=f"{root}/m/end"
    )
    assert arrived == allowed


def test_the_access_files_are_private(fleet_broker: MosquittoBroker) -> None:
    folder = fleet_broker.log_path
    assert folder is not None
    for name in ("passwd", "acl"):
        assert (folder.parent / name).stat().st_mode & 0o777 == 0o600
    assert folder.parent.stat().st_mode & 0o777 == 0o700
    assert "$7$" in (folder.parent / "passwd").read_text()  # hashed, never the password itself


def test_a_generated_password_is_32_letters_and_digits_and_never_an_option() -> None:
    # token_urlsafe drew "-" first in 1 of 64 passwords, and ``--password -x...`` is a missing
    # argument to argparse: CI lost a run to it.
    passwords = [new_password() for _ in range(4096)]
    assert all(re.fullmatch(r"[A-Za-z0-9]{32}", p) for p in passwords)
    assert len(set(passwords)) == len(passwords)
    assert {p[0] for p in passwords} >= set("abcXYZ019")  # every class of first character is drawn
    policy = AccessPolicy.generate([Principal(n, ("#",), ("#",)) for n in "abc"])
    assert all(re.fullmatch(r"[A-Za-z0-9]{32}", policy.password(n)) for n in "abc")


def test_an_oversized_message_is_dropped_by_the_broker() -> None:
    access = AccessPolicy.generate([Principal("a", ("#",), ("#",))])
    with MosquittoBroker(access=access, message_size_limit=4096) as broker:
        seen = _Collector()
        with (
            MqttBus(broker.url, client_id="watch") as watcher,
            MqttBus(broker.url, client_id="send") as sender,
        ):
            watcher.subscribe("t/#", seen, qos=1)
            time.sleep(0.2)
            sender.publish("t/big", b"x" * 4097, qos=1)
            sender.publish("t/fits", b"x" * 4096, qos=1)
            assert seen.wait_for("t/fits")
            time.sleep(0.1)
            assert seen.topics() == ["t/fits"]


def test_the_default_limit_passes_the_largest_preview_and_drops_larger(broker: MosquittoBroker) -> None:
    from telerig.cameras.preview import encode_jpeg

    # The worst case for JPEG (uniform noise) at the largest preview the rig schema allows.
    noise = np.random.default_rng(0).integers(0, 256, (1080, 1920, 3), dtype=np.uint8)
    preview = encode_jpeg(noise, width=1920, height=1080)
    assert len(preview) < DEFAULT_MESSAGE_SIZE_LIMIT
    seen = _Collector()
    with (
        MqttBus(broker.url, client_id="watch") as watcher,
        MqttBus(broker.url, client_id="send") as sender,
        MqttBus(broker.url, client_id="flood") as flood,
    ):
        watcher.subscribe("t/#", seen, qos=1)
        time.sleep(0.2)
        sender.publish("t/big", bytes(DEFAULT_MESSAGE_SIZE_LIMIT + 1), qos=1)  # read, then dropped
        flood.publish("t/flood", bytes(10_000_000))  # over the packet limit: its sender is cut off
        sender.publish("t/preview", preview, qos=1)
        assert seen.wait_for("t/preview", timeout_s=10.0)
        time.sleep(0.2)
        assert seen.topics() == ["t/preview"]
        assert sender.stats.reconnects == 0


def test_unknown_principal_names_the_valid_ones(fleet_broker: MosquittoBroker) -> None:
    from telerig.errors import ConfigError

    with pytest.raises(ConfigError, match=r"no bus principal 'nobody'. Valid: .*cli"):
        fleet_broker.url_for("nobody")
