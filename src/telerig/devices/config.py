"""Configs of the built-in input devices (registered by ``type``)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field

from telerig.config.schema import DeviceConfig
from telerig.registry import DEVICES

if TYPE_CHECKING:
    from telerig.devices.base import Device

__all__ = ["ButtonPressConfig", "ReplayConfig", "ScriptedVRConfig"]

Vec3 = tuple[float, float, float]


class ButtonPressConfig(BaseModel):
    """A button held from ``start_s`` to ``end_s`` [s] within each scripted cycle."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    button: Annotated[str, Field(pattern=r"^[a-z][a-z0-9_]*$")]
    start_s: Annotated[float, Field(ge=0)]
    end_s: Annotated[float, Field(gt=0)]


@DEVICES.register
class ScriptedVRConfig(DeviceConfig):
    """A scripted VR controller performing pick-and-place cycles.

    Positions are in the operator frame (x forward, y left, z up, metres, origin on the floor
    under the operator); ``cycle_s`` is the duration of one pick-and-place cycle [s].
    """

    type: Literal["scripted_vr"] = "scripted_vr"
    hand: Literal["left", "right"] = "right"
    rate_hz: Annotated[float, Field(gt=0, le=1000)] = 100.0
    home: Vec3 = (0.30, -0.10, 1.00)
    pick: Vec3 = (0.45, 0.10, 0.85)
    place: Vec3 = (0.45, -0.25, 0.85)
    lift_m: Annotated[float, Field(ge=0, le=1)] = 0.10
    cycle_s: Annotated[float, Field(gt=1, le=600)] = 10.0
    #: Buttons held during part of every cycle, e.g. ``[{button: b, start_s: 8.0, end_s: 8.2}]``.
    presses: list[ButtonPressConfig] = Field(default_factory=list)

    def build(self) -> Device:
        from telerig.devices.scripted import ButtonPress, ScriptedVRController

        return ScriptedVRController(
            self.id,
            hand=self.hand,
            rate_hz=self.rate_hz,
            home=self.home,
            pick=self.pick,
            place=self.place,
            lift_m=self.lift_m,
            cycle_s=self.cycle_s,
            presses=[ButtonPress(p.button, p.start_s, p.end_s) for p in self.presses],
        )


@DEVICES.register
class ReplayConfig(DeviceConfig):
    """Plays back a recorded device stream from an episode MCAP with its original timing."""

    type: Literal["replay"] = "replay"
    path: Path
    topic: str | None = None
    source_id: str | None = None
    speed: Annotated[float, Field(gt=0, le=100)] = 1.0
    loop: bool = False

    def build(self) -> Device:
        from telerig.devices.replay import ReplayDevice

        return ReplayDevice(
            self.path,
            topic=self.topic,
            source_id=self.source_id,
            speed=self.speed,
            loop=self.loop,
            id=self.id,
        )
