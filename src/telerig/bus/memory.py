"""In-process bus with the same interface as MQTT, for unit tests and single-process tools."""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass

from telerig.bus.base import BusStats, Message, MessageHandler, topic_matches
from telerig.ir.types import now_ns

__all__ = ["InMemoryBus"]

log = logging.getLogger(__name__)


@dataclass(eq=False, slots=True)
class _MemorySubscription:
    bus: InMemoryBus
    pattern: str
    handler: MessageHandler

    def cancel(self) -> None:
        self.bus._remove(self)


class InMemoryBus:
    """Delivers synchronously on the publisher's thread; retained messages replay on subscribe.

    A handler that raises is counted in ``stats.handler_errors`` and logged; it
    never breaks the publisher, like a remote subscriber could not.
    """

    def __init__(self) -> None:
        self._subs: list[_MemorySubscription] = []
        self._retained: dict[str, bytes] = {}
        self._lock = threading.Lock()
        self._closed = False
        self._stats = BusStats()

    @property
    def stats(self) -> BusStats:
        return self._stats

    def publish(self, topic: str, payload: bytes, *, qos: int = 0, retain: bool = False) -> None:
        if self._closed:
            return
        with self._lock:
            if retain:
                if payload:
                    self._retained[topic] = payload
                else:
                    self._retained.pop(topic, None)
            subs = [s for s in self._subs if topic_matches(s.pattern, topic)]
        self._stats.published += 1
        message = Message(topic, payload, now_ns())
        for sub in subs:
            self._deliver(sub, message)

    def subscribe(self, pattern: str, handler: MessageHandler, *, qos: int = 0) -> _MemorySubscription:
        sub = _MemorySubscription(self, pattern, handler)
        with self._lock:
            self._subs.append(sub)
            retained = [(t, p) for t, p in self._retained.items() if topic_matches(pattern, t)]
        for topic, payload in retained:
            self._deliver(sub, Message(topic, payload, now_ns()))
        return sub

    def close(self) -> None:
        self._closed = True
        with self._lock:
            self._subs.clear()

    def _deliver(self, sub: _MemorySubscription, message: Message) -> None:
        try:
            sub.handler(message)
            self._stats.delivered += 1
        except Exception:
            self._stats.handler_errors += 1
            log.exception("handler for %s failed on %s", sub.pattern, message.topic)

    def _remove(self, sub: _MemorySubscription) -> None:
        with self._lock:
            if sub in self._subs:
                self._subs.remove(sub)
