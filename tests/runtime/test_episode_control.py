"""Episode control: one session command per button press, debounced, with a configurable mapping."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from telerig.ir.types import ControllerState, Handedness, Stamp
from telerig.runtime.episode_control import (
    DEFAULT_BUTTONS,
    EpisodeControlConfig,
    EpisodeController,
    SessionCommand,
)

T0 = 1_700_000_000_000_000_000
MS = 1_000_000


def state(t_ms: int, *buttons: str, hand: Handedness = "right", source: str = "vr0/right") -> ControllerState:
    t = T0 + t_ms * MS
    return ControllerState(
        Stamp(source, t_ms, t, t), hand, (0.4, 0.0, 1.1), (1.0, 0.0, 0.0, 0.0), "operator", frozenset(buttons)
    )


def run(ctrl: EpisodeController, samples: list[ControllerState]) -> list[SessionCommand | None]:
    return [ctrl.update(s) for s in samples]


@pytest.mark.parametrize(
    ("button", "command"),
    [
        ("a", SessionCommand.END_SESSION),
        ("b", SessionCommand.RESET_AND_NEXT),
        ("x", SessionCommand.RESTART_EPISODE),
        ("y", SessionCommand.STOP_COLLECTION),
    ],
)
def test_default_mapping_follows_the_seed(button: str, command: SessionCommand) -> None:
    ctrl = EpisodeController()
    assert run(ctrl, [state(0), state(10, button)]) == [None, command]


def test_held_button_issues_one_command() -> None:
    ctrl = EpisodeController()
    out = run(ctrl, [state(0), *(state(10 * i, "a") for i in range(1, 200))])
    assert out.count(SessionCommand.END_SESSION) == 1


def test_button_held_when_the_stream_appears_does_nothing() -> None:
    ctrl = EpisodeController()
    assert run(ctrl, [state(0, "a"), state(10, "a")]) == [None, None]


def test_press_within_debounce_time_is_ignored() -> None:
    ctrl = EpisodeController(EpisodeControlConfig(debounce_s=0.5))
    out = run(ctrl, [state(0), state(10, "a"), state(20), state(300, "a"), state(400), state(600, "a")])
    assert out == [None, SessionCommand.END_SESSION, None, None, None, SessionCommand.END_SESSION]
    assert ctrl.debounced == 1


def test_debounce_spans_both_controllers() -> None:
    ctrl = EpisodeController()
    left = "vr0/left"
    out = [
        ctrl.update(state(0)),
        ctrl.update(state(0, hand="left", source=left)),
        ctrl.update(state(10, "a")),
        ctrl.update(state(20, "y", hand="left", source=left)),
    ]
    assert out == [None, None, SessionCommand.END_SESSION, None]


def test_presses_are_tracked_per_controller() -> None:
    ctrl = EpisodeController(EpisodeControlConfig(debounce_s=0.0))
    left = "vr0/left"
    out = [
        ctrl.update(state(0, "x", hand="left", source=left)),
        ctrl.update(state(5)),
        ctrl.update(state(10, "x")),  # right controller: a new press even though left holds x
    ]
    assert out == [None, None, SessionCommand.RESTART_EPISODE]


def test_hand_filter_ignores_the_other_controller() -> None:
    ctrl = EpisodeController(EpisodeControlConfig(hand="left"))
    assert run(ctrl, [state(0), state(10, "a")]) == [None, None]


def test_mapping_is_configurable_and_names_are_lowercased() -> None:
    config = EpisodeControlConfig(buttons={"Menu": "stop_collection", "thumbstick": "end_session"})  # type: ignore[dict-item]
    ctrl = EpisodeController(config)
    assert run(ctrl, [state(0), state(10, "a"), state(20, "menu")]) == [
        None,
        None,
        SessionCommand.STOP_COLLECTION,
    ]


def test_several_presses_in_one_sample_give_the_first_in_mapping_order() -> None:
    ctrl = EpisodeController()
    assert run(ctrl, [state(0), state(10, "y", "a")])[-1] == SessionCommand.END_SESSION


def test_unknown_command_names_the_valid_ones() -> None:
    with pytest.raises(ValidationError, match="end_session"):
        EpisodeControlConfig(buttons={"a": "finish"})  # type: ignore[dict-item]


@pytest.mark.parametrize("name", ["", "a b", "1", "trigger!"])
def test_bad_button_name_is_rejected(name: str) -> None:
    with pytest.raises(ValidationError, match="lowercase identifier"):
        EpisodeControlConfig(buttons={name: SessionCommand.END_SESSION})


def test_button_bound_twice_after_lowercasing_is_rejected() -> None:
    with pytest.raises(ValidationError, match="bound twice"):
        EpisodeControlConfig(buttons={"A": SessionCommand.END_SESSION, "a": SessionCommand.STOP_COLLECTION})


def test_config_round_trips_through_json() -> None:
    config = EpisodeControlConfig()
    assert EpisodeControlConfig.model_validate_json(config.model_dump_json()) == config
    assert config.buttons == DEFAULT_BUTTONS


def test_reset_makes_the_next_sample_a_baseline() -> None:
    ctrl = EpisodeController()
    run(ctrl, [state(0), state(10, "a")])
    ctrl.reset()
    assert run(ctrl, [state(20), state(30, "b")]) == [None, SessionCommand.RESET_AND_NEXT]
