"""The pages' latency reports: which joint state or camera preview they drew, and when.

- ``/api/latency``: a logged-in page's WebSocket (any role: it moves nothing, but what it reports is
  recorded, so the handshake is the WebXR relay's: the session cookie, this server's own
  ``Origin``, and the login's CSRF token offered as ``csrf.<token>`` beside ``telerig-latency.v1``).
  Text messages of at most :data:`MAX_MESSAGE` bytes, JSON objects:

  ==============================================================  ================================
  page → server                                                   meaning
  ==============================================================  ================================
  ``{"t": "sync", "id": n, "page_ms": p}``                        answer to the server's ``sync``
  ``{"t": "rendered", "robot": id, "stamp": ns, "page_ms": p}``   drew the joint state ``stamp``
  ``{"t": "displayed", "camera": id, "stamp": ns, "page_ms": p}`` drew the preview captured then
  ==============================================================  ================================

  The server sends ``{"t": "sync", "id": n}`` when the page connects and every
  :data:`SYNC_PERIOD_S`; the answers map the page's clock (``page_ms``: ``performance.timeOrigin +
  performance.now()``) to the server's (:class:`~telerig.server.view_latency.ClockMap`). ``stamp``
  is the state's or frame's capture time [ns] as a decimal string (a JavaScript number loses the
  last digits) or a number. Anything else (binary, oversized, not JSON, an unknown ``t``, a missing
  or wrong field, a node the rig does not have, a stamp too old or ahead, a report before the first
  clock exchange, faster than :data:`MAX_RATE_HZ`) is dropped and counted by reason, and the
  connection goes on.
- ``GET /api/latency``: those counters and the current browser-stage reports of every robot and
  camera.
- ``GET /static/latency.js``: the page's side (an ES module, ``connectLatency``).
"""

from __future__ import annotations

import asyncio
import json
from typing import Annotated, Any

from fastapi import APIRouter, Depends, HTTPException, Request, WebSocket, status
from pydantic import BaseModel, ConfigDict, JsonValue
from starlette.websockets import WebSocketDisconnect

from telerig.server.accounts import LoginSession
from telerig.server.auth import (
    RECHECK_S,
    TokenBucket,
    page_socket_session,
    refuse,
    require,
    websocket_session,
)
from telerig.server.gateway import RigGateway
from telerig.server.view_latency import ClockMap, ViewLatency, finite_ms

__all__ = ["MAX_MESSAGE", "MAX_RATE_HZ", "SUBPROTOCOL", "SYNC_PERIOD_S", "router"]

#: WebSocket subprotocol of the reports; the page also offers ``csrf.<token>``.
SUBPROTOCOL = "telerig-latency.v1"
#: Largest report [bytes]: the longest valid one is ~130.
MAX_MESSAGE = 512
#: Most reports a page may send per second (a 120 Hz display drawing every robot and camera), with
#: bursts of :data:`_BURST`; beyond, they are dropped (``drop_rate``).
MAX_RATE_HZ = 400.0
_BURST = 100.0
#: How often the server starts a clock exchange [s].
SYNC_PERIOD_S = 1.0
_PENDING = 8  # clock exchanges awaiting the page's answer

router = APIRouter(tags=["latency"])


class ViewLatencyOut(BaseModel):
    """The browser stages (``reports``: each robot's and camera's ``latency_view`` document) and what
    the pages' reports did (``counters``: ``rendered``, ``displayed``, ``sync``, ``drop_<reason>``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    counters: dict[str, int]
    reports: list[dict[str, JsonValue]]


class _Problem(BaseModel):
    detail: str


def _view(request: Request | WebSocket) -> ViewLatency | None:
    gateway: RigGateway | None = request.app.state.gateway
    return None if gateway is None else gateway.view


@router.get(
    "/api/latency",
    response_model=ViewLatencyOut,
    responses={401: {"model": _Problem}, 403: {"model": _Problem}, 503: {"model": _Problem}},
)
def view_latency(request: Request, _: Annotated[LoginSession, Depends(require("viewer"))]) -> ViewLatencyOut:
    """The browser stages of the watched rig and the pages' report counters."""
    view = _view(request)
    if view is None:
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, "this server watches no rig (--rig)")
    now = view.now_ns()
    reports = [view.report(n, now) for n in (*view.robots, *view.cameras)]
    return ViewLatencyOut(
        counters=view.counts(), reports=[json.loads(json.dumps(r)) for r in reports if r is not None]
    )


