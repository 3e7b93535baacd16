"""InMemoryBus, topic matching, the topic schema and the bounded Inbox."""

from __future__ import annotations

import pytest

from telerig.bus.base import Bus, Inbox, Message, topic_matches
from telerig.bus.memory import InMemoryBus
from telerig.bus.topics import Topic, qos_for


def test_memory_bus_satisfies_the_bus_protocol() -> None:
    assert isinstance(InMemoryBus(), Bus)


def test_memory_bus_delivers_to_matching_subscribers_only() -> None:
    bus = InMemoryBus()
    hits, misses = Inbox(), Inbox()
    bus.subscribe("telerig/v1/demo/+/pose", hits)
    bus.subscribe("telerig/v1/other/#", misses)
    bus.publish("telerig/v1/demo/vr0/pose", b"p")
    assert [(m.topic, m.payload) for m in hits.drain()] == [("telerig/v1/demo/vr0/pose", b"p")]
    assert len(misses) == 0
    assert (bus.stats.published, bus.stats.delivered) == (1, 1)


def test_memory_bus_replays_retained_to_late_subscriber_and_empty_payload_clears() -> None:
    bus = InMemoryBus()
    bus.publish("telerig/v1/demo/coord/session", b"recording", qos=1, retain=True)
    bus.publish("telerig/v1/demo/coord/status", b"ok", qos=1, retain=True)
    bus.publish("telerig/v1/demo/coord/status", b"", qos=1, retain=True)
    late = Inbox()
    bus.subscribe("telerig/v1/demo/coord/+", late)
    assert [(m.topic, m.payload) for m in late.drain()] == [("telerig/v1/demo/coord/session", b"recording")]


def test_memory_bus_counts_raising_handler_and_keeps_delivering() -> None:
    bus = InMemoryBus()

    def broken(message: Message) -> None:
        raise RuntimeError("handler bug")

    inbox = Inbox()
    bus.subscribe("t", broken)
    bus.subscribe("t", inbox)
    bus.publish("t", b"1")
    assert len(inbox) == 1
    assert bus.stats.handler_errors == 1


def test_memory_bus_cancel_is_idempotent_and_stops_delivery() -> None:
    bus = InMemoryBus()
    inbox = Inbox()
    sub = bus.subscribe("t", inbox)
    sub.cancel()
    sub.cancel()
    bus.publish("t", b"1")
    assert len(inbox) == 0


def test_memory_bus_close_is_idempotent_and_drops_later_publishes() -> None:
    bus = InMemoryBus()
    inbox = Inbox()
    bus.subscribe("t", inbox)
    bus.close()
    bus.close()
    bus.publish("t", b"1")
    assert (len(inbox), bus.stats.published) == (0, 0)


@pytest.mark.parametrize(
    ("pattern", "topic", "expected"),
    [
        ("a/b/c", "a/b/c", True),
        ("a/b/c", "a/b", False),
        ("a/b", "a/b/c", False),
        ("a/+/c", "a/x/c", True),
        ("a/+/c", "a/x/y/c", False),
        ("a/+", "a/", True),  # an empty level is a level
        ("+/+", "a/b", True),
        ("a/#", "a/b/c", True),
        ("a/#", "a", True),  # '#' also matches the parent level
        ("#", "anything/at/all", True),
        ("a/#", "b/c", False),
    ],
)
def test_topic_matches(pattern: str, topic: str, expected: bool) -> None:
    assert topic_matches(pattern, topic) is expected


def test_topic_formats_and_parses_round_trip() -> None:
    topic = Topic("demo", "vr0", "controller_right")
    assert str(topic) == "telerig/v1/demo/vr0/controller_right"
    assert Topic.parse(str(topic)) == topic


@pytest.mark.parametrize(
    "text",
    ["telerig/v2/demo/vr0/pose", "telerig/v1/demo/vr0", "other/v1/demo/vr0/pose", "telerig/v1/demo/vr 0/x"],
)
def test_topic_parse_rejects_other_shapes(text: str) -> None:
    with pytest.raises(ValueError, match=r"telerig|topic"):
        Topic.parse(text)


def test_topic_rejects_wildcards_in_names() -> None:
    with pytest.raises(ValueError, match="node '\\+'"):
        Topic("demo", "+", "pose")


def test_topic_pattern_defaults_to_every_node_and_stream() -> None:
    assert Topic.pattern("demo") == "telerig/v1/demo/+/+"
    assert topic_matches(Topic.pattern("demo", stream="session"), "telerig/v1/demo/coord/session")


def test_qos_for_state_streams_is_retained_qos1() -> None:
    assert qos_for("session") == (1, True)
    assert qos_for("controller_right") == (0, False)


def test_inbox_overflow_drops_oldest_and_counts() -> None:
    inbox = Inbox(maxlen=2)
    for i in range(5):
        inbox(Message("t", bytes([i]), i))
    assert inbox.overflow == 3
    assert [m.payload for m in inbox.drain()] == [b"\x03", b"\x04"]


def test_inbox_get_returns_none_on_timeout() -> None:
    assert Inbox().get(timeout=0.01) is None


def test_inbox_rejects_non_positive_maxlen() -> None:
    with pytest.raises(ValueError, match="maxlen"):
        Inbox(maxlen=0)
