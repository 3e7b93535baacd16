"""From a heard or typed phrase to the bus: parse it, stage or send the command, say what happened.

:class:`Dispatcher` is the one place voice and text commands go through (the voice node, ``telerig
say`` and the web endpoint all use it). It publishes through a ``publish(topic, payload, qos, retain)``
function, so it works on any bus client (the CLI's, the web server's gateway), and it learns which
robots have which live aid from their retained aid state (:meth:`observe`).

Every phrase ends in one :class:`Reply`, published as JSON on ``R/voice/feedback`` (for the UI) and
handed to ``say`` (espeak-ng): ``done`` (sent), ``staged`` (a critical command waiting for ``robot
please execute``), ``cancelled`` or ``rejected`` (with the reason said back).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Literal

from telerig.bus.base import Message
from telerig.bus.catalogue import (
    COMMAND,
    COORDINATOR,
    FEEDBACK,
    FIXTURE,
    MOTION_SCALE,
    PLAN,
    VIEW,
    VOICE,
    WBC_MODE,
)
from telerig.bus.jsonpayload import parse_json_object
from telerig.bus.topics import Topic
from telerig.errors import WireError
from telerig.safety.commands import SafetyCommand, safety_command_topic
from telerig.voice.grammar import (
    AidAction,
    CancelAction,
    Command,
    ConfirmAction,
    FixtureAction,
    PlanAction,
    SafetyAction,
    SessionAction,
    ViewAction,
    command_named,
    parse,
)

__all__ = ["AID_STREAMS", "Dispatcher", "Publish", "Reply", "Status"]

log = logging.getLogger(__name__)

#: ``publish(topic, payload, qos, retain)``.
Publish = Callable[[str, bytes, int, bool], None]
Status = Literal["done", "staged", "cancelled", "rejected"]
#: The aid state streams :meth:`Dispatcher.observe` reads (which robot has which aid).
AID_STREAMS = (WBC_MODE, FIXTURE, MOTION_SCALE, PLAN)
_AID_NAMES = {
    WBC_MODE: "the whole-body mode",
    FIXTURE: "virtual fixtures",
    MOTION_SCALE: "a motion scale",
    PLAN: "a reach planner",
}
#: Longest plan id taken from a robot's plan state [characters].
_MAX_PLAN_ID = 64


@dataclass(frozen=True, slots=True)
class Reply:
    """What became of one phrase (published on ``R/voice/feedback``).

    Attributes:
        heard: The normalized words.
        status: ``done``, ``staged``, ``cancelled`` or ``rejected``.
        say: The sentence said back.
        command: The grammar command's name, ``None`` when rejected.
        group: Its group (``mode``, ``episode``...), ``None`` when rejected.
        source: Where the phrase came from (``voice``, ``cli``, ``web``).
        stamp_ns: Wall clock when handled [ns].
    """

    heard: str
    status: Status
    say: str
    command: str | None = None
    group: str | None = None
    source: str = "voice"
    stamp_ns: int = 0

    def to_json(self) -> bytes:
        return json.dumps(asdict(self)).encode()


@dataclass(slots=True)
class _Staged:
    command: Command
    heard: str
    at: float


@dataclass(slots=True)
class DispatchStats:
    """Counters: phrases handled per status, instructions sent per group, malformed input dropped."""

    by_status: Counter[str] = field(default_factory=Counter)
    sent: Counter[str] = field(default_factory=Counter)
    malformed: int = 0


class Dispatcher:
    """Turns phrases into bus commands for one rig (see the module docs). Thread-safe.

    Args:
        rig: Rig name.
        publish: Sends one message.
        robot: The robot aid commands and e-stops go to; ``None``: the one robot that has the aid
            (rejected when several have it), and every robot for e-stops.
        source: Default source label of replies and commands.
        confirm_window_s: How long a staged critical command waits for the confirmation [s].
        say: Called with every reply's sentence (spoken feedback); ``None`` for none.
        clock: Monotonic clock [s] (tests inject one).
    """

    def __init__(
        self,
        rig: str,
        publish: Publish,
        *,
        robot: str | None = None,
        source: str = "voice",
        confirm_window_s: float = 10.0,
        say: Callable[[str], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not confirm_window_s > 0:
            raise ValueError(f"confirm_window_s must be > 0 s, got {confirm_window_s}")
        self.rig = rig
        self.robot = robot
        self.source = source
        self._publish = publish
        self._window = confirm_window_s
        self._say = say
        self._clock = clock
        self._lock = threading.RLock()  # _reply counts under it, also from inside handle()
        self._aids: dict[str, set[str]] = {s: set() for s in AID_STREAMS}
        self._staged: _Staged | None = None
        #: Per robot with a reach planner: (plan id or None, status) from its retained plan state.
        self._plans: dict[str, tuple[str | None, str]] = {}
        self.stats = DispatchStats()

    # --- what the rig has ------------------------------------------------------------------------

    def observe(self, message: Message) -> None:
        """Note which robot publishes which aid state (``R/<robot>/<aid>``, retained). Never raises."""
        topic = Topic.try_parse(message.topic)
        if topic is None or topic.rig != self.rig or topic.stream not in self._aids:
            return
        plan: tuple[str | None, str] | None = None
        if topic.stream == PLAN and message.payload:
            plan = _plan_of(message.payload)
            if plan is None:
                with self._lock:
                    self.stats.malformed += 1
                return
        with self._lock:
            if message.payload:
                self._aids[topic.stream].add(topic.node)
                if plan is not None:
                    self._plans[topic.node] = plan
            else:  # a cleared retained state: the robot is gone
                self._aids[topic.stream].discard(topic.node)
                if topic.stream == PLAN:
                    self._plans.pop(topic.node, None)

    def robots_with(self, aid: str) -> tuple[str, ...]:
        """The robots seen publishing ``aid``'s state, sorted."""
        with self._lock:
            return tuple(sorted(self._aids.get(aid, ())))

    # --- phrases ---------------------------------------------------------------------------------

    def reject(self, heard: str, reason: str, *, source: str | None = None) -> Reply:
        """Count malformed input (bad audio, oversized text) and say ``reason`` back."""
        with self._lock:
            self.stats.malformed += 1
        return self._reply(heard, "rejected", reason, None, source)

    def handle(self, text: str, *, source: str | None = None) -> Reply:
        """Parse ``text`` and act on it; returns the reply (also published and said)."""
        match = parse(text)
        command = match.command
        if command is None:
            return self._reply(match.text, "rejected", match.reason or "not a command", None, source)
        action = command.action
        now = self._clock()
        with self._lock:
            staged, self._staged = self._staged, None  # any phrase but a confirmation drops it
            if isinstance(action, ConfirmAction):
                if staged is None or now - staged.at > self._window:
                    why = "nothing to execute" if staged is None else "too late, say the command again"
                    return self._reply(match.text, "rejected", why, command, source)
                command, action = staged.command, staged.command.action
            elif command.critical:
                self._staged = _Staged(command, match.text, now)
                return self._reply(
                    match.text,
                    "staged",
                    f"say robot please execute to confirm: {command.done}",
                    command,
                    source,
                )
        if isinstance(action, CancelAction):
            plans = self._cancel_plans()
            return self._reply(
                match.text,
                "cancelled",
                "cancelled" if staged or plans else "nothing to cancel",
                command,
                source,
            )
        problem = self._send(command, source or self.source)
        if problem is not None:
            return self._reply(match.text, "rejected", problem, command, source)
        with self._lock:
            self.stats.sent[command.group.value] += 1
            if command.stages is not None:
                follow = command_named(command.stages)
                self._staged = _Staged(follow, match.text, now)
                say = f"{command.done}; say robot please execute to confirm: {follow.done}"
                return self._reply(match.text, "staged", say, command, source)
        return self._reply(match.text, "done", command.done, command, source)

    def _cancel_plans(self) -> int:
        """Send ``cancel`` to every robot whose plan is being made, staged or executing."""
        with self._lock:
            robots = [
                r
                for r, (_, status) in self._plans.items()
                if status in ("planning", "staged", "executing") and self.robot in (None, r)
            ]
        for robot in robots:
            self._publish(str(Topic(self.rig, robot, f"{PLAN}_command")), b"cancel", 0, False)
        return len(robots)

    def _send(self, command: Command, source: str) -> str | None:
        """Publish the command; returns why it cannot be sent, or ``None``."""
        action = command.action
        rig = self.rig
        if isinstance(action, SessionAction):
            doc: dict[str, str] = {"command": action.command, "source": source}
            if action.outcome is not None:
                doc["outcome"] = action.outcome
            self._publish(str(Topic(rig, COORDINATOR, COMMAND)), json.dumps(doc).encode(), 1, False)
        elif isinstance(action, SafetyAction):
            safety = SafetyCommand(command=action.command, robot=self.robot, source=source[:64])
            self._publish(safety_command_topic(rig), safety.model_dump_json().encode(), 1, False)
        elif isinstance(action, AidAction | FixtureAction):
            aid = FIXTURE if isinstance(action, FixtureAction) else action.aid
            text = f"kind:{action.kind}" if isinstance(action, FixtureAction) else action.text
            robot = self.robot
            if robot is None:
                have = self.robots_with(aid)
                if len(have) != 1:
                    return (
                        f"no robot has {_AID_NAMES[aid]}"
                        if not have
                        else f"several robots have {_AID_NAMES[aid]} ({', '.join(have)}): choose one"
                    )
                robot = have[0]
            self._publish(str(Topic(rig, robot, f"{aid}_command")), text.encode(), 0, False)
        elif isinstance(action, PlanAction):
            robot = self.robot
            if robot is None:
                have = self.robots_with(PLAN)
                if len(have) != 1:
                    return (
                        f"no robot has {_AID_NAMES[PLAN]}"
                        if not have
                        else f"several robots have {_AID_NAMES[PLAN]} ({', '.join(have)}): choose one"
                    )
                robot = have[0]
            text = action.command
            if action.command == "execute":
                with self._lock:
                    plan_id, plan_status = self._plans.get(robot, (None, "none"))
                if plan_id is None or plan_status != "staged":
                    return f"no plan is staged ({plan_status}): say plan reach, then robot please execute"
                text = f"execute {plan_id}"
            self._publish(str(Topic(rig, robot, f"{PLAN}_command")), text.encode(), 0, False)
        elif isinstance(action, ViewAction):
            doc = {"view": action.perspective, "source": source}
            self._publish(str(Topic(rig, VOICE, VIEW)), json.dumps(doc).encode(), 1, True)
        return None

    def _reply(
        self, heard: str, status: Status, say: str, command: Command | None, source: str | None
    ) -> Reply:
        reply = Reply(
            heard=heard,
            status=status,
            say=say,
            command=None if command is None else command.name,
            group=None if command is None else command.group.value,
            source=source or self.source,
            stamp_ns=time.time_ns(),
        )
        with self._lock:
            self.stats.by_status[status] += 1
        log.info("voice: %r -> %s: %s", heard, status, say)
        try:
            self._publish(str(Topic(self.rig, VOICE, FEEDBACK)), reply.to_json(), 1, False)
        except Exception as exc:  # feedback is best effort: the command itself went out or was refused
            log.warning("voice: feedback not published: %s", exc)
        if self._say is not None:
            self._say(say)
        return reply


def _plan_of(payload: bytes) -> tuple[str | None, str] | None:
    """(id, status) of a robot's plan state; None when malformed."""
    try:
        doc = parse_json_object(payload, max_bytes=64 << 10)
    except WireError:
        return None
    plan_id, status = doc.get("id"), doc.get("status")
    if not isinstance(status, str) or len(status) > 20:
        return None
    if plan_id is not None and not (isinstance(plan_id, str) and 0 < len(plan_id) <= _MAX_PLAN_ID):
        return None
    if plan_id is not None and not all(c.isalnum() or c == "-" for c in plan_id):
        return None
    return plan_id, status
