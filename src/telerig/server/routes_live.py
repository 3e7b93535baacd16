"""Live rig routes: the snapshot, the WebSocket feed, session commands, e-stop and reset.

Every route needs a login; the commands need the operator role and the CSRF header (see
:mod:`telerig.server.auth`) and are audited (user, action, target, client). They publish what the
command line publishes, through the server's :class:`~telerig.server.gateway.RigGateway` (the
``web`` principal of the rig's broker):

- ``POST /api/session/{start,stop,pause,resume,discard,restart,mark,end}``: an
  :class:`~telerig.runtime.session.EpisodeCommand` on ``R/coordinator/command``, as ``telerig
  session`` does; the reply is the session state the coordinator published next (409 when it did
  not change: the command is not allowed in the session's state, or no coordinator runs).
- ``POST /api/estop``, ``POST /api/reset``: a :class:`~telerig.safety.commands.SafetyCommand` on
  ``R/safety/command``, as ``telerig safety`` does, for one robot (``robot``) or every robot of the
  rig; the reply says which robots confirmed through their status topic.

- ``POST /api/rig/devices/{device}/pause``, ``.../resume``: per-device pause versus halt all
  (seed 000): ``pause_device``/``resume_device`` on ``R/coordinator/command`` (as ``telerig session
  pause_device --device D``); the device's robots hold their pose while the rest of the rig goes on,
  and re-anchor on resume. The session state in the snapshot lists ``paused_devices``. Halting all
  is the session's ``pause`` (the episode) or the e-stop (every robot). The rig's fault policy
  (``safety.policy``: ``halt_all`` or ``pause_affected``) is ``fault_policy`` in the snapshot.
- ``POST /api/rig/devices/{device}/calibrate``: operator calibration with that device, run by its
  device node where the device runs (``{"calibrate": {...}}`` on ``R/<device>/command``, see
  :mod:`telerig.runtime.device_calibration`); the reply is the node's first answer, progress and
  the result come as the device's events (the alerts, and ``calibration`` of the device in the
  snapshot).

``/api/live`` is a WebSocket: the session cookie must come with the handshake (and a browser's
``Origin`` must be this server); it sends ``{"type": "snapshot", ...}`` first, then
``{"type": "delta", "t_ns", "changed": {section: value}}`` with the sections that changed, at
most :data:`LIVE_HZ` times a second (ages alone do not count as a change; every section is resent
once a second to refresh them).
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from typing import Annotated, Any, Literal

from fastapi import (
    APIRouter,
    Body,
    Depends,
    HTTPException,
    Query,
    Request,
    Response,
    WebSocket,
    WebSocketDisconnect,
    status,
)
from pydantic import BaseModel, ConfigDict, Field, JsonValue

from telerig.errors import BusError
from telerig.runtime.session import COMMANDS, EpisodeCommand
from telerig.safety.commands import SafetyCommand
from telerig.server.accounts import AccountStore, LoginSession
from telerig.server.auth import RECHECK_S, client_address, require, same_origin, websocket_session
from telerig.server.gateway import RigGateway, RigSnapshot, SafetyResult, SessionOut

__all__ = ["LIVE_HZ", "router"]

log = logging.getLogger("telerig.server")

#: Most WebSocket updates per second.
LIVE_HZ = 10.0
#: Every section is resent this often even unchanged, so the ages it carries stay fresh [s].
_REFRESH_S = 1.0
_NAME = r"^[A-Za-z0-9_.\-]+$"

router = APIRouter(tags=["rig"])


class _In(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class StartRequest(_In):
    """Arm the next episode: task and operator (the previous episode's when omitted; the
    operator defaults to the logged-in user), start lead [s]."""

    task: str | None = Field(default=None, min_length=1, max_length=200)
    operator: str | None = Field(default=None, pattern=_NAME, max_length=64)
    lead_s: float | None = Field(default=None, ge=0, le=60)
    reason: str | None = Field(default=None, max_length=500)


class MarkRequest(_In):
    """The episode's outcome, and why."""

    outcome: Literal["success", "failure"]
    reason: str | None = Field(default=None, max_length=500)


class ReasonRequest(_In):
    """Why (kept in the session status)."""

    reason: str | None = Field(default=None, max_length=500)


class SafetyRequest(_In):
    """An e-stop or reset of one robot (``robot``) or of every robot (omitted); ``timeout_s``: how
    long to wait for the robots' confirmation."""

    robot: str | None = Field(default=None, pattern=_NAME, max_length=64)
    reason: str | None = Field(default=None, max_length=500)
    timeout_s: float = Field(default=3.0, gt=0, le=10)


