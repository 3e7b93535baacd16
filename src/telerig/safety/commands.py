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
"""

from __future__ import annotations

import logging
import threading
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from telerig.bus.base import Bus, Message
from telerig.bus.topics import Topic
from telerig.safety.supervisor import SafetySupervisor

__all__ = ["COMMAND", "SafetyCommand", "SafetyCommandListener", "safety_command_topic"]

log = logging.getLogger(__name__)

#: Stream of operator safety commands under ``telerig/v1/<rig>/safety/``.
COMMAND = "command"

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

    model_config = ConfigDict(frozen=True, extra="forbid")

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


def safety_command_topic(rig: str) -> str:
    """``telerig/v1/<rig>/safety/command``."""
    return str(Topic(rig, "safety", COMMAND))


class SafetyCommandListener:
    """Applies the safety commands of one rig to the robots a supervisor owns.

    Malformed commands are counted in :attr:`rejected`, logged in one line and dropped; commands
    for robots this supervisor does not own are ignored (another process owns them).
    """

    def __init__(self, bus: Bus, rig: str, supervisor: SafetySupervisor) -> None:
        self._supervisor = supervisor
        self._lock = threading.Lock()
        self.applied = 0
        self.rejected = 0
        bus.subscribe(safety_command_topic(rig), self._on_message, qos=1)

    def _on_message(self, message: Message) -> None:
        try:
            command = SafetyCommand.model_validate_json(message.payload)
        except ValidationError as exc:
            with self._lock:
                self.rejected += 1
            error = exc.errors()[0]
            where = ".".join(str(p) for p in error["loc"]) or "payload"
            log.warning("dropped a safety command on %s: %s: %s", message.topic, where, error["msg"])
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
        with self._lock:
            self.applied += 1
