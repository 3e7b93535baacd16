"""Text and voice commands through the grammar reach the bus (real Mosquitto), via ``telerig say``."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable

import pytest

from telerig.bus.base import Message
from telerig.bus.mqtt import MqttBus
from telerig.cli.main import main
from telerig.runtime.session import EpisodeCommand
from telerig.safety.commands import SafetyCommand
from telerig.voice.feedback import synthesize
from telerig.voice.node import connect_dispatcher, listen
from telerig.voice.recognizer import Recognizer

R = "telerig/v1/demo"


class _Seen:
    def __init__(self) -> None:
        self.messages: list[tuple[str, bytes]] = []
        self._lock = threading.Lock()

    def __call__(self, message: Message) -> None:
        with self._lock:
            self.messages.append((message.topic, message.payload))

    def on(self, topic: str, timeout_s: float = 5.0) -> list[bytes]:
        deadline = time.monotonic() + timeout_s
        while True:
            with self._lock:
                got = [p for t, p in self.messages if t == topic]
            if got or time.monotonic() > deadline:
                return got
            time.sleep(0.02)


@pytest.fixture
def rig(make_bus: Callable[..., MqttBus]) -> tuple[MqttBus, _Seen]:
    """A robot 'arm' that has the whole-body mode and fixtures (retained states), and a listener."""
    robot = make_bus("arm")
    robot.publish(f"{R}/arm/wbc_mode", b'{"mode": "ee", "gripper": 0.0}', qos=1, retain=True)
    robot.publish(
        f"{R}/arm/fixture", b'{"name": "free", "kind": "free", "options": ["free"]}', qos=1, retain=True
    )
    seen = _Seen()
    watcher = make_bus("watcher")
    watcher.subscribe(f"{R}/#", seen, qos=1)
    time.sleep(0.2)
    return robot, seen


def _say(url: str, *phrases: str) -> int:
    return main(["say", *phrases, "--rig", "demo", "--broker", url])


def test_say_mode_and_constraint_reach_the_robots_aid_topics(broker, rig, capsys) -> None:  # type: ignore[no-untyped-def]
    _, seen = rig
    assert _say(broker.url, "Navigation!", "keep orientation") == 0
    assert seen.on(f"{R}/arm/wbc_mode_command") == [b"whole_body"]
    assert seen.on(f"{R}/arm/fixture_command") == [b"kind:orientation"]
    feedback = [json.loads(p) for p in seen.on(f"{R}/voice/feedback")]
    assert [f["status"] for f in feedback][:1] == ["done"]
    assert "done: navigation mode" in capsys.readouterr().out


def test_episode_command_is_a_valid_coordinator_command(broker, rig) -> None:  # type: ignore[no-untyped-def]
    _, seen = rig
    assert _say(broker.url, "mark success") == 0
    (payload,) = seen.on(f"{R}/coordinator/command")
    command = EpisodeCommand.model_validate_json(payload)
    assert (command.command, command.outcome, command.source) == ("mark", "success", "cli")


def test_critical_command_needs_the_confirmation(broker, rig) -> None:  # type: ignore[no-untyped-def]
    _, seen = rig
    assert _say(broker.url, "release emergency stop") == 0
    assert seen.on(f"{R}/safety/command", timeout_s=1.0) == []
    assert _say(broker.url, "release emergency stop", "navigation", "robot please execute") == 1
    assert seen.on(f"{R}/safety/command", timeout_s=1.0) == []  # another command in between drops it
    assert _say(broker.url, "reset the robot", "robot please execute") == 0
    (payload,) = seen.on(f"{R}/safety/command")
    assert SafetyCommand.model_validate_json(payload).command == "reset"


@pytest.mark.parametrize("text", ["stop", "open the pod bay doors", "x" * 5000, "\x00\xff garbage"])
def test_garbage_text_is_rejected_in_one_line_and_sent_nowhere(broker, rig, capsys, text: str) -> None:  # type: ignore[no-untyped-def]
    _, seen = rig
    assert _say(broker.url, text) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("rejected: ")
    assert "\n" not in err
    (payload,) = seen.on(f"{R}/voice/feedback")
    assert json.loads(payload)["status"] == "rejected"
    assert not [t for t, _ in seen.messages if t.endswith("command")]


def test_speech_reaches_the_bus_and_bad_audio_is_counted(broker, rig, make_bus) -> None:  # type: ignore[no-untyped-def]
    _, seen = rig
    dispatcher = connect_dispatcher(make_bus("voice"), "demo", source="voice")
    replies = listen(dispatcher, Recognizer(), [synthesize("manipulation"), b"RIFFnot a wav", b"\x00" * 10])
    assert [r.status for r in replies] == ["done", "rejected", "rejected"]
    assert seen.on(f"{R}/arm/wbc_mode_command") == [b"ee"]
    assert dispatcher.stats.malformed == 2
    assert dispatcher.stats.sent["mode"] == 1
