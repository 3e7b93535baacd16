"""Config of the data glove device (registered as ``type: glove``)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field

from telerig.config.schema import DeviceConfig
from telerig.registry import DEVICES

if TYPE_CHECKING:
    from telerig.devices.base import Device

__all__ = ["GloveConfig"]

Lengths = tuple[float, float, float]


@DEVICES.register
class GloveConfig(DeviceConfig):
    """A Manus-class data glove behind a telerig glove bridge (TCP, see ``devices/glove/protocol.py``).

    Emits ``HandPose`` samples in the ``"<hand>_glove"`` frame (wrist at the origin, identity wrist
    pose unless the glove reports wrist angles); fuse a tracker pose to place the hand in the room.
    ``segment_lengths_mm``: rows thumb..little, each (proximal, middle, distal) [mm] (thumb:
    metacarpal, proximal, distal); default an adult hand. ``hand_scale`` scales the whole model.
    """

    type: Literal["glove"] = "glove"
    host: str = "127.0.0.1"
    port: Annotated[int, Field(ge=1, le=65535)] = 47810
    hand: Literal["left", "right"] | None = None
    hand_scale: Annotated[float, Field(ge=0.5, le=1.5)] = 1.0
    segment_lengths_mm: tuple[Lengths, Lengths, Lengths, Lengths, Lengths] | None = None
    use_measured_tips: bool = True
    gestures: bool = True
    gesture_hold_samples: Annotated[int, Field(ge=1, le=120)] = 3
    reconnect_s: Annotated[float, Field(gt=0, le=60)] = 0.5
    connect_timeout_s: Annotated[float, Field(gt=0, le=60)] = 2.0
    stale_timeout_s: Annotated[float, Field(gt=0, le=60)] = 2.0

    def build(self) -> Device:
        from telerig.devices.glove.device import GloveDevice
        from telerig.devices.glove.kinematics import DEFAULT_LENGTHS_MM, HandModel

        model = HandModel(self.segment_lengths_mm or DEFAULT_LENGTHS_MM, scale=self.hand_scale)
        return GloveDevice(
            self.id,
            host=self.host,
            port=self.port,
            hand=self.hand,
            model=model,
            use_measured_tips=self.use_measured_tips,
            gestures=self.gestures,
            gesture_hold_samples=self.gesture_hold_samples,
            reconnect_s=self.reconnect_s,
            connect_timeout_s=self.connect_timeout_s,
            stale_timeout_s=self.stale_timeout_s,
        )
