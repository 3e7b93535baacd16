"""The relay envelope: how ``telerig serve`` carries a logged-in page's WebSocket to its WebXR device.

The page talks to the control center (``/api/xr/<device>``: login cookie, operator role, same
origin, TLS); the server checks each message against the wire format (:mod:`.protocol`) and puts the
page's bytes, unchanged, in an envelope on the device's ``page_in`` topic; the device answers (clock
pings, a close) on its ``page_out`` topic. One WebSocket is one *connection* ``conn`` (a random
u64 the server picks), so the device can tell pages apart, keep one driving and hold a takeover::

    offset  type   field
    0       2 B    magic b"TR"
    2       u8     version (1)
    3       u8     event: 1 open, 2 message, 3 close, 4 stamped message
    4       u64    conn
    12      body   open (server -> device): UTF-8 JSON {"user", "client"} (at most 512 bytes)
                   message: one page message (server -> device) or ping (device -> server)
                   close (device -> server): u16 WebSocket close code, UTF-8 reason (<= 120 B)
                   close (server -> device): empty (the page went away)
                   stamped message (server -> device): i64 the server's receive time [ns, its
                   clock], then one page message: where the page's frame reached telerig (the
                   ``receive`` latency stage ends there, ``telerig.config.latency``)
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from typing import Final

from telerig.devices.webxr.protocol import WebXRWireError

__all__ = [
    "CLOSE",
    "MAX_PAGE_MESSAGE",
    "MESSAGE",
    "OPEN",
    "PAGE_SUBPROTOCOL",
    "STAMPED",
    "RelayEvent",
    "close_body",
    "decode_event",
    "encode_event",
    "open_body",
    "parse_close",
    "parse_open",
    "parse_stamped",
    "stamped_body",
]

#: WebSocket subprotocol of the page; it also offers ``csrf.<token>`` (its login's CSRF token).
PAGE_SUBPROTOCOL: Final = "telerig-xr.v1"
MAGIC: Final = b"TR"
VERSION: Final = 1
OPEN: Final = 1
MESSAGE: Final = 2
CLOSE: Final = 3
STAMPED: Final = 4
#: Largest page message relayed [bytes]: a full frame (head, 2 controllers, 2 hands) is 1,744 bytes.
MAX_PAGE_MESSAGE: Final = 1 << 14
_HEAD = struct.Struct("<2sBBQ")
_CODE = struct.Struct("<H")
_SERVER_NS = struct.Struct("<q")
_MAX_OPEN = 512
_MAX_REASON = 120


@dataclass(frozen=True, slots=True)
class RelayEvent:
    """One envelope: ``event`` (:data:`OPEN`, :data:`MESSAGE`, :data:`CLOSE`), connection, body."""

    event: int
    conn: int
    body: bytes


def encode_event(event: int, conn: int, body: bytes = b"") -> bytes:
    """The envelope of ``body`` for connection ``conn`` (u64)."""
    return _HEAD.pack(MAGIC, VERSION, event, conn & 0xFFFFFFFFFFFFFFFF) + body


def decode_event(data: bytes) -> RelayEvent:
    """Parse an envelope (not its body's page message).

    Raises:
        WebXRWireError: reason ``relay``: too short or long, wrong magic, version or event.
    """
    largest = _HEAD.size + _SERVER_NS.size + MAX_PAGE_MESSAGE
    if not _HEAD.size <= len(data) <= largest:
        raise WebXRWireError(
            "relay", f"relay envelope must be {_HEAD.size}..{largest} bytes, got {len(data)}"
        )
    magic, version, event, conn = _HEAD.unpack_from(data)
    if magic != MAGIC or version != VERSION or event not in (OPEN, MESSAGE, CLOSE, STAMPED):
        raise WebXRWireError(
            "relay",
            f"relay envelope must start b'TR', version {VERSION}, event 1-4; "
            f"got {bytes(magic)!r} {version} {event}",
        )
    return RelayEvent(event, conn, bytes(data[_HEAD.size :]))


def open_body(user: str, client: str) -> bytes:
    """The body of an open: who logged in and from where (each cut to 64 characters)."""
    return json.dumps({"user": user[:64], "client": client[:64]}).encode()


def parse_open(body: bytes) -> tuple[str, str]:
    """``(user, client)`` of an open's body.

    Raises:
        WebXRWireError: reason ``relay``: not that JSON object, or too long.
    """
    try:
        if len(body) > _MAX_OPEN:
            raise ValueError(f"{len(body)} bytes")
        doc = json.loads(body)
        user, client = doc["user"], doc["client"]
        if not isinstance(user, str) or not isinstance(client, str):
            raise ValueError("user and client must be strings")
    except (ValueError, KeyError, TypeError) as exc:
        raise WebXRWireError("relay", f"relay open must be JSON {{'user', 'client'}}: {exc}") from None
    return user[:64], client[:64]


def stamped_body(server_ns: int, message: bytes) -> bytes:
    """The body of a stamped message: the server's receive time [ns] and the page's message."""
    return _SERVER_NS.pack(server_ns) + message


def parse_stamped(body: bytes) -> tuple[int, bytes]:
    """``(server_ns, message)`` of a stamped message's body.

    Raises:
        WebXRWireError: reason ``relay``: shorter than the stamp.
    """
    if len(body) < _SERVER_NS.size:
        raise WebXRWireError("relay", f"a stamped relay message needs 8 bytes of stamp, got {len(body)}")
    (server_ns,) = _SERVER_NS.unpack_from(body)
    return server_ns, body[_SERVER_NS.size :]


def close_body(code: int, reason: str) -> bytes:
    """The body of a device's close: WebSocket close code and a short reason."""
    return _CODE.pack(code) + reason.encode()[:_MAX_REASON]


def parse_close(body: bytes) -> tuple[int, str]:
    """``(code, reason)`` of a device's close; a body without a code reads as 1000, ``""``."""
    if len(body) < _CODE.size:
        return 1000, ""
    (code,) = _CODE.unpack_from(body)
    return code, body[_CODE.size : _CODE.size + _MAX_REASON].decode("utf-8", "replace")
