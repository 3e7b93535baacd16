"""Topic names `telerig/v1/<rig>/<node>/<stream>`, and the lenient accessors log readers use."""

from __future__ import annotations

import pytest

from telerig.bus.topics import Topic, node_of, stream_of


def test_a_topic_round_trips() -> None:
    topic = Topic("demo", "arm0", "joint_state")
    assert Topic.parse(str(topic)) == topic
    assert (node_of(str(topic)), stream_of(str(topic))) == ("arm0", "joint_state")


@pytest.mark.parametrize(
    "text",
    [
        "",
        "telerig/v1/demo/arm0",
        "telerig/v2/demo/arm0/x",
        "other/v1/a/b/c",
        "telerig/v1/a/b c/d",
        "x" * 10_000,
    ],
)
def test_other_shapes_parse_to_none_and_keep_their_name_as_node(text: str) -> None:
    assert Topic.try_parse(text) is None
    assert stream_of(text) == ""
    assert node_of(text) == text
