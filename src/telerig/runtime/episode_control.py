"""Episode control from controller buttons: presses → session commands (A end, B next, X redo, Y stop)."""

from __future__ import annotations

from telerig.config.schema import DEFAULT_BUTTONS, EpisodeControlConfig, SessionCommand
from telerig.ir.types import ControllerState

__all__ = ["DEFAULT_BUTTONS", "EpisodeControlConfig", "EpisodeController", "SessionCommand"]


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
