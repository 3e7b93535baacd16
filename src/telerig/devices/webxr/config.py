"""Config of the WebXR device (registered as ``type: webxr``).

HTTPS: headset browsers only expose WebXR to secure contexts, so on a LAN serve the page over TLS.
A self-signed pair for the host's LAN address (here 192.168.1.20), valid one year::

    openssl req -x509 -newkey rsa:2048 -nodes -days 365 -keyout xr-key.pem -out xr-cert.pem \\
        -subj "/CN=telerig" -addext "subjectAltName=IP:192.168.1.20,DNS:localhost"

then set ``certfile: xr-cert.pem`` and ``keyfile: xr-key.pem``, open ``https://192.168.1.20:8443/``
in the headset browser and accept the certificate warning once. Without a certificate,
``http://localhost:<port>/`` is also a secure context: on a Quest or Pico over USB, run
``adb reverse tcp:8443 tcp:8443`` and open ``http://localhost:8443/`` in the headset.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field, model_validator

from telerig.config.schema import DeviceConfig
from telerig.registry import DEVICES

if TYPE_CHECKING:
    from telerig.devices.base import Device

__all__ = ["WebXRConfig"]


@DEVICES.register
class WebXRConfig(DeviceConfig):
    """A WebXR headset or phone browser (or a desktop browser with keyboard / gamepad).

    Serves the telerig page and its WebSocket on ``host``:``port``; samples are in ``frame_id``
    (operator frame: x forward, y left, z up, metres, origin on the floor under the operator).
    ``certfile`` / ``keyfile`` (PEM) switch to HTTPS/WSS, which headsets need on a LAN.
    """

    type: Literal["webxr"] = "webxr"
    host: str = "0.0.0.0"
    port: Annotated[int, Field(ge=0, le=65535)] = 8443
    certfile: Path | None = None
    keyfile: Path | None = None
    frame_id: str = "operator"
    ping_interval_s: Annotated[float, Field(gt=0, le=60)] = 0.5

    @model_validator(mode="after")
    def _tls_pair(self) -> WebXRConfig:
        if (self.certfile is None) != (self.keyfile is None):
            raise ValueError(
                "certfile and keyfile must be set together (PEM certificate and its key), or neither for HTTP"
            )
        return self

    def build(self) -> Device:
        from telerig.devices.webxr.device import WebXRDevice

        return WebXRDevice(
            self.id,
            host=self.host,
            port=self.port,
            certfile=self.certfile,
            keyfile=self.keyfile,
            frame_id=self.frame_id,
            ping_interval_s=self.ping_interval_s,
        )
