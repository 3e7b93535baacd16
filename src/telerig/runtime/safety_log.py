"""The episode's safety log: every fault, e-stop, reset and takeover while it records, from the bus.

Robots may run in other processes (robot hosts), so the log listens where every process reports:
the safety events (``telerig/v1/<rig>/<safety node>/events``), the operators' safety commands
(``telerig/v1/<rig>/safety/command``) and the devices' events (a client took a device over, was
refused, asks to). It also keeps the span of every per-device pause from the coordinator's
retained session status (``paused_devices``): ``device_paused`` and ``device_resumed`` entries
naming the device, and a ``device_paused`` at the start of an episode that begins with a device
paused, so the dataset knows which stretches of a device's stream drove nothing. A message that
does not parse is counted in :attr:`SafetyLog.malformed` and dropped.
"""

from __future__ import annotations

import json
import threading

from telerig.bus.base import Bus, Message
from telerig.bus.catalogue import COORDINATOR, EVENTS, SESSION
from telerig.bus.topics import Topic
from telerig.ir.types import now_ns
from telerig.runtime.session import SessionStatus
from telerig.safety.commands import parse_payload
from telerig.store.manifest_extra import SafetyEventRecord

__all__ = ["SafetyLog"]

#: Longest reason kept per entry [characters].
_MAX_REASON = 500
#: Most entries kept per episode (a flapping fault must not grow the manifest without bound).
_MAX_ENTRIES = 1000


class SafetyLog:
    """Collects the safety log of the running episode (between :meth:`begin` and :meth:`end`).

    Args:
        bus: A connected bus of this station.
        rig: Rig name.
    """

    def __init__(self, bus: Bus, rig: str) -> None:
        self._lock = threading.Lock()
        self._entries: list[SafetyEventRecord] = []
        self._running = False
        #: Messages dropped because they did not parse.
        self.malformed = 0
        #: Entries not kept past :data:`_MAX_ENTRIES` in the current episode.
        self.dropped = 0
        self._command_topic = str(Topic(rig, "safety", "command"))
        bus.subscribe(Topic.pattern(rig, "+", EVENTS), self._on_message, qos=1)
        bus.subscribe(self._command_topic, self._on_message, qos=1)
        self._paused: frozenset[str] = frozenset()
        bus.subscribe(str(Topic(rig, COORDINATOR, SESSION)), self._on_session, qos=1)

    def begin(self) -> None:
        """Start a new episode's log."""
        with self._lock:
            self._entries = []
            self.dropped = 0
            self._running = True
            t_ns = now_ns()
            for device in sorted(self._paused):
                self._add(
                    SafetyEventRecord(
                        t_ns=t_ns,
                        robot=None,
                        code="device_paused",
                        reason=f"{device}: paused before the episode",
                    )
                )

    def end(self) -> list[SafetyEventRecord]:
        """Stop logging; the episode's entries in time order."""
        with self._lock:
            self._running = False
            return sorted(self._entries, key=lambda e: e.t_ns)

    def _on_message(self, message: Message) -> None:
        if not self._running:
            return
        try:
            doc = json.loads(message.payload)
        except (ValueError, RecursionError):
            doc = None
        entry = self._entry(message.topic, doc) if isinstance(doc, dict) else None
        with self._lock:
            if doc is None or not isinstance(doc, dict):
                self.malformed += 1
            elif entry is not None and self._running:
                self._add(entry)

    def _on_session(self, message: Message) -> None:
        status = parse_payload(SessionStatus, message)
        with self._lock:
            if isinstance(status, str):
                self.malformed += 1
                return
            before, now = self._paused, frozenset(status.paused_devices)
            self._paused = now
            if not self._running:
                return
            why = (status.reason or "")[:_MAX_REASON]
            for code, devices in (("device_paused", now - before), ("device_resumed", before - now)):
                for device in sorted(devices):
                    self._add(
                        SafetyEventRecord(
                            t_ns=status.stamp_ns, robot=None, code=code, reason=f"{device}: {why}"
                        )
                    )

    def _add(self, entry: SafetyEventRecord) -> None:
        """Keep ``entry`` (the lock held) unless the episode's log is full."""
        if len(self._entries) < _MAX_ENTRIES:
            self._entries.append(entry)
        else:
            self.dropped += 1

    def _entry(self, topic: str, doc: dict[str, object]) -> SafetyEventRecord | None:
        stamp = doc.get("time_ns")
        t_ns = stamp if isinstance(stamp, int) else now_ns()
        robot = doc.get("robot")
        robot = robot if isinstance(robot, str) else None
        reason = str(doc.get("reason") or "")[:_MAX_REASON]
        if topic == self._command_topic:  # an operator's e-stop or reset
            command = doc.get("command")
            if command not in ("estop", "reset"):
                return None
            who = doc.get("operator")
            by = f" by {who}" if isinstance(who, str) else ""
            return SafetyEventRecord(
                t_ns=t_ns, robot=robot, code=f"operator_{command}", reason=f"{command}{by}: {reason}"
            )
        code = doc.get("code")
        if not isinstance(code, str):
            return None
        if "severity" not in doc:  # a device's event: takeover, refusal, confirmation asked
            device = topic.rsplit("/", 2)[-2]
            return SafetyEventRecord(t_ns=t_ns, robot=None, code=code[:64], reason=f"{device}: {reason}")
        if doc.get("severity") != "error":
            return None  # limits and holds are counted in safety_events, not listed
        if doc.get("active") is False:
            return SafetyEventRecord(t_ns=t_ns, robot=robot, code="reset", reason=f"{code} cleared")
        if doc.get("count", 1) != 1:
            return None  # a repeat of an active alert
        return SafetyEventRecord(t_ns=t_ns, robot=robot, code=code[:64], reason=reason)