class SessionReply(BaseModel):
    """The command sent and the session state the coordinator published after it."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    command: str
    session: SessionOut


class _Problem(BaseModel):
    detail: str


_ERRORS: dict[int | str, dict[str, Any]] = {
    401: {"model": _Problem, "description": "not logged in"},
    403: {"model": _Problem, "description": "missing role or CSRF token"},
    503: {"model": _Problem, "description": "no rig, or not connected to its broker"},
}
_COMMAND_ERRORS: dict[int | str, dict[str, Any]] = {
    **_ERRORS,
    409: {"model": _Problem, "description": "the session did not change (not allowed in its state)"},
}

Operator = Annotated[LoginSession, Depends(require("operator"))]
Viewer = Annotated[LoginSession, Depends(require("viewer"))]


def _gateway(request: Request) -> RigGateway:
    gateway: RigGateway | None = request.app.state.gateway
    if gateway is None:
        raise HTTPException(
            status.HTTP_503_SERVICE_UNAVAILABLE,
            "this server watches no rig: start it with `telerig serve --rig RIG`",
        )
    return gateway


@router.get("/api/rig", response_model=RigSnapshot, responses=_ERRORS)
def rig_snapshot(
    request: Request, _: Viewer, alerts: Annotated[int, Query(ge=0, le=200)] = 50
) -> RigSnapshot:
    """The rig now: session, robots' safety status, stations (red when silent), devices, streams
    (rates, drops, gaps), active alerts and the newest ``alerts`` alerts with suggested actions."""
    return _gateway(request).snapshot(alerts=alerts)


def _session_route(command: Literal["stop", "pause", "resume", "discard", "end"]) -> None:
    def send(
        request: Request, session: Operator, body: Annotated[ReasonRequest | None, Body()] = None
    ) -> SessionReply:
        reason = None if body is None else body.reason
        return _send_session(request, session, EpisodeCommand(command=command, reason=reason, source="web"))

    send.__name__ = f"session_{command}"
    send.__doc__ = f"{COMMANDS[command][0].upper()}{COMMANDS[command][1:]} (as `telerig session {command}`)."
    router.post(f"/api/session/{command}", response_model=SessionReply, responses=_COMMAND_ERRORS)(send)


@router.post("/api/session/start", response_model=SessionReply, responses=_COMMAND_ERRORS)
def session_start(
    request: Request, session: Operator, body: Annotated[StartRequest | None, Body()] = None
) -> SessionReply:
    """Arm the next episode (as `telerig session start`); the operator is the logged-in user by default."""
    return _start(request, session, "start", body)


@router.post("/api/session/restart", response_model=SessionReply, responses=_COMMAND_ERRORS)
def session_restart(
    request: Request, session: Operator, body: Annotated[StartRequest | None, Body()] = None
) -> SessionReply:
    """Throw the running episode away and record it again at once (as `telerig session restart`)."""
    return _start(request, session, "restart", body)


@router.post("/api/session/mark", response_model=SessionReply, responses=_COMMAND_ERRORS)
def session_mark(request: Request, session: Operator, body: MarkRequest) -> SessionReply:
    """Label the running (or last) episode a success or failure (as `telerig session mark`)."""
    command = EpisodeCommand(command="mark", outcome=body.outcome, reason=body.reason, source="web")
    return _send_session(request, session, command)


def _start(
    request: Request, session: LoginSession, what: Literal["start", "restart"], body: StartRequest | None
) -> SessionReply:
    body = body or StartRequest()
    command = EpisodeCommand(
        command=what,
        task=body.task,
        operator=body.operator or session.user.name,
        lead_s=body.lead_s,
        reason=body.reason,
        source="web",
    )
    return _send_session(request, session, command)


for _command in ("stop", "pause", "resume", "discard", "end"):
    _session_route(_command)


def _device_route(command: Literal["pause_device", "resume_device"]) -> None:
    verb = command.split("_")[0]

    def send(
        request: Request,
        session: Operator,
        device: str,
        body: Annotated[ReasonRequest | None, Body()] = None,
    ) -> SessionReply:
        gateway = _gateway(request)
        if device not in gateway.devices:
            raise HTTPException(
                status.HTTP_404_NOT_FOUND,
                f"no device {device!r} in rig {gateway.name!r}; valid: {', '.join(gateway.devices)}",
            )
        why = None if body is None or body.reason is None else body.reason[:400]
        reason = f"{why or verb} (by {session.user.name})"  # the episode's log says who
        episode_command = EpisodeCommand(command=command, device=device, reason=reason, source="web")
        return _send_session(request, session, episode_command)

    send.__name__ = f"device_{verb}"
    send.__doc__ = (
        f"{COMMANDS[command][0].upper()}{COMMANDS[command][1:].replace(' (--device)', '')} "
        f"(as `telerig session {command} --device D`); the reply's session lists ``paused_devices``."
    )
    router.post(
        f"/api/rig/devices/{{device}}/{verb}",
        response_model=SessionReply,
        responses=_COMMAND_ERRORS | {404: {"model": _Problem}},
    )(send)


_device_route("pause_device")
_device_route("resume_device")


class CalibrateRequest(_In):
    """Calibrate an operator with a device: ``operator`` (the logged-in user when omitted), the
    measured hold ``duration_s`` and the ``settle_s`` before it to get into the pose [s]."""

    operator: str | None = Field(default=None, pattern=_NAME, max_length=64)
    duration_s: float = Field(default=30.0, gt=0, le=120)
    settle_s: float = Field(default=3.0, ge=0, le=30)


class CalibrationReply(BaseModel):
    """The device node's first answer (``None`` when none came within 3 s): calibrating, or why not."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    device: str
    operator: str
    reply: str | None


