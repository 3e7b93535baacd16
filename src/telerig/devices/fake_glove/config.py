"""Config of the fake glove (registered as ``type: fake_glove``): dry-runs a glove rig with no hardware."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field

from telerig.config.schema import DeviceConfig
from telerig.registry import DEVICES

if TYPE_CHECKING:
    from telerig.devices.base import Device

__all__ = ["FakeGloveConfig"]


@DEVICES.register
class FakeGloveConfig(DeviceConfig):
    """A glove bridge simulated in-process (:class:`~telerig.devices.glove.fake.FakeGloveBridge` on a
    free 127.0.0.1 port) read by the real glove device over TCP, so a glove rig runs with no hardware.

    The hand cycles open, fist, point, pinch: each held ``dwell_s``, blended over ``transition_s``
    [s]. Samples are the glove device's (``HandPose`` on part ``<hand>_hand``).
    """

    type: Literal["fake_glove"] = "fake_glove"
    hand: Literal["left", "right"] = "right"
    rate_hz: Annotated[float, Field(gt=0, le=1000)] = 60.0
    dwell_s: Annotated[float, Field(ge=0, le=60)] = 0.6
    transition_s: Annotated[float, Field(gt=0, le=60)] = 0.4

    def build(self) -> Device:
        from telerig.devices.fake_glove.device import FakeGloveDevice

        return FakeGloveDevice(
            self.id,
            hand=self.hand,
            rate_hz=self.rate_hz,
            dwell_s=self.dwell_s,
            transition_s=self.transition_s,
        )
