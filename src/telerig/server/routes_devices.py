"""Device registration routes: list (any login), register and revoke (admin, CSRF header, audited).

The registry is ``app.state.devices`` (a :class:`~telerig.server.devices.DeviceRegistry`, set by
``telerig serve``); without one the routes answer 503. ``POST /api/devices`` is the only reply that
ever carries a device's password (``Cache-Control: no-store``); the audit log records who
registered or revoked which principal, never the password.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated, Literal

from fastapi import APIRouter, Depends, HTTPException, Query, Request, Response, status
from fastapi import Path as PathParam
from fastapi.responses import FileResponse, RedirectResponse
from pydantic import BaseModel, ConfigDict, Field

from telerig.server.accounts import AccountStore, LoginSession
from telerig.server.auth import COOKIE, client_address, require
from telerig.server.devices import (
    DeviceError,
    DeviceKind,
    DeviceRegistry,
    Registration,
    ReloadResult,
    UnknownRegistrationError,
)

__all__ = ["router"]

log = logging.getLogger("telerig.server")

_STATIC = Path(__file__).parent / "static"
#: The rig schema's identifier (rig, device and robot ids).
_ID = r"^[A-Za-z0-9_.\-]+$"
#: A device or robot id: an identifier that does not start with a dot (no ``..`` anywhere near a path).
_DEVICE = r"^[A-Za-z0-9_\-][A-Za-z0-9_.\-]*$"
_PRINCIPAL = r"^(dev|robot)-[A-Za-z0-9_\-][A-Za-z0-9_.\-]{0,63}$"
_PAGE_HEADERS = {
    "Content-Security-Policy": "default-src 'self'; connect-src 'self'; frame-ancestors 'none'",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "same-origin",
    "Cache-Control": "no-store",
}

router = APIRouter(tags=["devices"])


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class DeviceProblem(_Model):
    """An error: ``detail`` says what is wrong and what to do."""

    detail: str


class RegisterRequest(_Model):
    """A device to register: its rig (the only one served when omitted), whether it is an input
    device (``teleoperating``) or a robot (``teleoperated``), and its id in the rig file."""

    rig: str | None = Field(default=None, pattern=_ID, max_length=64)
    kind: DeviceKind
    device: str = Field(pattern=_DEVICE, min_length=1, max_length=64)


class RegisteredDevice(_Model):
    """A registration (never its password)."""

    rig: str
    principal: str = Field(description="its MQTT username")
    kind: DeviceKind
    device: str = Field(description="the input device's or robot's id in the rig file")
    created_ns: int
    created_by: str
    revoked_ns: int | None
    revoked_by: str | None
    active: bool
    publishes: list[str] = Field(description="topic filters the broker's ACL lets it publish on")


class BrokerReload(_Model):
    """What the broker was told after its files changed: ``signalled`` (SIGHUP to the pid in the
    pid file), ``manual`` (reload it yourself; ``detail`` says how), ``embedded`` (the rig embeds
    its broker, which does not read these files) or ``failed``."""

    status: Literal["signalled", "manual", "failed", "embedded"]
    detail: str


class IssuedOut(_Model):
    """A new registration and its MQTT login. The password is shown this once: store it on the
    device; the server keeps only its hash."""

    device: RegisteredDevice
    username: str
    password: str
    broker: BrokerReload


class RevokedOut(_Model):
    """A revoked registration and what the broker was told."""

    device: RegisteredDevice
    broker: BrokerReload


class RigDevicesOut(_Model):
    """A served rig: what may be registered on it."""

    rig: str
    teleoperating: list[str] = Field(description="input device ids")
    teleoperated: list[str] = Field(description="robot ids")


_ERRORS: dict[int | str, dict[str, object]] = {
    401: {"model": DeviceProblem, "description": "not logged in"},
    403: {"model": DeviceProblem, "description": "missing role or CSRF token"},
    503: {"model": DeviceProblem, "description": "no device registry configured"},
}
Viewer = Annotated[LoginSession, Depends(require("viewer"))]
Admin = Annotated[LoginSession, Depends(require("admin"))]
RigParam = Annotated[str, PathParam(pattern=_ID, max_length=64)]
PrincipalParam = Annotated[str, PathParam(pattern=_PRINCIPAL, max_length=70, description="MQTT username")]


def _registry(request: Request) -> DeviceRegistry:
    registry: DeviceRegistry | None = getattr(request.app.state, "devices", None)
    if registry is None:
        raise HTTPException(
            status.HTTP_503_SERVICE_UNAVAILABLE,
            "no device registry: start telerig serve with --rig to register the rig's devices",
        )
    return registry


def _out(r: Registration) -> RegisteredDevice:
    return RegisteredDevice(
        rig=r.rig,
        principal=r.principal,
        kind=r.kind,
        device=r.device,
        created_ns=r.created_ns,
        created_by=r.created_by,
        revoked_ns=r.revoked_ns,
        revoked_by=r.revoked_by,
        active=r.active,
        publishes=list(r.publishes),
    )


def _reload(result: ReloadResult) -> BrokerReload:
    return BrokerReload(status=result.status, detail=result.detail)


def _audit(request: Request, session: LoginSession, action: str, target: str, detail: str) -> None:
    accounts: AccountStore = request.app.state.accounts
    accounts.audit(
        action, user=session.user.name, target=target, detail=detail, client=client_address(request)
    )


@router.get("/api/devices", response_model=list[RegisteredDevice], responses=_ERRORS)
def list_devices(
    request: Request,
    _: Viewer,
    rig: Annotated[str | None, Query(pattern=_ID, max_length=64)] = None,
    active: Annotated[bool, Query(description="only registrations not revoked")] = False,
) -> list[RegisteredDevice]:
    """Registered devices (revoked ones too unless ``active``), by rig and principal."""
    registry = _registry(request)
    return [_out(r) for r in registry.registrations(rig, include_revoked=not active)]


@router.get("/api/devices/rigs", response_model=list[RigDevicesOut], responses=_ERRORS)
def rigs(request: Request, _: Viewer) -> list[RigDevicesOut]:
    """The rigs served here and the ids of their input devices and robots."""
    registry = _registry(request)
    out = []
    for name in registry.rigs:
        config = registry.rig_config(name)
        out.append(
            RigDevicesOut(
                rig=name,
                teleoperating=[d.id for d in config.devices],
                teleoperated=[r.id for r in config.robots],
            )
        )
    return out


@router.post(
    "/api/devices",
    response_model=IssuedOut,
    status_code=201,
    responses={
        **_ERRORS,
        409: {"model": DeviceProblem, "description": "registered already"},
        422: {"description": "not a device of the rig, or a malformed id"},
    },
)
def register(body: RegisterRequest, request: Request, response: Response, session: Admin) -> IssuedOut:
    """Register a device and issue its MQTT login; the broker's files are rewritten and the broker
    told to reload. The password is in this reply only."""
    registry = _registry(request)
    rig = body.rig
    if rig is None:
        if len(registry.rigs) != 1:
            raise HTTPException(422, f"name the rig: one of {', '.join(registry.rigs)}")
        rig = registry.rigs[0]
    try:
        principal = registry.principal(rig, body.kind, body.device)
    except DeviceError as exc:
        raise HTTPException(422, str(exc)) from None
    try:
        issued = registry.register(rig, body.kind, body.device, by=session.user.name)
    except DeviceError as exc:
        raise HTTPException(status.HTTP_409_CONFLICT, str(exc)) from None
    _audit(
        request, session, "device_registered", f"{rig}/{principal}", f"{body.kind}; {issued.reload.status}"
    )
    response.headers["Cache-Control"] = "no-store"
    return IssuedOut(
        device=_out(issued.registration),
        username=principal,
        password=issued.password,
        broker=_reload(issued.reload),
    )


@router.get(
    "/api/devices/{rig}/{principal}",
    response_model=RegisteredDevice,
    responses={**_ERRORS, 404: {"model": DeviceProblem, "description": "no such registration"}},
)
def device(rig: RigParam, principal: PrincipalParam, request: Request, _: Viewer) -> RegisteredDevice:
    """One registration."""
    registry = _registry(request)
    try:
        return _out(registry.get(rig, principal))
    except UnknownRegistrationError as exc:
        raise HTTPException(status.HTTP_404_NOT_FOUND, str(exc)) from None


@router.delete(
    "/api/devices/{rig}/{principal}",
    response_model=RevokedOut,
    responses={**_ERRORS, 404: {"model": DeviceProblem, "description": "no active registration"}},
)
def revoke(rig: RigParam, principal: PrincipalParam, request: Request, session: Admin) -> RevokedOut:
    """Revoke a registration: its login leaves the broker's password file and the broker reloads
    (Mosquitto disconnects it)."""
    registry = _registry(request)
    try:
        registration, reload = registry.revoke(rig, principal, by=session.user.name)
    except UnknownRegistrationError as exc:
        raise HTTPException(status.HTTP_404_NOT_FOUND, str(exc)) from None
    _audit(request, session, "device_revoked", f"{rig}/{principal}", reload.status)
    return RevokedOut(device=_out(registration), broker=_reload(reload))


@router.get("/devices", include_in_schema=False, response_model=None)
def page(request: Request) -> Response:
    accounts: AccountStore = request.app.state.accounts
    if accounts.session(request.cookies.get(COOKIE, "")) is None:
        return RedirectResponse("/login", status_code=303)
    return FileResponse(_STATIC / "devices.html", headers=_PAGE_HEADERS)


@router.get("/assets/devices.js", include_in_schema=False)
def script() -> FileResponse:
    return FileResponse(_STATIC / "devices.js", media_type="text/javascript", headers=_PAGE_HEADERS)
