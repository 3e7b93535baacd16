"""Episode control from controller buttons: presses → session commands (A end, B next, X redo, Y stop)."""

from __future__ import annotations

import re
from enum import StrEnum
from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, field_validator

from telerig.ir.types import ControllerState, Handedness

__all__ = ["DEFAULT_BUTTONS", "EpisodeControlConfig", "EpisodeController", "SessionCommand"]


class SessionCommand(StrEnum):
    """What the operator asks the session to do.

    Attributes:
        END_SESSION: End the active recording session (the episode is kept).
        RESET_AND_NEXT: Reset the robot to a safe pose so the operator can reposition, then start
            the next recording.
        RESTART_EPISODE: Discard the current episode and record it again from the start.
        STOP_COLLECTION: Stop collecting: discard the current episode, keep the earlier ones.
    """

    END_SESSION = "end_session"
    RESET_AND_NEXT = "reset_and_next"
    RESTART_EPISODE = "restart_episode"
    STOP_COLLECTION = "stop_collection"


#: The seed's mapping (Quest / Pico layout: A, B on the right controller, X, Y on the left).
DEFAULT_BUTTONS: dict[str, SessionCommand] = {
    "a": SessionCommand.END_SESSION,
    "b": SessionCommand.RESET_AND_NEXT,
    "x": SessionCommand.RESTART_EPISODE,
    "y": SessionCommand.STOP_COLLECTION,
}

_BUTTON = re.compile(r"^[a-z][a-z0-9_]*$")


class EpisodeControlConfig(BaseModel):
    """Which controller buttons issue which session commands.

    Attributes:
        buttons: Button name (as in ``ControllerState.buttons``, e.g. ``"a"``, ``"menu"``) → command;
            names are lower-cased. Order matters only when several bound buttons go down in one
            sample: the first in this mapping wins.
        hand: Only controllers of this hand issue commands; ``None`` = either hand.
        debounce_s: Presses within this time [s] of the previous command are ignored.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    buttons: dict[str, SessionCommand] = Field(default_factory=lambda: dict(DEFAULT_BUTTONS))
    hand: Handedness | None = None
    debounce_s: Annotated[float, Field(ge=0, le=10)] = 0.5

    @field_validator("buttons", mode="before")
    @classmethod
    def _names(cls, value: object) -> object:
        if not isinstance(value, dict):
            return value
        out: dict[object, object] = {}
        for name, command in value.items():
            key = name.strip().lower() if isinstance(name, str) else name
            if not isinstance(key, str) or not _BUTTON.match(key):
                raise ValueError(
                    f"button name {name!r} must be a lowercase identifier like 'a', 'menu' or 'thumbstick'"
                )
            if key in out:
                raise ValueError(f"button {key!r} is bound twice; bind each button to one command")
            out[key] = command
        return out


class EpisodeController:
    """Turns button presses of bound ``ControllerState`` samples into :class:`SessionCommand` values.

    A press is a bound button that is down in a sample and was not down in the previous sample
    of the same controller (``stamp.source_id``, hand); the first sample of a controller only sets
    the baseline, so a button already held when the stream appears does nothing. One command per
    press; presses within ``debounce_s`` of the previous command (by ``stamp.capture_ns``) are
    ignored. Pure: no clock, no threads.

    The seed also lets A, pressed while the robot is reset, return the robot to its neutral pose
    before B starts the next recording; that depends on the session state, so it is the runtime's
    reading of :attr:`SessionCommand.END_SESSION` while resetting.
    """

    def __init__(self, config: EpisodeControlConfig | None = None) -> None:
        self.config = config if config is not None else EpisodeControlConfig()
        self._bound = frozenset(self.config.buttons)
        self._debounce_ns = int(self.config.debounce_s * 1e9)
        self._previous: dict[tuple[str, str], frozenset[str]] = {}
        self._last_command_ns: int | None = None
        #: Presses ignored because they came too soon after a command.
        self.debounced = 0

    def update(self, sample: ControllerState) -> SessionCommand | None:
        """Consume one controller sample; return the command its presses ask for, if any."""
        hand = self.config.hand
        if hand is not None and sample.hand != hand:
            return None
        key = (sample.stamp.source_id, sample.hand)
        down = sample.buttons & self._bound
        before = self._previous.get(key)
        self._previous[key] = down
        if before is None:
            return None
        pressed = down - before
        if not pressed:
            return None
        t = sample.stamp.capture_ns
        last = self._last_command_ns
        if last is not None and t - last < self._debounce_ns:
            self.debounced += len(pressed)
            return None
        command = next(c for b, c in self.config.buttons.items() if b in pressed)
        self._last_command_ns = t
        return command

    def reset(self) -> None:
        """Forget button history and the debounce time (e.g. when a controller reconnects)."""
        self._previous.clear()
        self._last_command_ns = None
