"""Config of the native VR stream device (type ``udp_vr``)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field

from telerig.config.schema import DeviceConfig
from telerig.registry import DEVICES

if TYPE_CHECKING:
    from telerig.devices.base import Device

__all__ = ["UdpVrConfig"]


@DEVICES.register
class UdpVrConfig(DeviceConfig):
    """A headset companion app streaming ``telerig.v1.VrFrame`` datagrams (head, controllers, hands).

    ``host`` is the address to listen on: 127.0.0.1 (default) hears only this machine; a lab sets
    the station's LAN address (or 0.0.0.0) so the headset can reach it, and points the app at
    ``host:port``. Samples are in the operator frame (x forward, y left, z up, metres).
    """

    type: Literal["udp_vr"] = "udp_vr"
    host: str = "127.0.0.1"
    port: Annotated[int, Field(ge=0, le=65535)] = 9870
    frame_id: str = "operator"
    clock_window_s: Annotated[float, Field(gt=0, le=3600)] = 6.0

    def build(self) -> Device:
        from telerig.devices.udp_vr.device import UdpVrDevice

        return UdpVrDevice(
            self.id,
            host=self.host,
            port=self.port,
            frame_id=self.frame_id,
            clock_window_s=self.clock_window_s,
        )
