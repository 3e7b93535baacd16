"""Voice grammar commands typed in the control center: ``POST /api/voice/say`` (operator role, CSRF).

The text goes through the same grammar and dispatcher as speech and ``telerig say``
(:mod:`telerig.voice`), publishing as the ``web`` principal through the server's
:class:`~telerig.server.gateway.RigGateway`; the reply says what was done, staged (a critical
command waits for "robot please execute"), or why it was rejected (422, one line). Every command is
audited.
"""

from __future__ import annotations

import threading
from typing import Annotated, Literal

from fastapi import APIRouter, Depends, HTTPException, Request, status
from pydantic import BaseModel, ConfigDict, Field

from telerig.errors import BusError
from telerig.server.accounts import AccountStore, LoginSession
from telerig.server.auth import client_address, require
from telerig.server.gateway import RigGateway
from telerig.voice.dispatch import AID_STREAMS, Dispatcher
from telerig.voice.grammar import MAX_TEXT_CHARS

__all__ = ["router"]

router = APIRouter(tags=["voice"])
Operator = Annotated[LoginSession, Depends(require("operator"))]
_LOCK = threading.Lock()


class SayRequest(BaseModel):
    """A phrase of the voice command grammar, e.g. ``navigation`` or ``mark success``."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    text: str = Field(min_length=1, max_length=MAX_TEXT_CHARS)


class SayReply(BaseModel):
    """What became of the phrase: ``done``, ``staged`` or ``cancelled``, and the sentence said back."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    heard: str
    status: Literal["done", "staged", "cancelled"]
    say: str
    command: str | None


class _Problem(BaseModel):
    detail: str


_ERRORS: dict[int | str, dict[str, object]] = {
    401: {"model": _Problem, "description": "not logged in"},
    403: {"model": _Problem, "description": "missing role or CSRF token"},
    422: {"model": _Problem, "description": "not a command of the grammar (the reason, one line)"},
    503: {"model": _Problem, "description": "no rig, or not connected to its broker"},
}


def _dispatcher(request: Request) -> tuple[RigGateway, Dispatcher]:
    gateway: RigGateway | None = request.app.state.gateway
    if gateway is None:
        raise HTTPException(
            status.HTTP_503_SERVICE_UNAVAILABLE,
            "this server watches no rig: start it with `telerig serve --rig RIG`",
        )
    with _LOCK:
        dispatcher: Dispatcher | None = getattr(request.app.state, "voice", None)
        if dispatcher is None:

            def publish(topic: str, payload: bytes, qos: int, retain: bool) -> None:
                gateway.publish(topic, payload, qos=qos, retain=retain)

            dispatcher = Dispatcher(gateway.name, publish, source="web")
            for stream in AID_STREAMS:
                gateway.add_listener(stream, dispatcher.observe)
            request.app.state.voice = dispatcher
    return gateway, dispatcher


@router.post("/api/voice/say", response_model=SayReply, responses=_ERRORS)
def say(request: Request, session: Operator, body: SayRequest) -> SayReply:
    """Send one phrase of the voice command grammar (as `telerig say`)."""
    gateway, dispatcher = _dispatcher(request)
    accounts: AccountStore = request.app.state.accounts
    client = client_address(request)
    try:
        reply = dispatcher.handle(body.text, source="web")
    except BusError as exc:
        accounts.audit(
            "voice_failed", user=session.user.name, target=gateway.name, detail=str(exc), client=client
        )
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, str(exc)) from None
    accounts.audit(
        f"voice_{reply.status}",
        user=session.user.name,
        target=gateway.name,
        detail=f"{reply.heard!r} -> {reply.command or '-'}: {reply.say}"[:500],
        client=client,
    )
    if reply.status == "rejected":
        raise HTTPException(422, reply.say)
    return SayReply(heard=reply.heard, status=reply.status, say=reply.say, command=reply.command)
