"""Config of the SpaceMouse device (registered as ``type: spacemouse``)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field

from telerig.config.schema import DeviceConfig
from telerig.registry import DEVICES

if TYPE_CHECKING:
    from telerig.devices.base import Device

__all__ = ["SpaceMouseConfig"]

Sign = Literal[1, -1]


@DEVICES.register
class SpaceMouseConfig(DeviceConfig):
    """A 3Dconnexion SpaceMouse on a Linux hidraw node → operator-frame ``Twist`` + buttons.

    ``path`` is ``/dev/hidrawN`` (or a FIFO fed by the fake); leave it unset to find the first
    known 3Dconnexion device (or ``vendor_id``/``product_id``) through sysfs. Speeds are at full
    deflection (``full_scale`` counts, ~350): ``max_linear`` [m/s], ``max_angular`` [rad/s];
    ``deadband`` is in counts. ``axis_signs`` flips (x, y, z, roll, pitch, yaw) in the operator
    frame (x forward, y left, z up) for models that report an axis the other way.
    """

    type: Literal["spacemouse"] = "spacemouse"
    path: str | None = None
    vendor_id: Annotated[int, Field(ge=0, le=0xFFFF)] | None = None
    product_id: Annotated[int, Field(ge=0, le=0xFFFF)] | None = None
    layout: Literal["auto", "split", "combined"] = "auto"
    max_linear: Annotated[float, Field(gt=0, le=5)] = 0.25
    max_angular: Annotated[float, Field(gt=0, le=10)] = 1.0
    deadband: Annotated[int, Field(ge=0, le=200)] = 10
    full_scale: Annotated[int, Field(ge=50, le=32767)] = 350
    axis_signs: tuple[Sign, Sign, Sign, Sign, Sign, Sign] = (1, 1, 1, 1, 1, 1)
    button_names: tuple[str, ...] = ("left", "right")
    hand: Literal["left", "right"] = "right"
    frame_id: str = "operator"

    def build(self) -> Device:
        from telerig.devices.spacemouse.device import SpaceMouseDevice

        return SpaceMouseDevice(
            self.id,
            path=self.path,
            vendor_id=self.vendor_id,
            product_id=self.product_id,
            layout=self.layout,
            max_linear=self.max_linear,
            max_angular=self.max_angular,
            deadband=self.deadband,
            full_scale=self.full_scale,
            axis_signs=self.axis_signs,
            button_names=self.button_names,
            hand=self.hand,
            frame_id=self.frame_id,
        )
