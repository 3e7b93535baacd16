"""A fake WebXR page (public test utility): encodes page messages and plays the page's WebSocket side.

:func:`encode_frame` writes exactly what ``static/telerig-xr.js`` sends; :class:`FakeXRPage`
connects to the control center's page WebSocket (after a login), answers its clock pings and sends
frames, so a lab can dry-run a rig without a headset; :class:`LocalRelay` plays the control
center's relay in-process for a device alone. ``FAKE_XR_SHIM`` (the text of
``static/fake-xr.js``) is a ``navigator.xr`` emulation for driving the real page's XR path in a
browser without a headset (inject it before the page's scripts run).
"""

from __future__ import annotations

import contextlib
import importlib.resources
import math
import ssl
import struct
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from types import TracebackType

from telerig.devices.base import RelayedDevice
from telerig.devices.webxr.protocol import HAND_JOINTS, KIND_FRAME, KIND_PING, KIND_PONG, MAGIC, VERSION
from telerig.devices.webxr.relay import (
    CLOSE,
    MESSAGE,
    OPEN,
    PAGE_SUBPROTOCOL,
    decode_event,
    encode_event,
    open_body,
    parse_close,
)
from telerig.errors import DeviceError

__all__ = [
    "FAKE_XR_SHIM",
    "FakeXRPage",
    "LocalPage",
    "LocalRelay",
    "XRControllerInput",
    "XRHandInput",
    "encode_frame",
    "encode_pong",
    "typical_payload",
]

Vec3 = tuple[float, float, float]
#: WebXR quaternion order (x, y, z, w).
QuatXYZW = tuple[float, float, float, float]

_IDENTITY: QuatXYZW = (0.0, 0.0, 0.0, 1.0)
_MODES = {"desktop": 0, "immersive-vr": 1, "immersive-ar": 2}


def _shim() -> str:
    return (importlib.resources.files("telerig.devices.webxr") / "static" / "fake-xr.js").read_text("utf-8")


#: JavaScript that replaces ``navigator.xr`` with an emulated immersive session (see ``fake-xr.js``).
FAKE_XR_SHIM: str = _shim()


@dataclass(frozen=True, slots=True)
class XRControllerInput:
    """A controller as the page reads it, in the WebXR ``local-floor`` space (y up, -z forward, m).

    Attributes:
        position: Grip position [m]. Shape (3,).
        orientation: Grip orientation (x, y, z, w) (WebXR order).
        trigger: Trigger value in [0, 1].
        squeeze: Squeeze value in [0, 1].
        thumbstick: Thumbstick (x, y) as the Gamepad API reports it (y = -1 pushed forward).
        buttons: Bit i set when xr-standard ``gamepad.buttons[i]`` is pressed.
    """

    position: Vec3 = (0.2, 1.0, -0.3)
    orientation: QuatXYZW = _IDENTITY
    trigger: float = 0.0
    squeeze: float = 0.0
    thumbstick: tuple[float, float] = (0.0, 0.0)
    buttons: int = 0


@dataclass(frozen=True, slots=True)
class XRHandInput:
    """A tracked hand as the page reads it: 25 XRHand joints, WebXR ``local-floor`` space.

    Attributes:
        positions: Joint positions [m] in XRHand order. Length 25.
        orientations: Joint orientations (x, y, z, w). Length 25.
        radii: Joint radii [m]; 0 marks an untracked joint. Length 25.
    """

    positions: Sequence[Vec3]
    orientations: Sequence[QuatXYZW] = field(default_factory=lambda: [_IDENTITY] * len(HAND_JOINTS))
    radii: Sequence[float] = field(default_factory=lambda: [0.01] * len(HAND_JOINTS))

    @classmethod
    def flat(cls, wrist: Vec3 = (0.2, 1.0, -0.3), spacing_m: float = 0.02) -> XRHandInput:
        """A flat hand, fingers pointing forward (-z), joints ``spacing_m`` apart from ``wrist``."""
        positions: list[Vec3] = [wrist]
        for finger in range(5):
            x = wrist[0] + (finger - 2) * spacing_m
            positions.extend(
                (x, wrist[1], wrist[2] - (k + 1) * spacing_m) for k in range(4 if finger == 0 else 5)
            )
        return cls(positions=positions)


