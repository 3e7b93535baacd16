"""Topic schema: ``telerig/v1/<rig>/<node>/<stream>``; each stream's QoS is in the catalogue."""

from __future__ import annotations

import re
from dataclasses import dataclass

from telerig.bus.catalogue import qos_for

__all__ = ["TOPIC_VERSION", "Topic", "node_of", "qos_for", "stream_of"]

TOPIC_VERSION = "v1"
_NAME = re.compile(r"^[A-Za-z0-9_.\-]+$")


@dataclass(frozen=True, slots=True)
class Topic:
    """A parsed telerig topic."""

    rig: str
    node: str
    stream: str

    def __post_init__(self) -> None:
        for part, value in (("rig", self.rig), ("node", self.node), ("stream", self.stream)):
            if not _NAME.match(value):
                raise ValueError(
                    f"topic {part} {value!r} must be non-empty and use only letters, digits, '_', '-', '.'"
                )

    def __str__(self) -> str:
        return f"telerig/{TOPIC_VERSION}/{self.rig}/{self.node}/{self.stream}"

    @classmethod
    def parse(cls, topic: str) -> Topic:
        """Parse ``telerig/v1/<rig>/<node>/<stream>``; raises ``ValueError`` on any other shape."""
        parts = topic.split("/")
        if len(parts) != 5 or parts[0] != "telerig" or parts[1] != TOPIC_VERSION:
            raise ValueError(f"not a telerig/{TOPIC_VERSION} topic: {topic!r}")
        return cls(parts[2], parts[3], parts[4])

    @staticmethod
    def pattern(rig: str, node: str = "+", stream: str = "+") -> str:
        """Subscription pattern for a rig, optionally narrowed to a node and stream."""
        return f"telerig/{TOPIC_VERSION}/{rig}/{node}/{stream}"

    @classmethod
    def try_parse(cls, topic: str) -> Topic | None:
        """:meth:`parse`, or ``None`` for a topic of another shape."""
        try:
            return cls.parse(topic)
        except ValueError:
            return None


def stream_of(topic: str) -> str:
    """The stream name of a telerig topic (``joint_state``); ``""`` for a topic of another shape."""
    parsed = Topic.try_parse(topic)
    return "" if parsed is None else parsed.stream


def node_of(topic: str) -> str:
    """The node name of a telerig topic (``arm0``); the topic itself for one of another shape."""
    parsed = Topic.try_parse(topic)
    return topic if parsed is None else parsed.node
