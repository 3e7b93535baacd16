"""Config of the terminal keyboard device (registered as ``type: keyboard``)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field, field_validator

from telerig.config.schema import DeviceConfig
from telerig.registry import DEVICES

if TYPE_CHECKING:
    from telerig.devices.base import Device

__all__ = ["KeyboardConfig"]


@DEVICES.register
class KeyboardConfig(DeviceConfig):
    """The keyboard of the terminal telerig runs in (or of ``path``, a tty) → ``Twist`` + buttons.

    ``key_map`` maps key names (``w``, ``up``, ``pageup``, ``space``, ``3``...) to actions:
    ``+linear_x`` ... ``-angular_z`` (one held key moves at ``max_linear`` [m/s] /
    ``max_angular`` [rad/s] in the operator frame, x forward, y left, z up), ``toggle:trigger``,
    ``mode:<digit>``, ``button:<name>``; unset, WASD/arrows translate, R/F and PgUp/PgDn move up
    and down, Q/E yaw, space toggles the trigger, digits pick the mode. Terminals send no key-up:
    a key is held until ``initial_hold_s`` [s] passes without auto-repeat, then
    ``repeat_release_s`` [s] after its last repeat. ``rate_hz`` is the ``Twist`` rate.
    """

    type: Literal["keyboard"] = "keyboard"
    path: str | None = None
    rate_hz: Annotated[float, Field(gt=0, le=1000)] = 50.0
    key_map: dict[str, str] | None = None
    max_linear: Annotated[float, Field(gt=0, le=5)] = 0.1
    max_angular: Annotated[float, Field(gt=0, le=10)] = 0.5
    initial_hold_s: Annotated[float, Field(gt=0, le=5)] = 0.6
    repeat_release_s: Annotated[float, Field(gt=0, le=5)] = 0.12
    hand: Literal["left", "right"] = "right"
    frame_id: str = "operator"

    @field_validator("key_map")
    @classmethod
    def _check_key_map(cls, value: dict[str, str] | None) -> dict[str, str] | None:
        from telerig.devices.keyboard.protocol import KeyboardNormalizer
        from telerig.errors import ConfigError

        try:
            KeyboardNormalizer("check", key_map=value)
        except ConfigError as exc:
            raise ValueError(str(exc)) from None
        return value

    def build(self) -> Device:
        from telerig.devices.keyboard.device import KeyboardDevice

        return KeyboardDevice(
            self.id,
            path=self.path,
            rate_hz=self.rate_hz,
            key_map=self.key_map,
            max_linear=self.max_linear,
            max_angular=self.max_angular,
            initial_hold_s=self.initial_hold_s,
            repeat_release_s=self.repeat_release_s,
            hand=self.hand,
            frame_id=self.frame_id,
        )
