"""The operator's WebXR page and its pose stream, behind the control center's login and TLS.

- ``GET /xr``: the page (``telerig.devices.webxr``'s ``static/``), for an operator or admin;
  ``?device=<id>`` picks one of the rig's WebXR devices (the first by default).
- ``GET /api/xr``: the rig's WebXR devices and what this server relayed to each (counters).
- ``/api/xr/{device}``: the page's WebSocket. The handshake needs the session cookie of an
  operator or admin, a browser ``Origin`` that is this server's own (required: this route moves a
  robot) and the session's CSRF token offered as the ``csrf.<token>`` subprotocol beside
  ``telerig-xr.v1`` (a page of another site can send neither). Each binary message is checked
  against the wire format (:func:`telerig.devices.webxr.protocol.decode`) and a rate limit; a bad
  one is dropped and counted (``drop_<reason>``), a good one goes unchanged, in a relay envelope
  (:mod:`telerig.devices.webxr.relay`, stamped with the time this server received it), to the
  device over the rig's bus (its ``page_in`` topic,
  which only this server's ``web`` principal may publish). The device's clock pings and closes come
  back on ``page_out``. The login is checked again every 10 s: a logout or a disabled user ends the
  stream. Connections and their counts go to the audit log.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib.resources
import logging
import secrets
import threading
import time
from collections import Counter
from typing import Annotated, Any

from fastapi import APIRouter, Depends, FastAPI, HTTPException, Request, Response, WebSocket, status
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import RedirectResponse
from pydantic import BaseModel, ConfigDict
from starlette.websockets import WebSocketDisconnect

from telerig.devices.webxr.config import WebXRConfig
from telerig.devices.webxr.protocol import Pong, WebXRWireError, decode
from telerig.devices.webxr.relay import (
    CLOSE,
    MAX_PAGE_MESSAGE,
    MESSAGE,
    OPEN,
    PAGE_SUBPROTOCOL,
    STAMPED,
    decode_event,
    encode_event,
    open_body,
    parse_close,
    stamped_body,
)
from telerig.errors import BusError
from telerig.server.accounts import AccountStore, LoginSession
from telerig.server.auth import (
    COOKIE,
    PAGE_HEADERS,
    RECHECK_S,
    TokenBucket,
    client_address,
    page_socket_session,
    refuse,
    require,
    websocket_session,
)
from telerig.server.gateway import RigGateway

__all__ = ["MAX_RATE_HZ", "PageRelay", "router"]

log = logging.getLogger("telerig.server")

#: Most messages a page may send per second (frames and pongs; a headset renders at 72-120 Hz,
#: the desktop page sends 60 Hz), with bursts of :data:`_BURST`; beyond, they are dropped (``drop_rate``).
MAX_RATE_HZ = 200.0
_BURST = 50.0
#: WebSocket close code "try again later" (RFC 6455 1013): the rig's broker is not reachable.
_TRY_AGAIN = 1013
#: Messages from the device waiting to go to one page; beyond, they are dropped (pings: harmless).
_OUTBOX = 64
_STATIC = importlib.resources.files("telerig.devices.webxr") / "static"
#: The page's files (a fixed list: no path from a request reaches the file system).
_FILES = {
    "telerig-xr.js": "text/javascript; charset=utf-8",
    "telerig-xr.css": "text/css; charset=utf-8",
}

router = APIRouter(tags=["xr"])


class XRDeviceOut(BaseModel):
    """A WebXR device of the rig: its takeover policy, the pages this server relays to it now, and
    what it relayed or dropped (``frames``, ``pongs``, ``connections``, ``drop_<reason>``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    device: str
    takeover: str
    pages: int
    counters: dict[str, int]


class _Problem(BaseModel):
    detail: str


_ERRORS: dict[int | str, dict[str, Any]] = {
    401: {"model": _Problem, "description": "not logged in"},
    403: {"model": _Problem, "description": "missing role"},
}


class PageRelay:
    """This server's side of the relay: its open pages by connection, and counters per device."""

    def __init__(self, gateway: RigGateway) -> None:
        self.gateway = gateway
        self.devices = {d.id: d for d in gateway.rig.devices if isinstance(d, WebXRConfig)}
        self.counters: dict[str, Counter[str]] = {d: Counter() for d in self.devices}
        self._pages: dict[int, tuple[str, asyncio.AbstractEventLoop, asyncio.Queue[tuple[int, bytes]]]] = {}
        self._lock = threading.Lock()
        gateway.set_page_listener(self._from_device)

    def count(self, device: str, key: str, n: int = 1) -> None:
        with self._lock:
            self.counters[device][key] += n

    def pages(self, device: str) -> int:
        with self._lock:
            return sum(1 for d, _, _ in self._pages.values() if d == device)

    def open(self, device: str, conn: int) -> asyncio.Queue[tuple[int, bytes]]:
        outbox: asyncio.Queue[tuple[int, bytes]] = asyncio.Queue(_OUTBOX)
        with self._lock:
            self._pages[conn] = (device, asyncio.get_running_loop(), outbox)
        return outbox

    def close(self, conn: int) -> None:
        with self._lock:
            self._pages.pop(conn, None)

    def _from_device(self, device: str, payload: bytes) -> None:
        """A device's envelope for one of its pages (bus thread)."""
        try:
            event = decode_event(payload)
        except WebXRWireError:
            if device in self.counters:
                self.count(device, "drop_device_relay")
            return
        with self._lock:
            entry = self._pages.get(event.conn)
        if entry is None or entry[0] != device:
            return  # another server's page, or one already gone
        _, loop, outbox = entry

        def put() -> None:
            with contextlib.suppress(asyncio.QueueFull):
                outbox.put_nowait((event.event, event.body))

        with contextlib.suppress(RuntimeError):  # the loop closed: the page is gone with it
            loop.call_soon_threadsafe(put)


def _relay(app: FastAPI) -> PageRelay | None:
    gateway: RigGateway | None = app.state.gateway
    if gateway is None:
        return None
    relay: PageRelay | None = getattr(app.state, "xr_relay", None)
    if relay is None or relay.gateway is not gateway:
        relay = app.state.xr_relay = PageRelay(gateway)
    return relay


@router.get("/xr", include_in_schema=False, response_model=None)
def xr_page(request: Request) -> Response:
    """The WebXR page: log in first; viewers may not drive a robot."""
    accounts: AccountStore = request.app.state.accounts
    session = accounts.session(request.cookies.get(COOKIE, ""))
    if session is None:
        return RedirectResponse("/login", status_code=303)
    if not session.user.may("operator"):
        raise HTTPException(
            status.HTTP_403_FORBIDDEN, "the WebXR page moves a robot: it needs the operator role"
        )
    return Response((_STATIC / "index.html").read_bytes(), media_type="text/html", headers=PAGE_HEADERS)


@router.get("/xr/{name}", include_in_schema=False)
def xr_asset(name: str) -> Response:
    media_type = _FILES.get(name)
    if media_type is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, "no such file")
    return Response((_STATIC / name).read_bytes(), media_type=media_type, headers=PAGE_HEADERS)