@router.post(
    "/api/rig/devices/{device}/calibrate",
    response_model=CalibrationReply,
    responses=_ERRORS | {404: {"model": _Problem}, 422: {"model": _Problem}},
)
def device_calibrate(
    request: Request,
    session: Operator,
    device: str,
    body: Annotated[CalibrateRequest | None, Body()] = None,
) -> CalibrationReply:
    """Start the operator calibration (as `telerig calibrate`) where the device runs: hold both hands
    straight forward, level and still. A device that drives robots in a running episode must be
    paused first."""
    gateway = _gateway(request)
    if device not in gateway.devices:
        raise HTTPException(
            status.HTTP_404_NOT_FOUND,
            f"no device {device!r} in rig {gateway.name!r}; valid: {', '.join(gateway.devices)}",
        )
    body = body or CalibrateRequest()
    operator = body.operator or session.user.name
    accounts: AccountStore = request.app.state.accounts
    client = client_address(request)
    target = f"{gateway.name}/{device}"
    command: dict[str, JsonValue] = {
        "operator": operator,
        "duration_s": body.duration_s,
        "settle_s": body.settle_s,
    }
    try:
        reply = gateway.send_device_command(device, {"calibrate": command})
    except BusError as exc:
        accounts.audit(
            "calibrate_failed", user=session.user.name, target=target, detail=str(exc), client=client
        )
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, str(exc)) from None
    detail = f"operator {operator}: {reply or 'no reply from the device (is the rig running?)'}"
    accounts.audit("calibrate", user=session.user.name, target=target, detail=detail, client=client)
    return CalibrationReply(device=device, operator=operator, reply=reply)


def _send_session(request: Request, session: LoginSession, command: EpisodeCommand) -> SessionReply:
    gateway = _gateway(request)
    accounts: AccountStore = request.app.state.accounts
    client = client_address(request)
    detail = command.model_dump_json(exclude_none=True, exclude={"source"})
    try:
        new = gateway.send_session(command)
    except BusError as exc:
        accounts.audit(
            f"session_{command.command}_failed",
            user=session.user.name,
            target=gateway.name,
            detail=str(exc),
            client=client,
        )
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, str(exc)) from None
    snapshot = gateway.snapshot(alerts=0).session
    if new is None or snapshot is None:
        state = "unknown (no session state from the rig)" if snapshot is None else snapshot.state
        accounts.audit(
            f"session_{command.command}_refused",
            user=session.user.name,
            target=gateway.name,
            detail=f"{detail} (session {state})",
            client=client,
        )
        raise HTTPException(
            status.HTTP_409_CONFLICT,
            f"the session did not {command.command} within 3 s (session {state}): is the command allowed "
            "now, and is `telerig run` running?",
        )
    accounts.audit(
        f"session_{command.command}",
        user=session.user.name,
        target=gateway.name,
        detail=f"{detail} -> {snapshot.state} {snapshot.episode_id or ''}".strip(),
        client=client,
    )
    return SessionReply(command=command.command, session=snapshot)


@router.post("/api/estop", response_model=SafetyResult, responses=_ERRORS | {422: {"model": _Problem}})
def estop(
    request: Request, session: Operator, body: Annotated[SafetyRequest | None, Body()] = None
) -> SafetyResult:
    """E-stop one robot (``robot``) or every robot of the rig (as `telerig safety estop`); the reply
    says which robots confirmed ``estopped`` on their status topic within ``timeout_s``."""
    return _send_safety(request, session, "estop", body or SafetyRequest())


