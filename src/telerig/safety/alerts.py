"""Safety alerts on the bus: events on ``<rig>/safety/events``, retained active ones on ``.../alerts``."""

from __future__ import annotations

import json
import logging
import threading
from dataclasses import dataclass, replace
from typing import Literal

from pydantic import JsonValue

from telerig.bus.base import Bus
from telerig.bus.catalogue import ALERTS, EVENTS
from telerig.bus.topics import Topic, qos_for
from telerig.safety.chain import SafetyOutput
from telerig.safety.filters import SafetyCode, SafetyEvent

__all__ = ["ALERTS", "EVENTS", "SEVERITY", "SafetyAlert", "SafetyAlerts", "Severity"]

log = logging.getLogger(__name__)

# Streams (from the catalogue): ALERTS, the retained list of active safety alerts (QoS 1), and
# EVENTS, raised and cleared alerts (QoS 1, not retained).

Severity = Literal["info", "warning", "error"]

#: Severity of each code. ``info`` events (limits shaping the command, the normal case while the
#: operator moves fast) are counted by the chain but not published.
SEVERITY: dict[SafetyCode, Severity] = {
    "invalid_input": "warning",
    "out_of_range": "warning",
    "position_limit": "info",
    "velocity_limit": "info",
    "acceleration_limit": "info",
    "workspace": "warning",
    "self_collision": "warning",
    "deadman": "warning",
    "input_stale": "warning",
    "watchdog_stop": "warning",
    "joint_limit_fault": "error",
    "driver_fault": "error",
    "estop": "error",
}


@dataclass(frozen=True, slots=True)
class SafetyAlert:
    """A safety condition of one robot, raised by an event and cleared when the robot tracks again.

    Attributes:
        code: What happened (a :data:`~telerig.safety.SafetyCode`).
        robot: Robot (driver) name.
        reason: One line with numbers (the latest occurrence).
        suggested_action: One line for the operator.
        severity: ``warning`` or ``error``.
        since_ns: When it was raised, common clock [ns].
        count: Occurrences since it was raised.
        active: False in the message that clears it.
    """

    code: SafetyCode
    robot: str
    reason: str
    suggested_action: str
    severity: Severity
    since_ns: int
    count: int = 1
    active: bool = True

    def to_json(self) -> dict[str, JsonValue]:
        """The alert as JSON data (every attribute, by name)."""
        return {
            "code": self.code,
            "robot": self.robot,
            "reason": self.reason,
            "suggested_action": self.suggested_action,
            "severity": self.severity,
            "since_ns": self.since_ns,
            "count": self.count,
            "active": self.active,
        }


class SafetyAlerts:
    """Publishes every safety warning and error of a rig's robots, for the dashboard.

    Per robot and code, the first event raises an alert: published at once on
    ``telerig/v1/<rig>/safety/events`` (JSON: code, robot, reason, suggested_action, severity,
    time_ns, status, active) and listed in the retained ``telerig/v1/<rig>/safety/alerts``
    document (``{"type": "safety_alerts", "time_ns", "active_alerts": [...], "robots":
    {robot: status}}``). Repeats of an active alert are counted and republished on the events
    topic at most once per ``repeat_interval_s``. A warning clears at the first tick the robot
    tracks again (status ``ok``/``limited``) without that code; an error (e-stop, faults) clears
    when the robot leaves ``estopped`` (reset). Clearing publishes the alert with ``active: false``.

    Thread-safe: every robot's control thread calls :meth:`update`. Publishing never blocks
    (bus contract) and a failing publish is logged, never raised into a control loop.
    """

    def __init__(
        self,
        bus: Bus,
        rig: str,
        *,
        node: str = "safety",
        repeat_interval_s: float = 1.0,
    ) -> None:
        """Args:
        bus: Bus client to publish with.
        rig: Rig name (topic prefix).
        node: Node name in the topics.
        repeat_interval_s: Least time between two publications of one active alert [s].
        """
        self._bus = bus
        self.rig = rig
        self.events_topic = str(Topic(rig, node, EVENTS))
        self.alerts_topic = str(Topic(rig, node, ALERTS))
        self._repeat_ns = round(repeat_interval_s * 1e9)
        self._lock = threading.Lock()
        self._active: dict[tuple[str, SafetyCode], SafetyAlert] = {}
        self._published_ns: dict[tuple[str, SafetyCode], int] = {}
        self._status: dict[str, str] = {}

    def active(self) -> list[SafetyAlert]:
        """Alerts raised and not cleared, in the order they were raised."""
        with self._lock:
            return list(self._active.values())

    def update(self, robot: str, out: SafetyOutput, now_ns: int) -> None:
        """Take one tick's output of ``robot``'s chain: raise, repeat and clear its alerts."""
        if not out.events and self._status.get(robot) == out.status and not self._active:
            return  # nothing to do on a normal tick (checked without the lock; dicts are atomic)
        events: list[tuple[SafetyAlert, str]] = []
        with self._lock:
            changed = False  # the retained document changes with the alerts, not every status flip
            self._status[robot] = out.status
            seen: set[SafetyCode] = set()
            for event in out.events:
                severity = SEVERITY[event.code]
                if severity == "info":
                    continue
                seen.add(event.code)
                alert = self._raise(robot, event, severity, now_ns)
                key = (robot, event.code)
                if alert.count == 1 or now_ns - self._published_ns.get(key, 0) >= self._repeat_ns:
                    self._published_ns[key] = now_ns
                    events.append((alert, out.status))
                    changed = changed or alert.count == 1
            for key, alert in list(self._active.items()):
                if key[0] != robot or key[1] in seen:
                    continue
                if (alert.severity == "error" and out.status != "estopped") or (
                    alert.severity == "warning" and out.status in ("ok", "limited")
                ):
                    del self._active[key]
                    self._published_ns.pop(key, None)
                    events.append((replace(alert, active=False), out.status))
                    changed = True
            doc = self._alerts_json(now_ns) if changed else None
        for alert, status in events:
            payload: dict[str, JsonValue] = {**alert.to_json(), "time_ns": now_ns, "status": status}
            self._publish(self.events_topic, payload, qos=1, retain=False)
        if doc is not None:
            qos, retain = qos_for(ALERTS)
            self._publish(self.alerts_topic, doc, qos=qos, retain=retain)

    def _raise(self, robot: str, event: SafetyEvent, severity: Severity, now: int) -> SafetyAlert:
        key = (robot, event.code)
        old = self._active.get(key)
        if old is None:
            alert = SafetyAlert(event.code, robot, event.reason, event.suggested_action, severity, now)
            # Warnings (held input, stops on stale input) happen at every episode end when the devices
            # stop: the dashboard shows them; the console only gets errors.
            level = logging.ERROR if severity == "error" else logging.INFO
            log.log(level, "%s: %s: %s", robot, event.code, event.reason)
        else:
            alert = replace(old, reason=event.reason, count=old.count + 1)
        self._active[key] = alert
        return alert

    def _alerts_json(self, now: int) -> dict[str, JsonValue]:
        robots: dict[str, JsonValue] = dict(sorted(self._status.items()))
        return {
            "type": "safety_alerts",
            "time_ns": now,
            "active_alerts": [a.to_json() for a in self._active.values()],
            "robots": robots,
        }

    def _publish(self, topic: str, doc: dict[str, JsonValue], *, qos: int, retain: bool) -> None:
        try:
            self._bus.publish(topic, json.dumps(doc, separators=(",", ":")).encode(), qos=qos, retain=retain)
        except Exception:
            log.exception("publishing %s failed", topic)