@router.get("/api/xr", response_model=list[XRDeviceOut], responses=_ERRORS)
def xr_devices(request: Request, _: Annotated[LoginSession, Depends(require("viewer"))]) -> list[XRDeviceOut]:
    """The rig's WebXR devices, the pages this server relays to each now and its relay counters
    (empty without a rig)."""
    relay = _relay(request.app)
    if relay is None:
        return []
    with relay._lock:
        counters = {d: dict(c) for d, c in relay.counters.items()}
    return [
        XRDeviceOut(device=d, takeover=c.takeover, pages=relay.pages(d), counters=counters[d])
        for d, c in relay.devices.items()
    ]


@router.websocket("/api/xr/{device}")
async def xr_stream(websocket: WebSocket, device: str) -> None:
    """A logged-in operator's page streaming poses to ``device`` (see the module docs)."""
    session = await page_socket_session(websocket, PAGE_SUBPROTOCOL, role="operator")
    if session is None:
        return
    relay = _relay(websocket.app)
    if relay is None:
        await websocket.close(code=status.WS_1011_INTERNAL_ERROR, reason="this server watches no rig")
        return
    if device not in relay.devices:
        await refuse(websocket, f"no WebXR device {device[:40]!r} in rig {relay.gateway.name!r}")
        return
    await websocket.accept(subprotocol=PAGE_SUBPROTOCOL)
    if not relay.gateway.connected:  # told after the accept: a refused handshake shows no reason
        await websocket.close(code=_TRY_AGAIN, reason="the rig is not running or not reachable; retrying")
        return
    await _stream(websocket, relay, device, session)


