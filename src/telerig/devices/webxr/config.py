"""Config of the WebXR device (registered as ``type: webxr``).

The operator's page is served by the control center, ``telerig serve --rig RIG``, at
``https://<host>:<port>/xr`` behind its login and TLS (headset browsers expose WebXR to secure
contexts only): log in as an operator or admin, open the page from the dashboard's Teleoperate
button (``/xr?device=<id>`` picks one of several WebXR devices) and press Enter VR, or drive the
virtual controllers with the keyboard or a gamepad without a headset. The server checks every
message and relays it to the device over the rig's bus (its ``page_in`` topic, which only the web
server may publish); nothing reaches the device without a login.

A second page is refused while one drives the device; with ``takeover: confirm`` it waits until
the operator confirms: ``telerig device takeover confirm --rig RIG --device ID`` (or the
control center's answer; ``{"takeover": "confirm"}`` on the device's command topic).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field

from telerig.config.schema import DeviceConfig
from telerig.registry import DEVICES

if TYPE_CHECKING:
    from telerig.devices.base import Device

__all__ = ["WebXRConfig"]


@DEVICES.register
class WebXRConfig(DeviceConfig):
    """A WebXR headset or phone browser (or a desktop browser with keyboard / gamepad), through the
    control center's ``/xr`` page.

    Samples are in ``frame_id`` (operator frame: x forward, y left, z up, metres, origin on the
    floor under the operator). ``ping_interval_s``: clock-sync ping period [s]. ``takeover``:
    ``refuse`` a second page while one is active, or hold it until the operator ``confirm`` s
    (within ``takeover_timeout_s`` [s]).
    """

    type: Literal["webxr"] = "webxr"
    frame_id: str = "operator"
    ping_interval_s: Annotated[float, Field(gt=0, le=60)] = 0.5
    takeover: Literal["refuse", "confirm"] = "refuse"
    takeover_timeout_s: Annotated[float, Field(gt=0, le=600)] = 30.0

    def build(self) -> Device:
        from telerig.devices.webxr.device import WebXRDevice

        return WebXRDevice(
            self.id,
            frame_id=self.frame_id,
            ping_interval_s=self.ping_interval_s,
            takeover=self.takeover,
            takeover_timeout_s=self.takeover_timeout_s,
        )
