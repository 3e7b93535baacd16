"""A device node hands an observing device (the scripted operator) only the watched robot's decodable
samples: garbage, forged sources and oversized payloads as the object_pose of <robot>/tick, and ticks
that are no Bundle, are counted and dropped."""

from __future__ import annotations

import time

import numpy as np

from telerig.bus.memory import InMemoryBus
from telerig.bus.topics import Topic
from telerig.config import load_rig
from telerig.devices.pick_place.operator import ScriptedPickPlace
from telerig.ir import wire
from telerig.ir.types import Pose, Stamp
from telerig.runtime.device_node import DeviceNode

TICK = str(Topic("pick_place", "arm0", "tick"))


def _tick(*object_poses: bytes) -> bytes:
    """A control tick of arm0 carrying ``object_poses`` (one part each)."""
    return wire.encode_bundle([("object_pose", pose) for pose in object_poses])


def _pose(source: str, position: tuple[float, float, float], seq: int) -> bytes:
    t = time.time_ns()
    return wire.encode(
        Pose(Stamp(source, seq, t, t), np.array(position), np.array([1.0, 0.0, 0.0, 0.0]), "world")
    )


def test_garbage_and_forged_object_poses_are_dropped_and_real_ones_planned_from() -> None:
    rig = load_rig("pick_place")
    device = rig.devices[0].build()
    assert isinstance(device, ScriptedPickPlace)
    bus = InMemoryBus()
    node = DeviceNode(rig.name, device, bus, health_period_s=None)
    node.start()
    try:
        garbage = [
            b"",
            b"\x00" * 7,
            b"not protobuf at all \xff\xfe",
            b"\x0a" * 70_000,  # oversized nonsense
            _pose("arm0/cube", (0.5, 0.1, 0.82), 0)[:-3],  # truncated
            _pose("vr0/cube", (0.5, 0.1, 0.82), 0),  # another node's sample on arm0's topic
            _pose("arm01/cube", (0.5, 0.1, 0.82), 0),  # a prefix is not the node
        ]
        for payload in garbage:
            bus.publish(TICK, _tick(payload))
        # Not a tick at all, or one over the catalogue's 256 KiB (60 parts, dropped once, unparsed).
        not_ticks = [b"", b"\x08\x01", b"\xff" * 64, _tick(b"x")[:-2], _tick(*[b"\x0a" * 5000] * 60)]
        for payload in not_ticks:
            bus.publish(TICK, payload)
        assert node.observed_dropped == len(garbage) + len(not_ticks)
        assert device.plan is None
        # Values that decode but make no sense to the operator are ignored by it, not planned from.
        bus.publish(TICK, _tick(_pose("arm0/cube", (1e6, 0.0, 0.0), 1)))
        assert device.ignored == 1
        for i in range(40):
            cube, target = (
                _pose("arm0/cube", (0.5, 0.1, 0.82), 2 + i),
                _pose("arm0/target", (0.46, -0.15, 0.8), 2 + i),
            )
            bus.publish(TICK, _tick(cube, target))
            time.sleep(0.005)
        deadline = time.monotonic() + 2.0
        while device.plan is None and time.monotonic() < deadline:
            time.sleep(0.01)
        assert device.plan is not None
        assert node.observed_dropped == len(garbage) + len(not_ticks)
    finally:
        node.stop()
    # Stopped: the subscription is gone, nothing more reaches the device.
    bus.publish(TICK, b"garbage after stop")
    assert node.observed_dropped == len(garbage) + len(not_ticks)
