"""A robot's tick as the messages its streams would have been: unbundle and picking."""

from __future__ import annotations

import pytest

from telerig.bus.base import Message
from telerig.bus.ticks import picking, unbundle
from telerig.errors import WireError
from telerig.ir import wire

TICK = "telerig/v1/rig/arm0/tick"


def _tick(*parts: tuple[str, bytes]) -> Message:
    return Message(TICK, wire.encode_bundle(list(parts)), 123)


def test_unbundle_gives_each_part_its_streams_topic_and_the_ticks_receive_time() -> None:
    assert unbundle(_tick(("joint_state", b"s"), ("residual", b"r"))) == [
        Message("telerig/v1/rig/arm0/joint_state", b"s", 123),
        Message("telerig/v1/rig/arm0/residual", b"r", 123),
    ]


def test_picking_passes_on_the_named_streams_only() -> None:
    got: list[Message] = []
    handle = picking({"joint_state", "base_pose"}, got.append)
    handle(_tick(("joint_command_sent", b"c"), ("joint_state", b"s"), ("base_pose", b"b")))
    handle(Message("telerig/v1/rig/arm0/joint_state", b"not a tick", 1))  # another stream: ignored
    assert [(m.topic.rsplit("/", 1)[1], m.payload) for m in got] == [
        ("joint_state", b"s"),
        ("base_pose", b"b"),
    ]


def test_garbage_raises_for_the_callers_guard() -> None:
    handle = picking({"joint_state"}, lambda m: None)
    with pytest.raises(WireError, match="cannot decode Bundle"):
        handle(Message(TICK, b"\xff\x00garbage", 1))
    with pytest.raises(WireError, match="1 to 64 parts"):
        unbundle(Message(TICK, b"\x08\x01", 1))
    with pytest.raises(ValueError, match="not a tick topic"):
        unbundle(Message("telerig/v1/rig/arm0/joint_state", wire.encode_bundle([("x", b"1")]), 1))


def test_a_tick_over_the_catalogues_size_is_refused_unparsed() -> None:
    # 300 kB of valid parts: a robot's tick is at most the catalogue's 256 KiB, whoever reads it.
    big = _tick(*[("joint_state", b"\x08" * 5000)] * 60)
    assert len(big.payload) > 256 * 1024
    with pytest.raises(WireError, match=r"a tick of \d+ bytes, limit 262144"):
        unbundle(big)
    with pytest.raises(WireError, match="limit 262144"):
        picking({"joint_state"}, lambda m: None)(big)