@router.post("/api/reset", response_model=SafetyResult, responses=_ERRORS | {422: {"model": _Problem}})
def reset(
    request: Request, session: Operator, body: Annotated[SafetyRequest | None, Body()] = None
) -> SafetyResult:
    """Release the e-stop of one robot or of every robot (as `telerig safety reset`); the robot
    restarts stopped and ramps up on fresh input."""
    return _send_safety(request, session, "reset", body or SafetyRequest())


def _send_safety(
    request: Request, session: LoginSession, what: Literal["estop", "reset"], body: SafetyRequest
) -> SafetyResult:
    gateway = _gateway(request)
    if body.robot is not None and body.robot not in gateway.robots:
        raise HTTPException(
            422,
            f"no robot {body.robot!r} in rig {gateway.name!r}; valid: {', '.join(gateway.robots)}",
        )
    accounts: AccountStore = request.app.state.accounts
    client = client_address(request)
    target = f"{gateway.name}/{body.robot or '*'}"
    command = SafetyCommand(
        command=what, robot=body.robot, reason=body.reason, operator=session.user.name, source="web"
    )
    try:
        result = gateway.send_safety(command, timeout_s=body.timeout_s)
    except BusError as exc:
        accounts.audit(
            f"{what}_failed", user=session.user.name, target=target, detail=str(exc), client=client
        )
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, f"{exc}; use the hardware e-stop") from None
    confirmed = [r.robot for r in result.robots if r.confirmed]
    missing = [r.robot for r in result.robots if not r.confirmed]
    detail = f"confirmed: {', '.join(confirmed) or 'none'}" + (
        f"; not confirmed: {', '.join(missing)}" if missing else ""
    )
    if body.reason:
        detail += f"; reason: {body.reason}"
    accounts.audit(what, user=session.user.name, target=target, detail=detail, client=client)
    return result


@router.get(
    "/api/rig/cameras/{camera}/preview",
    response_class=Response,
    responses={
        200: {"content": {"image/jpeg": {}}, "description": "the camera's latest JPEG preview"},
        **_ERRORS,
        404: {"model": _Problem, "description": "no such camera, or no preview yet"},
    },
)
def camera_preview(request: Request, _: Viewer, camera: str) -> Response:
    """The latest low-rate JPEG preview of a camera (``X-Preview-Age`` [s] says how old;
    ``X-Capture-Ns``, when the camera stamped it, its frame's capture time for the page's
    ``displayed`` latency report, see ``/api/latency``)."""
    gateway = _gateway(request)
    if camera not in gateway.cameras:
        valid = ", ".join(gateway.cameras) or "none"
        raise HTTPException(
            status.HTTP_404_NOT_FOUND, f"no camera {camera!r} in rig {gateway.name!r}; valid: {valid}"
        )
    got = gateway.preview(camera)
    if got is None:
        raise HTTPException(
            status.HTTP_404_NOT_FOUND, f"no preview from camera {camera!r} yet: is the rig running?"
        )
    jpeg, age = got
    headers = {
        "Cache-Control": "no-store",
        "X-Content-Type-Options": "nosniff",
        "X-Preview-Age": f"{age:.3f}",
    }
    capture_ns = gateway.preview_capture_ns(camera)
    if capture_ns is not None:
        headers["X-Capture-Ns"] = str(capture_ns)
    return Response(jpeg, media_type="image/jpeg", headers=headers)


class TakeoverRequest(_In):
    """The operator's answer to a page asking to take over a WebXR device (``takeover: confirm``)."""

    answer: Literal["confirm", "deny"]


