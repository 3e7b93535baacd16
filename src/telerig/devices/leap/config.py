"""Config of the Leap Motion hand tracker device (registered as ``type: leap``)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field, field_validator

from telerig.config.schema import DeviceConfig
from telerig.registry import DEVICES

if TYPE_CHECKING:
    from telerig.devices.base import Device

__all__ = ["LeapConfig"]

Hand = Literal["left", "right"]


@DEVICES.register
class LeapConfig(DeviceConfig):
    """A Leap Motion class hand tracker, read from its service's WebSocket (legacy JSON, v6).

    The mounting maps the Leap frame (origin at the device, x right, y up, z toward the user, mm)
    into the operator frame (x forward, y left, z up, m): ``mount_orientation`` is the unit
    quaternion (w, x, y, z) rotating Leap vectors into the operator frame, ``mount_position_m`` the
    device origin in the operator frame [m]. The defaults describe a device lying on a 0.75 m desk,
    0.40 m in front of the operator, its +z toward them. For a head-mounted device set both to the
    head pose (and ``frame_id`` to the head frame if it moves).
    """

    type: Literal["leap"] = "leap"
    url: str = "ws://127.0.0.1:6437/v6.json"
    hands: tuple[Hand, ...] = ("left", "right")
    mount_orientation: tuple[float, float, float, float] = (0.5, 0.5, -0.5, -0.5)
    mount_position_m: tuple[float, float, float] = (0.40, 0.0, 0.75)
    frame_id: str = "operator"
    min_confidence: Annotated[float, Field(ge=0, le=1)] = 0.0
    background: bool = True
    reconnect_s: Annotated[float, Field(gt=0, le=60)] = 0.5
    open_timeout_s: Annotated[float, Field(gt=0, le=60)] = 2.0
    stale_timeout_s: Annotated[float, Field(gt=0, le=60)] = 2.0

    @field_validator("url")
    @classmethod
    def _ws_url(cls, value: str) -> str:
        if not value.startswith(("ws://", "wss://")):
            raise ValueError(
                f"url must start with ws:// or wss://, e.g. ws://127.0.0.1:6437/v6.json; got {value!r}"
            )
        return value

    @field_validator("mount_orientation")
    @classmethod
    def _unit_quaternion(cls, value: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
        norm = sum(v * v for v in value) ** 0.5
        if abs(norm - 1.0) > 1e-3:
            raise ValueError(
                f"mount_orientation must be a unit quaternion (w, x, y, z); its norm is {norm:.4f}"
            )
        return value

    @field_validator("hands")
    @classmethod
    def _hands(cls, value: tuple[Hand, ...]) -> tuple[Hand, ...]:
        if not value or len(set(value)) != len(value):
            raise ValueError("hands must list 'left' and/or 'right' once each")
        return value

    def build(self) -> Device:
        from telerig.devices.leap.device import LeapDevice
        from telerig.devices.leap.protocol import Mounting

        return LeapDevice(
            self.id,
            url=self.url,
            hands=self.hands,
            mounting=Mounting(self.mount_orientation, self.mount_position_m),
            frame_id=self.frame_id,
            min_confidence=self.min_confidence,
            background=self.background,
            reconnect_s=self.reconnect_s,
            open_timeout_s=self.open_timeout_s,
            stale_timeout_s=self.stale_timeout_s,
        )
