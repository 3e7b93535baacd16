"""Who is asking: session cookies, CSRF tokens, roles and login rate limiting for the web server.

- The session cookie is ``HttpOnly`` and ``SameSite=Strict`` (``Secure`` over TLS): scripts cannot
  read it and other sites' pages cannot send it.
- Every state-changing request (POST, PUT, PATCH, DELETE) must carry the session's CSRF token in
  the ``X-CSRF-Token`` header (a header a cross-site form cannot set); login itself takes only a
  JSON body (a cross-site form cannot send one without a CORS preflight, which the server refuses)
  and refuses a foreign ``Origin``.
- Failed logins are limited per client address and per user name (a sliding window), so a password
  cannot be guessed at speed from one place or against one account from many.
"""

from __future__ import annotations

import secrets
import threading
import time
from collections import deque
from collections.abc import Callable, Coroutine
from typing import Any

from fastapi import Depends, HTTPException, Request, WebSocket, status
from fastapi.concurrency import run_in_threadpool
from starlette.requests import HTTPConnection

from telerig.server.accounts import AccountStore, LoginSession, Role

__all__ = [
    "COOKIE",
    "CSRF_HEADER",
    "PAGE_HEADERS",
    "RECHECK_S",
    "LoginLimiter",
    "TokenBucket",
    "client_address",
    "csrf_protected",
    "page_socket_session",
    "refuse",
    "require",
    "same_origin",
    "websocket_session",
]

#: Name of the session cookie.
COOKIE = "telerig_session"
#: Header that carries the session's CSRF token on state-changing requests.
CSRF_HEADER = "X-CSRF-Token"
_UNSAFE_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})
#: Headers of every page the server sends: scripts, styles and connections from this server only.
PAGE_HEADERS = {
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data: blob:; connect-src 'self'; "
    "frame-ancestors 'none'",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "same-origin",
    "Cache-Control": "no-store",
}


def client_address(request: HTTPConnection) -> str:
    """The peer's address (proxies are not trusted: a header is the client's word)."""
    return request.client.host if request.client is not None else ""


class LoginLimiter:
    """Failed logins allowed per key (client address, user name) in a sliding window.

    Args:
        failures: Failures allowed in the window before further attempts are refused.
        window_s: Window length [s].
    """

    def __init__(self, failures: int = 5, window_s: float = 60.0) -> None:
        self._failures = failures
        self._window_s = window_s
        self._seen: dict[str, deque[float]] = {}
        self._lock = threading.Lock()

    def retry_after(self, *keys: str) -> float:
        """Seconds until a login may be tried for these keys; 0 when allowed now."""
        now = time.monotonic()
        wait = 0.0
        with self._lock:
            for key in keys:
                seen = self._prune(key, now)
                if len(seen) >= self._failures:
                    wait = max(wait, seen[0] + self._window_s - now)
        return wait

    def failed(self, *keys: str) -> None:
        now = time.monotonic()
        with self._lock:
            for key in keys:
                self._prune(key, now).append(now)
            if len(self._seen) > 10_000:  # a flood of distinct names must not grow memory without bound
                for key in [k for k, v in self._seen.items() if not v]:
                    del self._seen[key]

    def succeeded(self, *keys: str) -> None:
        with self._lock:
            for key in keys:
                self._seen.pop(key, None)

    def _prune(self, key: str, now: float) -> deque[float]:
        seen = self._seen.setdefault(key, deque())
        while seen and seen[0] <= now - self._window_s:
            seen.popleft()
        return seen


