"""Safety payloads read from a real broker are validated: forged or malformed ones are counted and dropped."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import pytest

from telerig.bus.mqtt import MqttBus
from telerig.safety import SafetySupervisor
from telerig.safety.commands import HaltListener, SafetyCommandListener, halt_topic, safety_command_topic

pytestmark = pytest.mark.broker

MakeBus = Callable[..., MqttBus]
NOT_OBJECTS = [b"[]", b'"halt"', b"42", b"null", b"true", b"{not json", b"\xff\xfe", b"[" * 5000]


class _Halts:
    def __init__(self) -> None:
        self.reasons: list[str] = []
        self.event = threading.Event()

    def __call__(self, reason: str) -> None:
        self.reasons.append(reason)
        self.event.set()


def _settle(listener: HaltListener | SafetyCommandListener, count: int, timeout_s: float = 3.0) -> None:
    deadline = time.monotonic() + timeout_s
    while listener.rejected + listener.applied < count and time.monotonic() < deadline:
        time.sleep(0.01)


def _halt_listener(make_bus: MakeBus, halts: _Halts) -> tuple[HaltListener, MqttBus]:
    listener = HaltListener(
        make_bus("arm1-host"), "fleet", own={"arm1"}, rig_robots={"arm0", "arm1"}, halt=halts
    )
    sender = make_bus("sender")
    time.sleep(0.2)  # the SUBACK
    return listener, sender


def test_a_forged_halt_for_an_unknown_robot_halts_nothing(
    make_bus: MakeBus, caplog: pytest.LogCaptureFixture
) -> None:
    halts = _Halts()
    listener, sender = _halt_listener(make_bus, halts)
    sender.publish(halt_topic("fleet"), b'{"robot": "nobody"}', qos=1)
    _settle(listener, 1)
    assert listener.rejected == 1
    assert halts.reasons == []
    assert "robot 'nobody' is not in the rig; no robot halted" in caplog.text


def test_non_object_json_on_the_halt_topic_is_counted_and_dropped(
    make_bus: MakeBus, caplog: pytest.LogCaptureFixture
) -> None:
    halts = _Halts()
    listener, sender = _halt_listener(make_bus, halts)
    for payload in [*NOT_OBJECTS, b'{"robot": "arm0", "extra": 1}', b'{"robot": 7}', b"{}"]:
        sender.publish(halt_topic("fleet"), payload, qos=1)
    _settle(listener, len(NOT_OBJECTS) + 3)
    assert listener.rejected == len(NOT_OBJECTS) + 3
    assert halts.reasons == []
    assert "Traceback" not in caplog.text
    assert all(len(r.message.splitlines()) == 1 for r in caplog.records)


def test_a_halt_for_another_robot_of_the_rig_halts_this_process(make_bus: MakeBus) -> None:
    halts = _Halts()
    listener, sender = _halt_listener(make_bus, halts)
    sender.publish(halt_topic("fleet"), b'{"robot": "arm1", "code": "driver_fault"}', qos=1)  # its own
    sender.publish(halt_topic("fleet"), b'{"robot": "arm0", "code": "driver_fault", "reason": "enc"}', qos=1)
    assert halts.event.wait(3.0)
    assert halts.reasons == ["halted because robot 'arm0' faulted: enc"]
    assert listener.rejected == 0


def test_malformed_safety_commands_are_counted_and_dropped(
    make_bus: MakeBus, caplog: pytest.LogCaptureFixture
) -> None:
    listener = SafetyCommandListener(
        make_bus("station"), "fleet", SafetySupervisor("pause_affected"), rig_robots={"arm0"}
    )
    sender = make_bus("sender")
    time.sleep(0.2)
    bad = [
        *NOT_OBJECTS,
        b'{"command": "estop", "robot": 5}',  # strict: not a string
        b'{"command": "estop", "robot": "nobody"}',  # not in the rig
        b'{"command": "estop", "reason": "' + b"x" * 5000 + b'"}',  # over the size limit
    ]
    for payload in bad:
        sender.publish(safety_command_topic("fleet"), payload, qos=1)
    _settle(listener, len(bad))
    assert listener.rejected == len(bad)
    assert listener.applied == 0
    assert "robot 'nobody', not in the rig" in caplog.text
    assert "Traceback" not in caplog.text
