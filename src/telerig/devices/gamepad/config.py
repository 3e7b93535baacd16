"""Config of the evdev gamepad device (registered as ``type: gamepad``)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field, ValidationInfo, field_validator

from telerig.config.schema import DeviceConfig
from telerig.registry import DEVICES

if TYPE_CHECKING:
    from telerig.devices.base import Device

__all__ = ["GamepadConfig"]


@DEVICES.register
class GamepadConfig(DeviceConfig):
    """A gamepad on a Linux evdev node → left/right ``ControllerState`` + a ``Twist``.

    ``path`` is ``/dev/input/eventN`` (or a FIFO fed by the fake); leave it unset to take the
    first device with gamepad buttons (whose name contains ``name``, if set). ``profile`` picks
    button codes and default raw ranges (``xbox``: xpad; ``playstation``: hid-playstation); real
    nodes report their ranges themselves, ``axis_ranges`` overrides per axis (``x``, ``y``, ``rx``,
    ``ry``, ``z``, ``rz``, ``gas``, ``brake``). Deadzones are fractions of full deflection.
    ``twist_map`` maps ``linear_x`` ... ``angular_z`` to expressions such as ``"-left_x"`` or
    ``"right_trigger-left_trigger"``; a value of 1 gives ``max_linear`` [m/s] / ``max_angular``
    [rad/s]. Unset, the left stick drives x/y, the right stick z and yaw.
    """

    type: Literal["gamepad"] = "gamepad"
    path: str | None = None
    name: str | None = None
    profile: Literal["xbox", "playstation"] = "xbox"
    axis_ranges: dict[str, tuple[int, int]] = Field(default_factory=dict)
    button_map: dict[int, str] = Field(default_factory=dict)
    stick_deadzone: Annotated[float, Field(ge=0, le=0.9)] = 0.1
    trigger_deadzone: Annotated[float, Field(ge=0, le=0.9)] = 0.02
    twist_map: dict[str, str] | None = None
    max_linear: Annotated[float, Field(gt=0, le=5)] = 0.25
    max_angular: Annotated[float, Field(gt=0, le=10)] = 1.0
    frame_id: str = "operator"
    twist_frame_id: str = "operator"

    @field_validator("twist_map", "axis_ranges")
    @classmethod
    def _check_with_normalizer(cls, value: object, info: ValidationInfo) -> object:
        # One source of truth for valid axis names and twist expressions: the normalizer.
        from telerig.devices.gamepad.protocol import GamepadNormalizer
        from telerig.errors import ConfigError

        try:
            GamepadNormalizer("check", **{str(info.field_name): value})  # type: ignore[arg-type]
        except ConfigError as exc:
            raise ValueError(str(exc)) from None
        return value

    def build(self) -> Device:
        from telerig.devices.gamepad.device import GamepadDevice

        return GamepadDevice(
            self.id,
            path=self.path,
            name=self.name,
            profile=self.profile,
            axis_ranges=self.axis_ranges,
            button_map=self.button_map,
            stick_deadzone=self.stick_deadzone,
            trigger_deadzone=self.trigger_deadzone,
            twist_map=self.twist_map,
            max_linear=self.max_linear,
            max_angular=self.max_angular,
            frame_id=self.frame_id,
            twist_frame_id=self.twist_frame_id,
        )
