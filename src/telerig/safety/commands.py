"""Operator safety commands on the bus: e-stop and reset, from the dashboard or ``telerig safety``.

A command is JSON on ``telerig/v1/<rig>/safety/command`` (QoS 1, never retained: a retained
e-stop would fire again on every reconnect, a retained reset would re-arm a robot nobody looked
at), e.g. ``{"command": "reset", "robot": "ur5e", "operator": "op7"}``. Every process that
supervises robots (the station, and each robot process with ``runtime.isolation: processes``)
listens and applies it to the robots it owns; a command naming a robot of another process is
left to that process.

* ``estop``: latch the named robot's (or every robot's) e-stop and stop its driver at once, like
  a fault, without applying the rig's fault policy (an operator's e-stop names what it stops).
* ``reset``: release the named robot's (or every robot's) e-stop after a fault, a halt or an
  e-stop command. The chain restarts stopped: it re-seeds from the measured position and waits
  for fresh valid input, then ramps up again, so a reset never makes a robot jump. A fault whose
  cause is still there (a lost connection, a joint beyond its limit) latches again on the next
  tick, with a new alert.

Halts (``telerig/v1/<rig>/safety/halt``, :class:`HaltNotice`) tell every process of a rig under
``halt_all`` that a robot faulted. Every payload read here is validated (strict types, no extra
fields, at most :data:`MAX_PAYLOAD_BYTES`); one that is not valid, or that names a robot the rig
does not have, is counted, logged in one line and dropped.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Collection
from typing import Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from telerig.bus.base import Bus, Message
from telerig.bus.topics import Topic
from telerig.safety.supervisor import SafetySupervisor

__all__ = [
    "COMMAND",
    "HALT",
    "MAX_PAYLOAD_BYTES",
    "HaltListener",
    "HaltNotice",
    "SafetyCommand",
    "SafetyCommandListener",
    "halt_topic",
    "parse_payload",
    "safety_command_topic",
]

log = logging.getLogger(__name__)

#: Stream of operator safety commands under ``telerig/v1/<rig>/safety/``.
COMMAND = "command"
#: Stream (on the ``safety`` node) where a ``halt_all`` fault reaches every process of the rig.
HALT = "halt"
#: Largest safety payload accepted [bytes]; ours are under 700 (a 500-character reason).
MAX_PAYLOAD_BYTES = 4096

_ID = r"^[A-Za-z0-9_.\-]+$"


class SafetyCommand(BaseModel):
    """An operator's safety command (see the module docs).

    Attributes:
        command: ``estop`` or ``reset``.
        robot: The robot's id; ``None`` for every robot of the rig.
        reason: Why (shown in the e-stop's alert); free text.
        operator: Who sent it (logged, and named in the e-stop's reason).
        source: What sent it, e.g. ``cli`` or ``web``.
    """

    model_config = ConfigDict(frozen=True, extra="forbid", strict=True)

    command: Literal["estop", "reset"]
    robot: str | None = Field(default=None, pattern=_ID, max_length=64)
    reason: str | None = Field(default=None, max_length=500)
    operator: str | None = Field(default=None, pattern=_ID, max_length=64)
    source: str = Field(default="bus", max_length=64)

    def describe(self) -> str:
        """One line for logs and alerts, e.g. ``e-stop by op7 (cli): gripper slipping``."""
        what = "e-stop" if self.command == "estop" else "reset"
        who = f" by {self.operator}" if self.operator else ""
        why = f": {self.reason}" if self.reason else ""
        return f"{what}{who} ({self.source}){why}"


class HaltNotice(BaseModel):
    """What a robot process publishes on ``telerig/v1/<rig>/safety/halt`` when its robot faults
    under ``halt_all``, e.g. ``{"robot": "arm3", "code": "driver_fault", "reason": "..."}``.

    Attributes:
        robot: The robot that faulted.
        code: The safety event's code.
        reason: The fault's reason, free text.
    """

    model_config = ConfigDict(frozen=True, extra="forbid", strict=True)

    robot: str = Field(pattern=_ID, max_length=64)
    code: str = Field(default="", max_length=64)
    reason: str = Field(default="", max_length=1000)


def safety_command_topic(rig: str) -> str:
    """``telerig/v1/<rig>/safety/command``."""
    return str(Topic(rig, "safety", COMMAND))


def halt_topic(rig: str) -> str:
    """``telerig/v1/<rig>/safety/halt``."""
    return str(Topic(rig, "safety", HALT))


_M = TypeVar("_M", bound=BaseModel)


def parse_payload(model: type[_M], message: Message) -> _M | str:
    """Validate ``message``'s payload as ``model``; on failure, return one line saying why.

    The payload must be at most :data:`MAX_PAYLOAD_BYTES` and a JSON object of ``model``'s
    fields with their exact types (strict: ``"1"`` is not a number, ``[]`` is not an object).
    """
    if len(message.payload) > MAX_PAYLOAD_BYTES:
        return f"{len(message.payload)} bytes, over the {MAX_PAYLOAD_BYTES}-byte limit"
    try:
        return model.model_validate_json(message.payload)
    except ValidationError as exc:
        error = exc.errors()[0]
        where = ".".join(str(p) for p in error["loc"]) or "payload"
        return f"{where}: {error['msg']}"


class _Counter:
    #: What the messages are, for the log line.
    what = "message"

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.applied = 0
        self.rejected = 0

    def reject(self, message: Message, why: str) -> None:
        with self._lock:
            self.rejected += 1
        log.warning("dropped a %s on %s: %s", self.what, message.topic, why)

    def apply(self) -> None:
        with self._lock:
            self.applied += 1


class SafetyCommandListener(_Counter):
    """Applies the safety commands of one rig to the robots a supervisor owns.

    Malformed commands, and commands naming a robot not in ``rig_robots``, are counted in
    :attr:`rejected`, logged in one line and dropped; commands for robots of the rig this
    supervisor does not own are ignored (another process owns them).

    Args:
        bus: A connected bus.
        rig: Rig name.
        supervisor: Owns the robots commands apply to.
        rig_robots: Every robot id of the rig; ``None``: not known, so a command for a robot
            this supervisor does not own is ignored, never rejected.
    """

    what = "safety command"

    def __init__(
        self, bus: Bus, rig: str, supervisor: SafetySupervisor, *, rig_robots: Collection[str] | None = None
    ) -> None:
        super().__init__()
        self._supervisor = supervisor
        self._rig_robots = None if rig_robots is None else frozenset(rig_robots)
        bus.subscribe(safety_command_topic(rig), self._on_message, qos=1)

    def _on_message(self, message: Message) -> None:
        command = parse_payload(SafetyCommand, message)
        if isinstance(command, str):
            self.reject(message, command)
            return
        known = self._rig_robots
        if command.robot is not None and known is not None and command.robot not in known:
            self.reject(message, f"{command.describe()} names robot {command.robot!r}, not in the rig")
            return
        robots = self._supervisor.robots
        names = list(robots) if command.robot is None else [command.robot]
        names = [n for n in names if n in robots]
        if not names:
            return
        log.warning("%s: %s", ", ".join(names), command.describe())
        for name in names:
            if command.command == "estop":
                robots[name].halt(command.describe(), suggested_action=f"telerig safety reset --robot {name}")
            else:
                robots[name].reset()
        self.apply()


class HaltListener(_Counter):
    """Halts this process's robots when a robot of another process of the rig faults under ``halt_all``.

    A notice that is not a valid :class:`HaltNotice`, or that names a robot not in ``rig_robots``
    (a forged ``{"robot": "nobody"}`` must not stop a fleet), is counted in :attr:`rejected`,
    logged in one line and dropped. A notice about one of ``own`` is ignored (this process
    already reacted to its own fault).

    Args:
        bus: A connected bus.
        rig: Rig name.
        own: The robots this process runs.
        rig_robots: Every robot id of the rig.
        halt: Called with the reason to halt this process's robots.
    """

    what = "halt notice"

    def __init__(
        self,
        bus: Bus,
        rig: str,
        *,
        own: Collection[str],
        rig_robots: Collection[str],
        halt: Callable[[str], None],
    ) -> None:
        super().__init__()
        self._own = frozenset(own)
        self._rig_robots = frozenset(rig_robots)
        self._halt = halt
        bus.subscribe(halt_topic(rig), self._on_message, qos=1)

    def _on_message(self, message: Message) -> None:
        notice = parse_payload(HaltNotice, message)
        if isinstance(notice, str):
            self.reject(message, notice)
            return
        if notice.robot not in self._rig_robots:
            self.reject(message, f"robot {notice.robot!r} is not in the rig; no robot halted")
            return
        if notice.robot in self._own:
            return
        self.apply()
        self._halt(f"halted because robot {notice.robot!r} faulted: {notice.reason}")