async def _stream(websocket: WebSocket, relay: PageRelay, device: str, session: LoginSession) -> None:
    accounts: AccountStore = websocket.app.state.accounts
    client = client_address(websocket)
    conn = secrets.randbits(64)
    outbox = relay.open(device, conn)
    seen: Counter[str] = Counter()
    target = f"{relay.gateway.name}/{device}"

    def send(event: int, body: bytes = b"") -> bool:
        try:
            relay.gateway.send_page(device, encode_event(event, conn, body))
        except BusError:
            return False
        return True

    def count(key: str) -> None:
        seen[key] += 1
        relay.count(device, key)

    await run_in_threadpool(
        accounts.audit, "xr_connect", user=session.user.name, target=target, client=client
    )
    count("connections")
    send(OPEN, open_body(session.user.name, client))
    writer = asyncio.create_task(_from_device(websocket, outbox))
    bucket = TokenBucket(MAX_RATE_HZ, _BURST)
    loop = asyncio.get_running_loop()
    checked = loop.time()
    try:
        while not writer.done():
            message = await websocket.receive()
            received_ns = time.time_ns()  # where the frame reached telerig (its ``receive`` stage)
            if message["type"] == "websocket.disconnect":
                break
            if loop.time() - checked > RECHECK_S:
                checked = loop.time()
                if await websocket_session(websocket) is None:
                    await refuse(websocket, "logged out")
                    break
            data = message.get("bytes")
            if data is None:
                count("drop_text")
                continue
            if len(data) > MAX_PAGE_MESSAGE:
                count("drop_size")
                continue
            if not bucket.take():
                count("drop_rate")
                continue
            try:
                msg = decode(data)
            except WebXRWireError as exc:
                count(f"drop_{exc.reason}")
                continue
            if send(STAMPED, stamped_body(received_ns, data)):
                count("pongs" if isinstance(msg, Pong) else "frames")
            else:
                count("drop_offline")
    except (WebSocketDisconnect, RuntimeError):
        pass  # the page went away (RuntimeError: receiving on a socket starlette saw closed)
    finally:
        writer.cancel()
        relay.close(conn)
        send(CLOSE)
    detail = ", ".join(f"{k} {v}" for k, v in sorted(seen.items()))
    await run_in_threadpool(
        accounts.audit, "xr_disconnect", user=session.user.name, target=target, detail=detail, client=client
    )


async def _from_device(websocket: WebSocket, outbox: asyncio.Queue[tuple[int, bytes]]) -> None:
    """The device's pings to the page; its close closes the page's WebSocket."""
    with contextlib.suppress(WebSocketDisconnect, RuntimeError):
        while True:
            event, body = await outbox.get()
            if event == MESSAGE:
                await websocket.send_bytes(body)
            elif event == CLOSE:
                code, reason = parse_close(body)
                await websocket.close(code=code, reason=reason)
                return
