"""Operator calibration launched over the bus and run by the device node where the device runs: a real
UDP VR device fed by the fake headset, a real Mosquitto with the rig's ACL, the command from the web
principal, progress and result on the device's events, the profile on disk."""

from __future__ import annotations

import json
import socket
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from telerig.bus.acl import STATION, WEB, rig_access_policy
from telerig.bus.base import Message
from telerig.bus.broker import MosquittoBroker
from telerig.bus.mqtt import MqttBus
from telerig.calibrate import load_profile
from telerig.config.schema import RigConfig
from telerig.devices.udp_vr.fake import FakeVrSender
from telerig.runtime.device_node import DeviceNode
from telerig.runtime.session import SessionState, SessionStatus

pytestmark = pytest.mark.broker

COMMAND = "telerig/v1/vr/quest/command"
EVENTS = "telerig/v1/vr/quest/events"


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_for(condition: Callable[[], object], timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.02)
    return bool(condition())


class Events:
    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.docs: list[dict[str, object]] = []

    def __call__(self, message: Message) -> None:
        with self.lock:
            self.docs.append(json.loads(message.payload))

    def codes(self) -> list[str]:
        with self.lock:
            return [str(d["code"]) for d in self.docs]

    def last(self, code: str) -> dict[str, object]:
        with self.lock:
            return [d for d in self.docs if d["code"] == code][-1]


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[tuple[DeviceNode, dict[str, MqttBus], Events, int, list[str]]]:
    port = _free_udp_port()
    config = RigConfig.model_validate(
        {
            "name": "vr",
            "devices": [
                {"id": "quest", "type": "udp_vr", "host": "127.0.0.1", "port": port},
                {"id": "other", "type": "udp_vr", "host": "127.0.0.1", "port": _free_udp_port()},
            ],
            "robots": [],
            "bindings": [],
        }
    )
    broker = MosquittoBroker(access=rig_access_policy(config), owner=STATION).start()
    buses = {p: MqttBus(broker.url_for(p), client_id=f"t-{p}").connect() for p in (WEB, STATION, "dev-other")}
    device_bus = MqttBus(broker.url_for("dev-quest"), client_id="vr-dev-quest").connect()
    events = Events()
    buses[WEB].subscribe(EVENTS, events, qos=1)
    samples: list[str] = []
    buses[WEB].subscribe(
        "telerig/v1/vr/quest/+",
        lambda m: samples.append(m.topic) if "_" in m.topic.rsplit("/", 1)[1] else None,
    )
    node = DeviceNode("vr", config.devices[0].build(), device_bus, profile_root=tmp_path)
    _until_subscribed(node, buses[WEB], events)
    try:
        yield node, buses, events, port, samples
    finally:
        node.stop()
        node.calibration.join(10.0)
        for bus in (*buses.values(), device_bus):
            bus.close()
        broker.stop()


def _until_subscribed(node: DeviceNode, web: MqttBus, events: Events) -> None:
    """MQTT subscriptions are acknowledged asynchronously: send refused probes until the node hears
    its command topic and the test hears the node's events, so no test's first command is lost (the
    full suite once lost 2 of 7), then start every count from zero."""
    deadline = time.monotonic() + 10.0
    while not (node.calibration.rejected and events.codes()) and time.monotonic() < deadline:
        web.publish(COMMAND, b'{"calibrate": {"operator": "../probe"}}', qos=1)
        time.sleep(0.1)
    assert node.calibration.rejected, "the device node never heard its command topic"
    time.sleep(0.3)  # probes still in flight
    node.calibration.rejected = 0
    with events.lock:
        events.docs.clear()


def _calibrate(bus: MqttBus, **request: object) -> None:
    bus.publish(COMMAND, json.dumps({"calibrate": request}).encode(), qos=1)


def test_a_web_operator_calibrates_between_episodes_and_the_profile_is_saved(
    rig: tuple[DeviceNode, dict[str, MqttBus], Events, int, list[str]], tmp_path: Path
) -> None:
    node, buses, events, port, samples = rig
    with FakeVrSender(port, rate_hz=90.0, cycle_s=1e9, hands=False) as headset:  # held still
        headset.start()
        _calibrate(buses[WEB], operator="ana", duration_s=1.5, settle_s=0.5)
        assert wait_for(
            lambda: "calibration_done" in events.codes() or "calibration_failed" in events.codes(), 15.0
        )
    codes = events.codes()
    assert codes[0] == "command_reply"
    assert "calibrating operator ana with quest" in str(events.last("command_reply")["reason"])
    assert codes.count("calibration_progress") >= 2  # about one a second over 2 s
    done = events.last("calibration_done")
    assert "arm length" in str(done["reason"])
    assert str(tmp_path / "operators" / "ana.json") in str(done["reason"])
    assert load_profile("ana", data_root=tmp_path).operator == "ana"
    assert samples == []  # the calibration's samples never went on the bus (no robot follows them)
    assert node.published == 0


