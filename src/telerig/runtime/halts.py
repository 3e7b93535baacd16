"""The rig-wide halt between processes under ``halt_all``: publish this process's robot faults, halt
on another's (over ``telerig/v1/<rig>/safety/halt``, see :mod:`telerig.safety.commands`).

Used by the station's nodes in every process; a module of its own so that the nodes and the robot
host processes that build them do not import each other.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

from telerig.safety.commands import HaltListener, halt_topic
from telerig.safety.filters import SafetyEvent

__all__ = ["halt_publisher", "listen_for_halts"]


def listen_for_halts(runtime: Any, rig: str) -> HaltListener:
    """Halt this process's robots when another process's robot faults under ``halt_all``.

    Notices are validated (:class:`~telerig.safety.commands.HaltNotice`); a malformed one, or one
    naming a robot the rig does not have, is counted in the listener's ``rejected`` and dropped.
    """
    return HaltListener(
        runtime.node_bus,
        rig,
        own=set(runtime.robots),
        rig_robots=[r.id for r in runtime.config.robots],
        halt=runtime.supervisor.estop_all,
    )


def halt_publisher(bus: Any, rig: str) -> Callable[[str, SafetyEvent], None]:
    """The supervisor hook that tells every process of the rig to halt (``halt_all``)."""
    topic = halt_topic(rig)

    def publish(robot: str, event: SafetyEvent) -> None:
        doc = {"robot": robot, "code": event.code, "reason": event.reason}
        bus.publish(topic, json.dumps(doc).encode(), qos=1)

    return publish
