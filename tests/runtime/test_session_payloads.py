"""Session payloads from a real broker are strict and size-limited: a malformed one is counted and dropped."""

from __future__ import annotations

import time
from collections.abc import Callable

import pytest

from telerig.bus.mqtt import MqttBus
from telerig.runtime.session import COMMAND, COORDINATOR, Coordinator

pytestmark = pytest.mark.broker

MakeBus = Callable[..., MqttBus]


def test_malformed_episode_commands_are_counted_and_dropped(
    make_bus: MakeBus, caplog: pytest.LogCaptureFixture
) -> None:
    topic = f"telerig/v1/demo/{COORDINATOR}/{COMMAND}"
    bad = [
        b"[]",
        b'"stop"',
        b"null",
        b"[" * 5000,
        b'{"command": "start", "lead_s": "2"}',  # strict: a string is not a number
        b'{"command": "start", "task": 7}',
        b'{"command": "start", "reason": "' + b"x" * 5000 + b'"}',  # over the size limit
    ]
    with Coordinator(make_bus("coordinator"), "demo", lead_s=0.0) as coordinator:
        sender = make_bus("sender")
        time.sleep(0.2)
        for payload in bad:
            sender.publish(topic, payload, qos=1)
        deadline = time.monotonic() + 3.0
        while coordinator.stats.malformed < len(bad) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert coordinator.stats.malformed == len(bad)
        assert coordinator.stats.accepted == 0
    assert "Traceback" not in caplog.text
    assert "lead_s: Input should be a valid number" in caplog.text