def encode_frame(
    seq: int,
    client_ms: float,
    *,
    mode: str = "immersive-vr",
    head: tuple[Vec3, QuatXYZW] | None = None,
    left: XRControllerInput | None = None,
    right: XRControllerInput | None = None,
    left_hand: XRHandInput | None = None,
    right_hand: XRHandInput | None = None,
) -> bytes:
    """One frame message exactly as the page encodes it (see :mod:`telerig.devices.webxr.protocol`).

    ``client_ms`` is the page clock [ms since the Unix epoch]; poses are in WebXR ``local-floor``.
    """
    present = 0
    body = bytearray()
    if head is not None:
        present |= 1
        body += struct.pack("<7f", *head[0], *head[1])
    for bit, c in ((1, left), (2, right)):
        if c is not None:
            present |= 1 << bit
            body += struct.pack(
                "<11fI", *c.position, *c.orientation, c.trigger, c.squeeze, *c.thumbstick, c.buttons
            )
    for bit, h in ((3, left_hand), (4, right_hand)):
        if h is not None:
            present |= 1 << bit
            if not len(h.positions) == len(h.orientations) == len(h.radii) == len(HAND_JOINTS):
                raise ValueError(f"a hand needs {len(HAND_JOINTS)} joint positions, orientations and radii")
            for p, q, r in zip(h.positions, h.orientations, h.radii, strict=True):
                body += struct.pack("<8f", *p, *q, r)
    head_bytes = struct.pack(
        "<2sBBIdBBH", MAGIC, VERSION, KIND_FRAME, seq, client_ms, _MODES[mode], present, 0
    )
    return head_bytes + bytes(body)


def encode_pong(ping_id: int, client_ms: float) -> bytes:
    """A pong message: the page clock [ms since epoch] when ping ``ping_id`` arrived."""
    return struct.pack("<2sBBId", MAGIC, VERSION, KIND_PONG, ping_id, client_ms)


def typical_payload() -> bytes:
    """One typical headset frame: head, both controllers and both tracked hands (1,744 bytes)."""
    tilt = math.sqrt(0.5)
    return encode_frame(
        1234,
        1.7e12 + 0.5,
        head=((0.0, 1.6, 0.0), (0.0, 0.0, 0.0, 1.0)),
        left=XRControllerInput((-0.2, 1.0, -0.3), (0.0, 0.0, 0.0, 1.0), 0.1, 0.9, (0.0, -0.5), 0b10010),
        right=XRControllerInput((0.2, 1.0, -0.3), (-tilt, 0.0, 0.0, tilt), 0.8, 0.0, (0.3, 0.0), 0b1),
        left_hand=XRHandInput.flat((-0.2, 1.0, -0.3)),
        right_hand=XRHandInput.flat((0.2, 1.0, -0.3)),
    )