def require(role: Role) -> Callable[[Request], Coroutine[Any, Any, LoginSession]]:
    """A FastAPI dependency: the request's session, which must have at least ``role``.

    Unauthenticated requests get 401; a user below ``role`` gets 403; a state-changing request
    without the session's CSRF token gets 403.
    """

    async def dependency(request: Request) -> LoginSession:
        accounts: AccountStore = request.app.state.accounts
        token = request.cookies.get(COOKIE, "")
        session = accounts.session(token) if token else None
        if session is None:
            raise HTTPException(status.HTTP_401_UNAUTHORIZED, "log in first")
        if request.method in _UNSAFE_METHODS and request.headers.get(CSRF_HEADER) != session.csrf:
            raise HTTPException(status.HTTP_403_FORBIDDEN, f"missing or wrong {CSRF_HEADER} header")
        if not session.user.may(role):
            raise HTTPException(status.HTTP_403_FORBIDDEN, f"needs the {role} role")
        return session

    return dependency


def csrf_protected(role: Role) -> Any:
    """``Depends(require(role))``, for route signatures."""
    return Depends(require(role))


def same_origin(websocket: WebSocket, *, required: bool = False) -> bool:
    """Whether a WebSocket handshake's ``Origin`` is this server's own. Browsers always send it;
    without one the cookie alone decides, unless ``required`` (routes that move a robot)."""
    origin = websocket.headers.get("origin")
    if origin is None:
        return not required
    scheme = "https" if websocket.url.scheme == "wss" else "http"
    return origin == f"{scheme}://{websocket.url.netloc}"


async def websocket_session(websocket: WebSocket) -> LoginSession | None:
    """The login session of a WebSocket handshake's cookie (``None``: none, expired or disabled)."""
    accounts: AccountStore = websocket.app.state.accounts
    token = websocket.cookies.get(COOKIE, "")
    if not token:
        return None
    session: LoginSession | None = await run_in_threadpool(accounts.session, token)
    return session if session is not None and session.user.may("viewer") else None


#: How often a page WebSocket checks its login again (a logout or a disabled account ends it) [s].
RECHECK_S = 10.0


async def refuse(websocket: WebSocket, reason: str) -> None:
    """Close a WebSocket handshake as a policy violation (1008) with ``reason`` (one line)."""
    await websocket.close(code=status.WS_1008_POLICY_VIOLATION, reason=reason)


async def page_socket_session(
    websocket: WebSocket, subprotocol: str, *, role: Role = "viewer"
) -> LoginSession | None:
    """The one handshake check of a page's WebSocket that carries commands or reports: this
    server's own ``Origin`` (required: browsers always send it), a login cookie of ``role`` or
    above, and the login's CSRF token offered as a ``csrf.<token>`` subprotocol beside
    ``subprotocol`` (a browser WebSocket cannot set headers). On refusal the handshake is closed
    (1008, with the reason) and ``None`` returned; otherwise the route accepts it with
    ``subprotocol`` once its own checks pass.
    """
    if not same_origin(websocket, required=True):
        await refuse(websocket, "foreign or missing origin")
        return None
    session = await websocket_session(websocket)
    if session is None:
        await refuse(websocket, "log in first")
        return None
    if not session.user.may(role):
        await refuse(websocket, f"needs the {role} role")
        return None
    # One header may list several (uvicorn's sans-I/O implementation does not split them).
    offered = [p.strip() for value in websocket.scope.get("subprotocols", []) for p in value.split(",")]
    if subprotocol not in offered or not any(
        secrets.compare_digest(p, f"csrf.{session.csrf}") for p in offered if p.startswith("csrf.")
    ):
        await refuse(websocket, "missing or wrong CSRF token")
        return None
    return session


class TokenBucket:
    """At most ``rate_hz`` events a second on average, in bursts of up to ``burst`` (a page's messages).

    Args:
        rate_hz: Refill rate [1/s].
        burst: Bucket size [events].
    """

    def __init__(self, rate_hz: float, burst: float) -> None:
        self._rate = rate_hz
        self._burst = burst
        self.tokens = burst
        self.at = time.monotonic()

    def take(self) -> bool:
        """Spend one token; ``False`` (spend nothing) when the bucket is empty."""
        now = time.monotonic()
        self.tokens = min(self._burst, self.tokens + (now - self.at) * self._rate)
        self.at = now
        if self.tokens < 1.0:
            return False
        self.tokens -= 1.0
        return True
