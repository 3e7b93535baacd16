"""Config of the WebXR device (registered as ``type: webxr``).

By default the server listens on 127.0.0.1 (this host only). For a headset on the LAN set ``host:
0.0.0.0`` (or the LAN address): the server then requires the pairing token it generates at start
(``telerig run`` prints the URL with the token and a QR code to scan with the headset) and serves
HTTPS with a self-signed certificate it generates once into ``tls_dir`` (accept it once in the
headset browser). A second page is refused while one drives the device; with ``takeover: confirm``
it waits until the operator confirms: ``telerig device takeover confirm --rig RIG --device ID``
(``{"takeover": "confirm"}`` on the device's command topic).

HTTPS: headset browsers only expose WebXR to secure contexts. To use your own certificate instead,
e.g. a self-signed pair for the host's LAN address (here 192.168.1.20), valid one year::

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
    ``certfile`` / ``keyfile`` (PEM) switch to HTTPS/WSS, which headsets need on a LAN; bound
    beyond loopback without them, a self-signed pair is generated into ``tls_dir``
    (``<data root>/tls``). ``takeover``: ``refuse`` a second page while one is active, or hold it
    until the operator ``confirm`` s (within ``takeover_timeout_s``). ``allowed_origins``: browser
    origins allowed besides the server's own. ``pairing``: require the token and TLS (default: exactly
    when bound beyond loopback).
    """

    type: Literal["webxr"] = "webxr"
    host: str = "127.0.0.1"
    port: Annotated[int, Field(ge=0, le=65535)] = 8443
    certfile: Path | None = None
    keyfile: Path | None = None
    frame_id: str = "operator"
    ping_interval_s: Annotated[float, Field(gt=0, le=60)] = 0.5
    tls_dir: Path = Path("telerig-data/tls")
    takeover: Literal["refuse", "confirm"] = "refuse"
    takeover_timeout_s: Annotated[float, Field(gt=0, le=600)] = 30.0
    allowed_origins: tuple[str, ...] = ()
    pairing: bool | None = None

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
            tls_dir=self.tls_dir,
            takeover=self.takeover,
            takeover_timeout_s=self.takeover_timeout_s,
            allowed_origins=self.allowed_origins,
            pairing=self.pairing,
        )
