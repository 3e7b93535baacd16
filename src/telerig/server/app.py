"""The control center's web application (FastAPI): accounts, audit log and the pages.

Every ``/api`` route except ``POST /api/login`` needs a session; state-changing routes also need
the session's CSRF token and the role they name. :func:`create_app` has no side effects beyond
building the app: the account database is opened by the caller (``telerig serve``, the tests).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated, Literal

from fastapi import Body, Depends, FastAPI, HTTPException, Query, Request, Response, status
from fastapi.responses import FileResponse, JSONResponse, RedirectResponse
from pydantic import BaseModel, ConfigDict, Field

from telerig import __version__
from telerig.server import routes_live, routes_scene, routes_voice, routes_xr
from telerig.server.accounts import AccountError, AccountStore, LoginSession, Role
from telerig.server.auth import COOKIE, PAGE_HEADERS, LoginLimiter, client_address, require
from telerig.server.gateway import RigGateway
from telerig.server.routes_devices import router as devices_router
from telerig.server.routes_episodes import episodes_router
from telerig.server.routes_latency import router as latency_router
from telerig.server.routes_review import review_router

__all__ = ["create_app"]

_log = logging.getLogger("telerig.server")
_STATIC = Path(__file__).parent / "static"


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class LoginRequest(_Model):
    """A login: user name and password."""

    user: str = Field(min_length=1, max_length=64)
    password: str = Field(min_length=1, max_length=1024)


class Me(_Model):
    """The logged-in user, and the CSRF token its state-changing requests must send."""

    user: str
    role: Role
    csrf: str


class UserOut(_Model):
    """A user as the admin pages list it."""

    name: str
    role: Role
    created_ns: int
    disabled: bool


class NewUser(_Model):
    """A user to create."""

    name: str = Field(min_length=2, max_length=32)
    role: Role
    password: str = Field(min_length=12, max_length=1024)


class UserChange(_Model):
    """A change to a user: its role, or disabling it (both optional)."""

    role: Role | None = None
    disabled: Literal[True] | None = None


class AuditOut(_Model):
    """One audit log entry."""

    seq: int
    t_ns: int
    user: str | None
    action: str
    target: str
    detail: str
    client: str


class Problem(_Model):
    """An error: ``detail`` says what is wrong and what to do."""

    detail: str


_ERRORS: dict[int | str, dict[str, object]] = {
    401: {"model": Problem, "description": "not logged in"},
    403: {"model": Problem, "description": "missing role or CSRF token"},
}


def create_app(
    accounts: AccountStore,
    *,
    limiter: LoginLimiter | None = None,
    gateway: RigGateway | None = None,
    data_root: Path | None = None,
) -> FastAPI:
    """The web application over an open account store; ``gateway``: the running rig it watches and
    commands (its routes answer 503 without one)."""
    app = FastAPI(
        title="telerig control center",
        version=__version__,
        description="Operators, devices, sessions, live monitoring and episodes of a telerig lab.",
        docs_url=None,
        redoc_url=None,
    )
    app.state.accounts = accounts
    app.state.limiter = limiter or LoginLimiter()
    if data_root is not None:  # the episode browser and its jobs (exports, quality checks)
        app.include_router(episodes_router(data_root))
        app.include_router(review_router(data_root))  # segment review (<data root>/processed)
    app.state.gateway = gateway
    app.include_router(routes_live.router)
    app.include_router(latency_router)  # the pages' reports of what they drew (latency stages)
    app.include_router(routes_xr.router)  # the operator's WebXR page and its pose relay
    app.include_router(routes_voice.router)  # voice grammar commands typed in the UI (telerig.voice)
    app.include_router(routes_scene.router)  # the operator's 3D scene (/scene) and its state feed
    app.include_router(devices_router)  # device registration (app.state.devices: telerig serve --rig)
    _add_auth_routes(app)
    _add_admin_routes(app)
    _add_pages(app)
    return app


def _add_auth_routes(app: FastAPI) -> None:
    @app.post(
        "/api/login",
        response_model=Me,
        responses={401: {"model": Problem}, 403: {"model": Problem}, 429: {"model": Problem}},
        tags=["auth"],
    )
    def login(body: LoginRequest, request: Request, response: Response) -> Me:
        """Log in: sets the session cookie and returns the CSRF token."""
        origin = request.headers.get("origin")
        if origin is not None and origin != f"{request.url.scheme}://{request.url.netloc}":
            raise HTTPException(status.HTTP_403_FORBIDDEN, "login from another site is refused")
        accounts: AccountStore = request.app.state.accounts
        limiter: LoginLimiter = request.app.state.limiter
        client = client_address(request)
        keys = (f"addr:{client}", f"user:{body.user.lower()}")
        wait = limiter.retry_after(*keys)
        if wait > 0:
            accounts.audit("login_throttled", user=None, target=body.user[:32], client=client)
            raise HTTPException(
                status.HTTP_429_TOO_MANY_REQUESTS,
                f"too many failed logins; try again in {wait:.0f} s",
                headers={"Retry-After": str(max(1, round(wait)))},
            )
        try:
            session = accounts.login(body.user, body.password)
        except AccountError as exc:
            limiter.failed(*keys)
            accounts.audit("login_failed", user=None, target=body.user[:32], client=client)
            raise HTTPException(status.HTTP_401_UNAUTHORIZED, str(exc)) from None
        limiter.succeeded(*keys)
        accounts.audit("login", user=session.user.name, client=client)
        response.set_cookie(
            COOKIE,
            session.token,
            httponly=True,
            samesite="strict",
            secure=request.url.scheme == "https",
            path="/",
        )
        return Me(user=session.user.name, role=session.user.role, csrf=session.csrf)

    @app.post("/api/logout", status_code=204, responses=_ERRORS, tags=["auth"])
    def logout(request: Request, session: Annotated[LoginSession, Depends(require("viewer"))]) -> Response:
        """End this session."""
        accounts: AccountStore = request.app.state.accounts
        accounts.logout(request.cookies.get(COOKIE, ""))
        accounts.audit("logout", user=session.user.name, client=client_address(request))
        response = Response(status_code=204)
        response.delete_cookie(COOKIE, path="/")
        return response

    @app.get("/api/me", response_model=Me, responses=_ERRORS, tags=["auth"])
    def me(session: Annotated[LoginSession, Depends(require("viewer"))]) -> Me:
        """Who is logged in, and the CSRF token."""
        return Me(user=session.user.name, role=session.user.role, csrf=session.csrf)


def _add_admin_routes(app: FastAPI) -> None:
    @app.get("/api/users", response_model=list[UserOut], responses=_ERRORS, tags=["admin"])
    def users(request: Request, _: Annotated[LoginSession, Depends(require("admin"))]) -> list[UserOut]:
        """Every user."""
        accounts: AccountStore = request.app.state.accounts
        return [
            UserOut(name=u.name, role=u.role, created_ns=u.created_ns, disabled=u.disabled)
            for u in accounts.users()
        ]

    @app.post(
        "/api/users",
        response_model=UserOut,
        status_code=201,
        responses={**_ERRORS, 409: {"model": Problem}},
        tags=["admin"],
    )
    def add_user(
        body: NewUser, request: Request, session: Annotated[LoginSession, Depends(require("admin"))]
    ) -> UserOut:
        """Create a user."""
        accounts: AccountStore = request.app.state.accounts
        try:
            user = accounts.add_user(body.name, body.role, body.password)
        except AccountError as exc:
            raise HTTPException(status.HTTP_409_CONFLICT, str(exc)) from None
        accounts.audit(
            "user_added",
            user=session.user.name,
            target=user.name,
            detail=user.role,
            client=client_address(request),
        )
        return UserOut(name=user.name, role=user.role, created_ns=user.created_ns, disabled=user.disabled)

    @app.patch(
        "/api/users/{name}",
        response_model=UserOut,
        responses={**_ERRORS, 409: {"model": Problem}},
        tags=["admin"],
    )
    def change_user(
        name: str,
        request: Request,
        session: Annotated[LoginSession, Depends(require("admin"))],
        body: Annotated[UserChange, Body()],
    ) -> UserOut:
        """Change a user's role or disable it."""
        accounts: AccountStore = request.app.state.accounts
        try:
            if body.role is not None:
                accounts.set_role(name, body.role)
            if body.disabled:
                accounts.disable(name)
            user = accounts.user(name)
        except AccountError as exc:
            raise HTTPException(status.HTTP_409_CONFLICT, str(exc)) from None
        accounts.audit(
            "user_changed",
            user=session.user.name,
            target=name,
            detail=body.model_dump_json(exclude_none=True),
            client=client_address(request),
        )
        return UserOut(name=user.name, role=user.role, created_ns=user.created_ns, disabled=user.disabled)

    @app.get("/api/audit", response_model=list[AuditOut], responses=_ERRORS, tags=["admin"])
    def audit(
        request: Request,
        _: Annotated[LoginSession, Depends(require("admin"))],
        limit: Annotated[int, Query(ge=1, le=1000)] = 200,
        before: Annotated[int | None, Query(ge=1, le=2**63 - 1)] = None,
    ) -> list[AuditOut]:
        """The audit log, newest first (``before``: page back from this sequence number)."""
        accounts: AccountStore = request.app.state.accounts
        entries = accounts.audit_log(limit=limit, before_seq=before)
        return [AuditOut(**{f: getattr(e, f) for f in AuditOut.model_fields}) for e in entries]


def _add_pages(app: FastAPI) -> None:
    @app.get("/", include_in_schema=False, response_model=None)
    def index(request: Request) -> Response:
        accounts: AccountStore = request.app.state.accounts
        if accounts.session(request.cookies.get(COOKIE, "")) is None:
            return RedirectResponse("/login", status_code=303)
        return FileResponse(_STATIC / "index.html", headers=PAGE_HEADERS)

    @app.get("/login", include_in_schema=False)
    def login_page() -> FileResponse:
        return FileResponse(_STATIC / "login.html", headers=PAGE_HEADERS)

    @app.get("/static/{name}", include_in_schema=False)
    def static(name: str) -> FileResponse:
        if name not in _ASSETS:
            raise HTTPException(status.HTTP_404_NOT_FOUND, "no such file")
        return FileResponse(_STATIC / name, headers=PAGE_HEADERS)

    @app.exception_handler(HTTPException)
    def problem(_: Request, exc: HTTPException) -> JSONResponse:
        return JSONResponse({"detail": exc.detail}, status_code=exc.status_code, headers=exc.headers)


#: Files the pages load (a fixed list: no path from a request reaches the file system).
_ASSETS = frozenset({"api.js", "app.js", "login.js", "style.css", "latency.js"})
