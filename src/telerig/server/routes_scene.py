"""The operator scene: a three.js view of the rig's robots, live, behind the control center's login.

- ``GET /scene``: the page (any logged-in user; the login page otherwise). It draws each robot
  from its shared model with the measured joint states, the operator's hand or controller, the
  commanded target, the camera previews, and the live aids (motion scale, virtual fixture, hand to
  end-effector distance, reachability, safety status). See ``static/scene.js``.
- ``GET /scene/{file}``: the page's script and style, and three.js from ``node_modules`` (installed
  by ``make scene-js`` with ``npm ci`` from the committed ``package-lock.json``; nothing is fetched
  at run time; without it the page answers 503 naming the make target).
- ``/api/scene``: the page's WebSocket. The handshake needs the session cookie, this server's own
  ``Origin`` (required) and the session's CSRF token offered as the ``csrf.<token>`` subprotocol
  beside ``telerig-scene.v1``. The server sends ``{"type": "scene", ...}`` once (geometry), then
  ``{"type": "state", ...}`` at most :data:`~telerig.server.scene.SCENE_HZ` times a second when
  it changed (and every second regardless). The page sends nothing the server acts on: whatever
  it receives is read, counted and dropped. The login is checked again every 10 s.
"""

from __future__ import annotations

import asyncio
import base64
import hashlib
import json
import os
from collections import Counter
from pathlib import Path

from fastapi import APIRouter, FastAPI, HTTPException, Request, Response, WebSocket, status
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import RedirectResponse
from starlette.websockets import WebSocketDisconnect

from telerig.server.accounts import AccountStore
from telerig.server.auth import (
    COOKIE,
    PAGE_HEADERS,
    RECHECK_S,
    page_socket_session,
    refuse,
    websocket_session,
)
from telerig.server.gateway import RigGateway
from telerig.server.scene import SCENE_HZ, SceneHub

__all__ = ["SCENE_SUBPROTOCOL", "node_modules", "router"]

#: The page's WebSocket subprotocol (offered with ``csrf.<token>``).
SCENE_SUBPROTOCOL = "telerig-scene.v1"
#: The make target that installs three.js (named in the error when it is missing).
MAKE_TARGET = "make scene-js"
_STATIC = Path(__file__).parent / "static"
_REFRESH_S = 1.0
#: The page's own files, and three.js's files by the path they have under ``node_modules``.
_OWN = {"scene.js": "text/javascript; charset=utf-8", "scene.css": "text/css; charset=utf-8"}
_THREE = {
    "three.module.js": "three/build/three.module.js",
    "three.core.js": "three/build/three.core.js",
    "OrbitControls.js": "three/examples/jsm/controls/OrbitControls.js",
}
#: The import map (inline, allowed by its hash in the page's Content-Security-Policy).
_IMPORTMAP = '{"imports": {"three": "/scene/three.module.js"}}'

router = APIRouter(tags=["scene"])


def node_modules() -> Path:
    """Where ``npm ci`` put three.js: ``$TELERIG_NODE_MODULES``, or the repository's ``node_modules``."""
    env = os.environ.get("TELERIG_NODE_MODULES")
    return Path(env) if env else Path(__file__).resolve().parents[3] / "node_modules"


def _missing() -> str | None:
    """Why three.js cannot be served (one line), or ``None``."""
    root = node_modules()
    if all((root / path).is_file() for path in _THREE.values()):
        return None
    return f"three.js is not installed in {root}: run `{MAKE_TARGET}` (npm ci from package-lock.json)"


def _page_headers() -> dict[str, str]:
    digest = base64.b64encode(hashlib.sha256(_IMPORTMAP.encode()).digest()).decode()
    csp = PAGE_HEADERS["Content-Security-Policy"] + f"; script-src 'self' 'sha256-{digest}'"
    return {**PAGE_HEADERS, "Content-Security-Policy": csp}


@router.get("/scene", include_in_schema=False, response_model=None)
def scene_page(request: Request) -> Response:
    """The operator scene (log in first)."""
    accounts: AccountStore = request.app.state.accounts
    if accounts.session(request.cookies.get(COOKIE, "")) is None:
        return RedirectResponse("/login", status_code=303)
    missing = _missing()
    if missing is not None:
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, missing)
    html = (_STATIC / "scene.html").read_text().replace("{{IMPORTMAP}}", _IMPORTMAP)
    return Response(html, media_type="text/html; charset=utf-8", headers=_page_headers())


@router.get("/scene/{name}", include_in_schema=False)
def scene_asset(name: str) -> Response:
    """The page's script and style, and three.js (a fixed list: no request path reaches the disk)."""
    if name in _OWN:
        return Response((_STATIC / name).read_bytes(), media_type=_OWN[name], headers=PAGE_HEADERS)
    if name not in _THREE:
        raise HTTPException(status.HTTP_404_NOT_FOUND, "no such file")
    missing = _missing()
    if missing is not None:
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, missing)
    body = (node_modules() / _THREE[name]).read_bytes()
    return Response(body, media_type="text/javascript; charset=utf-8", headers=PAGE_HEADERS)


def _hub(app: FastAPI) -> SceneHub | None:
    gateway: RigGateway | None = app.state.gateway
    if gateway is None:
        return None
    hub: SceneHub | None = getattr(app.state, "scene_hub", None)
    if hub is None or hub.gateway is not gateway:
        hub = app.state.scene_hub = SceneHub(gateway)
    return hub


@router.websocket("/api/scene")
async def scene_stream(websocket: WebSocket) -> None:
    """The scene's geometry once, then its state at a bounded rate (see the module docs)."""
    if await page_socket_session(websocket, SCENE_SUBPROTOCOL) is None:
        return
    hub = _hub(websocket.app)
    if hub is None:
        await websocket.close(code=status.WS_1011_INTERNAL_ERROR, reason="this server watches no rig")
        return
    await websocket.accept(subprotocol=SCENE_SUBPROTOCOL)
    received: Counter[str] = Counter()
    reader = asyncio.create_task(_drain(websocket, received))
    try:
        await run_in_threadpool(hub.start)  # the first client builds the geometry (seconds)
        await websocket.send_text(json.dumps(hub.document(), allow_nan=False))
        await _feed(websocket, hub, reader)
    except (WebSocketDisconnect, RuntimeError):
        pass  # the page went away (RuntimeError: sending on a socket starlette saw closed)
    finally:
        reader.cancel()


async def _drain(websocket: WebSocket, received: Counter[str]) -> None:
    """Read and drop what the page sends (counted by kind); ends when it disconnects."""
    try:
        while True:
            message = await websocket.receive()
            if message["type"] == "websocket.disconnect":
                return
            received["bytes" if message.get("bytes") is not None else "text"] += 1
    except (WebSocketDisconnect, RuntimeError):
        return


async def _feed(websocket: WebSocket, hub: SceneHub, reader: asyncio.Task[None]) -> None:
    loop = asyncio.get_running_loop()
    checked = sent_at = next_at = loop.time()
    last: object = -1
    while not reader.done():
        now = loop.time()
        if now - checked > RECHECK_S:
            checked = now
            if await websocket_session(websocket) is None:
                await refuse(websocket, "logged out")
                return
        state = await run_in_threadpool(hub.state)
        if state["seq"] != last or now - sent_at >= _REFRESH_S:  # something arrived, or a refresh of the ages
            last, sent_at = state["seq"], now
            await websocket.send_text(json.dumps(state, allow_nan=False))
        next_at = max(next_at + 1.0 / SCENE_HZ, loop.time())  # a steady rate; a late tick is not caught up
        await asyncio.sleep(next_at - loop.time())
