"""Config of the scripted twist device (registered as ``type: scripted_twist``)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field

from telerig.config.schema import DeviceConfig
from telerig.registry import DEVICES

if TYPE_CHECKING:
    from telerig.devices.base import Device

__all__ = ["ScriptedTwistConfig", "TwistSegmentConfig"]

Vec3 = tuple[float, float, float]
_Button = Annotated[str, Field(pattern=r"^[A-Za-z0-9_.\-]+$", min_length=1, max_length=32)]


class TwistSegmentConfig(BaseModel):
    """One script step: a twist (operator frame: x forward, y left, z up) held for ``duration_s`` [s]."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    duration_s: Annotated[float, Field(gt=0, le=600)]
    #: Linear velocity [m/s].
    linear: Vec3 = (0.0, 0.0, 0.0)
    #: Angular velocity [rad/s].
    angular: Vec3 = (0.0, 0.0, 0.0)
    #: Buttons held during the segment (SpaceMouse names: ``left``, ``right``).
    buttons: list[_Button] = Field(default_factory=list)


@DEVICES.register
class ScriptedTwistConfig(DeviceConfig):
    """A scripted SpaceMouse: plays ``segments`` as ``Twist`` samples (part ``twist``) and button
    changes (part ``<hand>_controller``), exactly the streams a ``spacemouse`` device gives."""

    type: Literal["scripted_twist"] = "scripted_twist"
    rate_hz: Annotated[float, Field(gt=0, le=1000)] = 100.0
    #: Blend time between segment twists [s] (minimum jerk).
    ramp_s: Annotated[float, Field(ge=0, le=10)] = 0.2
    loop: bool = True
    hand: Literal["left", "right"] = "right"
    frame_id: str = "operator"
    segments: Annotated[list[TwistSegmentConfig], Field(min_length=1)]

    def build(self) -> Device:
        from telerig.devices.scripted_twist.device import ScriptedTwistDevice, TwistSegment

        return ScriptedTwistDevice(
            self.id,
            segments=[
                TwistSegment(s.duration_s, s.linear, s.angular, frozenset(s.buttons)) for s in self.segments
            ],
            rate_hz=self.rate_hz,
            ramp_s=self.ramp_s,
            loop=self.loop,
            hand=self.hand,
            frame_id=self.frame_id,
        )