@router.websocket("/api/latency")
async def latency_reports(websocket: WebSocket) -> None:
    """A logged-in page reporting what it drew (see the module docs)."""
    if await page_socket_session(websocket, SUBPROTOCOL) is None:
        return
    view = _view(websocket)
    if view is None:
        await websocket.close(code=status.WS_1011_INTERNAL_ERROR, reason="this server watches no rig")
        return
    await websocket.accept(subprotocol=SUBPROTOCOL)
    clock = ClockMap()
    pending: dict[int, int] = {}  # exchange id -> server time sent [ns]
    syncer = asyncio.create_task(_sync(websocket, view, pending))
    bucket = TokenBucket(MAX_RATE_HZ, _BURST)
    loop = asyncio.get_running_loop()
    checked = loop.time()
    try:
        while not syncer.done():
            message = await websocket.receive()
            if message["type"] == "websocket.disconnect":
                break
            if loop.time() - checked > RECHECK_S:
                checked = loop.time()
                if await websocket_session(websocket) is None:
                    await refuse(websocket, "logged out")
                    break
            reason = _take(message, view, clock, pending, bucket)
            if reason is not None:
                view.count(f"drop_{reason}")
    except (WebSocketDisconnect, RuntimeError):
        pass  # the page went away
    finally:
        syncer.cancel()


async def _sync(websocket: WebSocket, view: ViewLatency, pending: dict[int, int]) -> None:
    """Start a clock exchange now and every :data:`SYNC_PERIOD_S`."""
    n = 0
    try:
        while True:
            n += 1
            pending[n] = view.now_ns()
            pending.pop(n - _PENDING, None)
            await websocket.send_text(json.dumps({"t": "sync", "id": n}))
            await asyncio.sleep(SYNC_PERIOD_S)
    except (WebSocketDisconnect, RuntimeError):
        return


def _take(
    message: Any, view: ViewLatency, clock: ClockMap, pending: dict[int, int], bucket: TokenBucket
) -> str | None:
    """Handle one page message; returns the drop reason, ``None`` when it was taken (or counted by
    :class:`ViewLatency` itself)."""
    text = message.get("text")
    if text is None:
        return "binary"
    if len(text) > MAX_MESSAGE:
        return "size"
    if not bucket.take():
        return "rate"
    try:
        doc = json.loads(text)
    except ValueError:
        return "json"
    if not isinstance(doc, dict):
        return "json"
    kind = doc.get("t")
    page_ms = finite_ms(doc.get("page_ms"))
    if kind == "sync":
        sent = pending.pop(doc["id"], None) if isinstance(doc.get("id"), int) else None
        if sent is None or page_ms is None:
            return "field"
        clock.add(sent, page_ms, view.now_ns())
        view.count("sync")
        return None
    if kind not in ("rendered", "displayed"):
        return "type"
    node = doc.get("robot" if kind == "rendered" else "camera")
    stamp = _stamp(doc.get("stamp"))
    if not isinstance(node, str) or stamp is None or page_ms is None:
        return "field"
    if not clock.synced:
        return "unsynced"
    drawn = clock.to_server_ns(page_ms)
    if kind == "rendered":
        view.rendered(node[:64], stamp, drawn)
    else:
        view.displayed(node[:64], stamp, drawn)
    return None


def _stamp(value: object) -> int | None:
    """A capture stamp [ns]: a decimal string of at most 19 digits or a positive finite number."""
    if isinstance(value, str):
        return int(value) if value.isascii() and value.isdigit() and len(value) <= 19 else None
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return int(value) if 0 < value < 2**63 else None  # NaN and infinities fail the comparison