def test_a_moving_operator_is_told_why_and_nothing_is_saved(
    rig: tuple[DeviceNode, dict[str, MqttBus], Events, int, list[str]], tmp_path: Path
) -> None:
    _, buses, events, port, _ = rig
    with FakeVrSender(port, rate_hz=90.0) as headset:  # circling controllers, hands opening and closing
        headset.start()
        _calibrate(buses[WEB], operator="bo", duration_s=1.5, settle_s=0.0)
        assert wait_for(lambda: "calibration_failed" in events.codes(), 15.0), events.docs
    failed = events.last("calibration_failed")
    assert "moved" in str(failed["reason"]) or "turned" in str(failed["reason"])
    assert failed["severity"] == "warning"
    assert "hold both hands" in str(failed["suggested_action"])
    assert not (tmp_path / "operators" / "bo.json").exists()


def test_during_an_episode_only_a_paused_device_calibrates(
    rig: tuple[DeviceNode, dict[str, MqttBus], Events, int, list[str]], tmp_path: Path
) -> None:
    node, buses, events, port, _ = rig
    with FakeVrSender(port, rate_hz=90.0, cycle_s=1e9, hands=False) as headset:
        headset.start()
        node.start()  # an episode streams the device to its robots
        _calibrate(buses[WEB], operator="cy", duration_s=1.0, settle_s=0.0)
        assert wait_for(lambda: "command_reply" in events.codes(), 5.0)
        assert "pause the device first" in str(events.last("command_reply")["reason"])
        assert not node.calibration.busy
        status = SessionStatus(
            rig="vr", state=SessionState.RECORDING, session_id="s", paused_devices=("quest",)
        )
        buses[STATION].publish("telerig/v1/vr/coordinator/session", status.model_dump_json().encode(), qos=1)
        assert wait_for(lambda: node.calibration._paused, 5.0)
        _calibrate(buses[WEB], operator="cy", duration_s=1.0, settle_s=0.2)
        assert wait_for(lambda: "calibration_done" in events.codes(), 15.0), events.codes()
    assert load_profile("cy", data_root=tmp_path).operator == "cy"
    assert node.published > 50  # the episode's stream went on while it calibrated


def test_garbage_commands_are_refused_in_one_line_and_another_device_cannot_send_one(
    rig: tuple[DeviceNode, dict[str, MqttBus], Events, int, list[str]],
) -> None:
    node, buses, events, _, _ = rig
    junk = [
        b"\xff\xfe",
        b"[1, 2]",
        b'{"calibrate": {"operator": "../etc/passwd"}}',
        b'{"calibrate": {"operator": "ana", "duration_s": 1e9}}',
        b'{"calibrate": {"operator": "ana", "duration_s": "30"}}',
        b'{"calibrate": {"operator": "ana"}, "also": 1}',
        b'{"calibrate": "' + b"x" * 5000 + b'"}',
    ]
    for payload in junk:
        buses[WEB].publish(COMMAND, payload, qos=1)
    assert wait_for(lambda: node.calibration.rejected == len(junk), 5.0), node.calibration.rejected
    assert wait_for(lambda: len(events.codes()) == len(junk), 5.0)
    replies = [str(d["reason"]) for d in events.docs if d["code"] == "command_reply"]
    assert len(replies) == len(junk)
    assert all(r.startswith("calibrate refused: ") and "\n" not in r for r in replies)
    # Another device's login cannot command this one: the broker drops it.
    _calibrate(buses["dev-other"], operator="eve", duration_s=1.0)
    time.sleep(0.5)
    assert not node.calibration.busy
    assert len(events.codes()) == len(junk)


def test_an_episode_starting_cancels_a_calibration_that_runs_the_device_itself(
    rig: tuple[DeviceNode, dict[str, MqttBus], Events, int, list[str]], tmp_path: Path
) -> None:
    node, buses, events, port, _ = rig
    with FakeVrSender(port, rate_hz=90.0, cycle_s=1e9, hands=False) as headset:
        headset.start()
        _calibrate(buses[WEB], operator="dee", duration_s=60.0, settle_s=0.0)
        assert wait_for(lambda: "calibration_progress" in events.codes(), 5.0)
        node.start()  # the episode wins: the calibration stops the device, then the node starts it
        assert wait_for(lambda: "calibration_failed" in events.codes(), 5.0)
        assert wait_for(lambda: node.published > 20, 5.0)
    assert "an episode started" in str(events.last("calibration_failed")["reason"])
    assert not (tmp_path / "operators" / "dee.json").exists()