class DeviceReply(BaseModel):
    """What the device answered (its ``command_reply`` event); ``reply`` is ``None`` when it did not
    answer within 3 s."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    device: str
    answer: Literal["confirm", "deny"]
    reply: str | None


@router.post(
    "/api/rig/devices/{device}/takeover",
    response_model=DeviceReply,
    responses=_ERRORS | {404: {"model": _Problem}},
)
def device_takeover(request: Request, session: Operator, device: str, body: TakeoverRequest) -> DeviceReply:
    """Confirm or deny the page waiting to take over a WebXR device (as `telerig device takeover`)."""
    gateway = _gateway(request)
    if device not in gateway.devices:
        raise HTTPException(
            status.HTTP_404_NOT_FOUND,
            f"no device {device!r} in rig {gateway.name!r}; valid: {', '.join(gateway.devices)}",
        )
    accounts: AccountStore = request.app.state.accounts
    client = client_address(request)
    target = f"{gateway.name}/{device}"
    try:
        reply = gateway.send_device_command(device, {"takeover": body.answer})
    except BusError as exc:
        accounts.audit(
            f"takeover_{body.answer}_failed",
            user=session.user.name,
            target=target,
            detail=str(exc),
            client=client,
        )
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, str(exc)) from None
    accounts.audit(
        f"takeover_{body.answer}",
        user=session.user.name,
        target=target,
        detail=reply or "no reply from the device",
        client=client,
    )
    return DeviceReply(device=device, answer=body.answer, reply=reply)


# --- the live feed -----------------------------------------------------------------------------------


@router.websocket("/api/live")
async def live(websocket: WebSocket) -> None:
    """The rig's snapshot, then its changes at most 10 times a second (login cookie required)."""
    if not same_origin(websocket):  # without an Origin (not a browser) the cookie decides
        await websocket.close(code=status.WS_1008_POLICY_VIOLATION, reason="foreign origin")
        return
    if await websocket_session(websocket) is None:
        await websocket.close(code=status.WS_1008_POLICY_VIOLATION, reason="log in first")
        return
    gateway: RigGateway | None = websocket.app.state.gateway
    if gateway is None:
        await websocket.close(code=status.WS_1011_INTERNAL_ERROR, reason="this server watches no rig")
        return
    await websocket.accept()
    reader = asyncio.create_task(_drain(websocket))
    try:
        await _feed(websocket, gateway, reader)
    except (WebSocketDisconnect, RuntimeError):
        pass  # the client went away (RuntimeError: sending on a socket starlette saw closed)
    finally:
        reader.cancel()


async def _drain(websocket: WebSocket) -> None:
    """Read (and ignore) what the client sends, so a close is noticed; ends when it disconnects."""
    try:
        while True:
            message = await websocket.receive()
            if message["type"] == "websocket.disconnect":
                return
    except (WebSocketDisconnect, RuntimeError):
        return


async def _feed(websocket: WebSocket, gateway: RigGateway, reader: asyncio.Task[None]) -> None:
    loop = asyncio.get_running_loop()
    snapshot, sent = _shared_snapshot(websocket, gateway)
    await websocket.send_text(json.dumps({"type": "snapshot", **snapshot.model_dump(mode="json")}))
    checked = full = loop.time()
    while not reader.done():
        await asyncio.sleep(1.0 / LIVE_HZ)
        now = loop.time()
        if now - checked > RECHECK_S:
            checked = now
            if await websocket_session(websocket) is None:
                await websocket.close(code=status.WS_1008_POLICY_VIOLATION, reason="logged out")
                return
        snapshot, sections = _shared_snapshot(websocket, gateway)
        everything = now - full >= _REFRESH_S
        changed = {k: v for k, (key, v) in sections.items() if everything or sent[k][0] != key}
        if everything:
            full = now
        if changed:
            sent = sections
            await websocket.send_text(
                json.dumps({"type": "delta", "t_ns": snapshot.t_ns, "changed": changed})
            )


Sections = dict[str, tuple[str, Any]]


def _shared_snapshot(websocket: WebSocket, gateway: RigGateway) -> tuple[RigSnapshot, Sections]:
    """The snapshot and its sections, computed at most once per feed period for every client."""
    state = websocket.app.state
    cached: tuple[float, RigSnapshot, Sections] | None = getattr(state, "live_snapshot", None)
    now = time.monotonic()
    if cached is None or now - cached[0] >= 0.5 / LIVE_HZ:
        snapshot = gateway.snapshot()
        cached = (now, snapshot, _sections(snapshot))
        state.live_snapshot = cached
    return cached[1], cached[2]


#: The ages in each section (they change every tick; every section is resent each _REFRESH_S).
_AGES: dict[str, Any] = {
    "session": {"age_s"},
    "robots": {"__all__": {"status_age_s"}},
    "stations": {"__all__": {"last_seen_s"}},
    "devices": {"__all__": {"report_age_s"}},
    "streams": {"__all__": {"report_age_s"}},
}


def _sections(snapshot: RigSnapshot) -> Sections:
    """Each top-level field of the snapshot but the time: a comparison key without the ages, and
    its value."""
    doc = snapshot.model_dump(mode="json", exclude={"t_ns"})
    keys = snapshot.model_dump(mode="json", exclude={"t_ns": True, **_AGES})
    return {k: (json.dumps(keys[k], sort_keys=True), v) for k, v in doc.items()}
