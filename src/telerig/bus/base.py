"""The bus interface every transport implements, and the bounded inbox nodes read from."""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

__all__ = ["Bus", "BusStats", "Inbox", "Message", "MessageHandler", "Subscription", "topic_matches"]

#: Default bound of every client-side queue (inboxes, outgoing queues).
DEFAULT_QUEUE_SIZE = 64


@dataclass(frozen=True, slots=True)
class Message:
    """One message received from the bus.

    Attributes:
        topic: Full topic, e.g. ``telerig/v1/demo/vr0/controller_right``.
        payload: Encoded bytes (a ``telerig.v1.Envelope`` for IR streams).
        received_ns: Time the bus client received it, common clock [ns].
    """

    topic: str
    payload: bytes
    received_ns: int


MessageHandler = Callable[[Message], None]


@dataclass(slots=True)
class BusStats:
    """Counters of one bus client. Overflow counts messages dropped by full bounded queues."""

    published: int = 0
    delivered: int = 0
    publish_overflow: int = 0
    inbox_overflow: int = 0
    handler_errors: int = 0
    reconnects: int = 0


class Subscription(Protocol):
    """Handle returned by :meth:`Bus.subscribe`; ``cancel()`` is idempotent."""

    def cancel(self) -> None: ...


@runtime_checkable
class Bus(Protocol):
    """Publish/subscribe transport shared by MQTT and the in-memory bus.

    Handlers run on the transport's delivery thread and must not block; nodes
    hand messages to an :class:`Inbox` and process them on their own thread.
    """

    @property
    def stats(self) -> BusStats: ...

    def publish(self, topic: str, payload: bytes, *, qos: int = 0, retain: bool = False) -> None:
        """Send ``payload`` on ``topic``. Never blocks; a full outgoing queue drops and counts."""
        ...

    def subscribe(self, pattern: str, handler: MessageHandler, *, qos: int = 0) -> Subscription:
        """Call ``handler`` for every message whose topic matches ``pattern`` (MQTT wildcards)."""
        ...

    def close(self) -> None:
        """Disconnect and release resources. Idempotent."""
        ...


def topic_matches(pattern: str, topic: str) -> bool:
    """Return whether ``topic`` matches an MQTT subscription ``pattern`` (``+`` and ``#`` wildcards)."""
    p_parts = pattern.split("/")
    t_parts = topic.split("/")
    for i, p in enumerate(p_parts):
        if p == "#":
            return True
        if i >= len(t_parts):
            return False
        if p != "+" and p != t_parts[i]:
            return False
    return len(p_parts) == len(t_parts)


@dataclass(slots=True)
class Inbox:
    """A bounded FIFO between a bus delivery thread and a node thread.

    When full, the oldest message is dropped and counted in ``overflow`` (a
    control node wants the newest sample, not a backlog).
    """

    maxlen: int = DEFAULT_QUEUE_SIZE
    overflow: int = 0
    _items: deque[Message] = field(init=False)
    _cond: threading.Condition = field(init=False, default_factory=threading.Condition)

    def __post_init__(self) -> None:
        if self.maxlen < 1:
            raise ValueError(f"maxlen must be >= 1, got {self.maxlen}")
        self._items = deque()

    def __call__(self, message: Message) -> None:
        with self._cond:
            if len(self._items) >= self.maxlen:
                self._items.popleft()
                self.overflow += 1
            self._items.append(message)
            self._cond.notify()

    def get(self, timeout: float | None = None) -> Message | None:
        """Pop the oldest message, waiting up to ``timeout`` seconds; ``None`` on timeout."""
        with self._cond:
            if not self._items and not self._cond.wait_for(lambda: bool(self._items), timeout):
                return None
            return self._items.popleft()

    def drain(self) -> list[Message]:
        """Pop every queued message without waiting."""
        with self._cond:
            items = list(self._items)
            self._items.clear()
            return items

    def __len__(self) -> int:
        return len(self._items)
