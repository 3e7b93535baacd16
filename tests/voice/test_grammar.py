"""The command grammar on text: phrasings, rejections, and that its payloads are what the bus accepts."""

from __future__ import annotations

import pytest

from telerig.runtime.session import EpisodeCommand
from telerig.safety.commands import SafetyCommand
from telerig.voice.grammar import (
    COMMANDS,
    CONFIRMATION,
    MAX_TEXT_CHARS,
    SafetyAction,
    SessionAction,
    parse,
)


def test_every_phrasing_parses_to_its_command() -> None:
    for command in COMMANDS:
        assert len(command.phrases) >= 1
        for phrase in command.phrases:
            assert parse(phrase.upper() + "!").command is command


def test_several_phrasings_per_command_except_the_confirmation() -> None:
    assert all(len(c.phrases) >= 2 for c in COMMANDS if c.name != "execute")


def test_only_motion_commands_are_critical_and_confirmation_is_three_distinct_words() -> None:
    # Releasing the e-stop and executing a staged plan let a robot move; nothing else does.
    assert {c.name for c in COMMANDS if c.critical} == {"release_estop", "execute_plan"}
    assert len(set(CONFIRMATION.split())) == 3


def test_session_and_safety_actions_are_valid_bus_commands() -> None:
    for command in COMMANDS:
        action = command.action
        if isinstance(action, SessionAction):
            fields = {"command": action.command, "source": "voice"}
            if action.outcome is not None:
                fields["outcome"] = action.outcome
            EpisodeCommand.model_validate(fields)
        if isinstance(action, SafetyAction):
            SafetyCommand(command=action.command, source="voice")


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ("stop", "ambiguous"),
        ("episode", "ambiguous"),
        ("robot please", "did you mean 'robot please execute'"),
        ("please move the robot to the kitchen", "not a command"),
        ("", "no words"),
        ("!!! 123 ...", "no words"),
        ("x" * (MAX_TEXT_CHARS + 1), "too long"),
        ("navigation\x00; rm -rf /", "not a command"),
    ],
)
def test_unknown_ambiguous_and_garbage_text_is_rejected_with_one_line(text: str, says: str) -> None:
    match = parse(text)
    assert match.command is None
    assert match.reason is not None
    assert says in match.reason
    assert "\n" not in match.reason