class FakeXRPage:
    """Plays the page side of the control center's WebSocket (``/api/xr/<device>`` of ``telerig
    serve``): answers clock pings, sends frames you build.

    Log in first (``POST /api/login``) and give the session cookie and its CSRF token; the
    server also wants the ``Origin`` a browser would send (its own). Its clock is
    ``time.time_ns()`` plus ``clock_skew_ms``. Use as a context manager; :meth:`close` is idempotent.
    """

    def __init__(
        self,
        ws_url: str,
        *,
        cookie: str,
        csrf: str,
        origin: str,
        clock_skew_ms: float = 0.0,
        timeout_s: float = 5.0,
        ssl_context: ssl.SSLContext | None = None,
    ) -> None:
        """Args:
        ws_url: The server's page WebSocket, e.g. ``wss://lab:8443/api/xr/browser``.
        cookie: The ``telerig_session`` cookie's value from the login.
        csrf: The login's CSRF token (sent as the ``csrf.<token>`` subprotocol, as the page does).
        origin: ``Origin`` header, e.g. ``https://lab:8443``.
        clock_skew_ms: Page clock minus the common clock [ms].
        timeout_s: Connection timeout [s].
        ssl_context: TLS settings for a ``wss://`` URL (e.g. trusting the server's certificate).
        """
        from websockets.sync.client import connect
        from websockets.typing import Origin, Subprotocol

        self.clock_skew_ms = float(clock_skew_ms)
        self.pings_answered = 0
        self.close_code: int | None = None
        self._stack = contextlib.ExitStack()
        try:
            self._ws = self._stack.enter_context(
                connect(
                    ws_url,
                    open_timeout=timeout_s,
                    compression=None,
                    ssl=ssl_context,
                    origin=Origin(origin),
                    subprotocols=[Subprotocol(PAGE_SUBPROTOCOL), Subprotocol(f"csrf.{csrf}")],
                    additional_headers={"Cookie": f"telerig_session={cookie}"},
                )
            )
        except OSError as exc:
            raise DeviceError(
                f"fake page cannot connect to {ws_url}: {exc}; is telerig serve running?"
            ) from exc
        self._closed = False
        self._thread = threading.Thread(target=self._answer_pings, name="telerig-fake-xr-page", daemon=True)
        self._thread.start()

    def now_ms(self) -> float:
        """The page clock [ms since epoch]."""
        return time.time_ns() / 1e6 + self.clock_skew_ms

    def send(self, message: bytes | str) -> None:
        """Send one raw message (bytes as binary, str as text)."""
        self._ws.send(message)

    def _answer_pings(self) -> None:
        from websockets.exceptions import ConnectionClosed

        try:
            for message in self._ws:
                if isinstance(message, bytes) and len(message) == 8 and message[3] == KIND_PING:
                    (ping_id,) = struct.unpack_from("<I", message, 4)
                    self._ws.send(encode_pong(ping_id, self.now_ms()))
                    self.pings_answered += 1
        except ConnectionClosed:
            pass
        self.close_code = self._ws.close_code

    def close(self) -> None:
        """Close the connection and join the ping thread. Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._stack.close()
        self._thread.join(timeout=5.0)

    def __enter__(self) -> FakeXRPage:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


class LocalRelay:
    """Plays ``telerig serve``'s relay in-process, for a :class:`~telerig.devices.webxr.device.WebXRDevice`
    without a bus or a web server (tests, benchmarks): pages you :meth:`open` send their messages in
    relay envelopes; their clock pings are answered at once; the device's closes are kept.

    Call before the device starts (it sets the device's page sink).
    """

    def __init__(self, device: RelayedDevice, *, clock_skew_ms: float = 0.0) -> None:
        self._device = device
        self.clock_skew_ms = float(clock_skew_ms)
        #: Close code and reason the device sent, per connection.
        self.closed: dict[int, tuple[int, str]] = {}
        self.pings_answered = 0
        self._next = 1
        self._lock = threading.Lock()
        device.set_page_sink(self._from_device)

    def open(self, user: str = "otto", client: str = "127.0.0.1") -> LocalPage:
        """A new page connection of ``user``."""
        with self._lock:
            conn, self._next = self._next, self._next + 1
        self._device.page_message(encode_event(OPEN, conn, open_body(user, client)))
        return LocalPage(self, conn)

    def now_ms(self) -> float:
        """The pages' clock [ms since epoch]."""
        return time.time_ns() / 1e6 + self.clock_skew_ms

    def _from_device(self, payload: bytes) -> None:
        event = decode_event(payload)
        if event.event == CLOSE:
            with self._lock:  # the first close ends the connection, as a WebSocket's does
                self.closed.setdefault(event.conn, parse_close(event.body))
        elif event.conn in self.closed:
            return
        elif event.event == MESSAGE and len(event.body) == 8 and event.body[3] == KIND_PING:
            (ping_id,) = struct.unpack_from("<I", event.body, 4)
            pong = encode_pong(ping_id, self.now_ms())
            self._device.page_message(encode_event(MESSAGE, event.conn, pong))
            self.pings_answered += 1


@dataclass(frozen=True, slots=True)
class LocalPage:
    """One page connection of a :class:`LocalRelay`."""

    relay: LocalRelay
    conn: int

    def send(self, message: bytes) -> None:
        """Relay one page message to the device."""
        self.relay._device.page_message(encode_event(MESSAGE, self.conn, message))

    def close(self) -> None:
        """The page goes away."""
        self.relay._device.page_message(encode_event(CLOSE, self.conn))

    @property
    def close_code(self) -> int | None:
        """The close code the device sent this page, if it did."""
        got = self.relay.closed.get(self.conn)
        return None if got is None else got[0]
