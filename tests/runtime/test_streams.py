"""Stream names: which bus stream (rig binding ``part``) each device sample travels on."""

from __future__ import annotations

import numpy as np
import pytest

from telerig.bus.topics import Topic
from telerig.config.load import load_rig, shipped_rig_path, shipped_rigs
from telerig.ir.types import BodySkeleton, ControllerState, HandPose, Pose, Stamp, Twist
from telerig.runtime.streams import JOINT_SENT, device_stream, rig_nodes

Q = np.array([1.0, 0.0, 0.0, 0.0])


def _stamp(source: str) -> Stamp:
    return Stamp(source, 0, 1, 1)


@pytest.mark.parametrize(
    ("sample", "stream"),
    [
        (ControllerState(_stamp("vr0/right"), "right", np.zeros(3), Q, "operator"), "right_controller"),
        (
            HandPose(_stamp("g/left"), "left", np.zeros(3), Q, np.zeros((21, 3)), np.ones(21), "operator"),
            "left_hand",
        ),
        (Pose(_stamp("quest/head"), np.zeros(3), Q, "operator"), "head"),
        (Pose(_stamp("mocap/Rigid Body 1"), np.zeros(3), Q, "mocap"), "Rigid_Body_1"),
        (Pose(_stamp("tracker"), np.zeros(3), Q, "mocap"), "pose"),
        (BodySkeleton(_stamp("bvh/actor"), ("hips",), np.zeros((1, 3)), np.array([Q]), "operator"), "actor"),
        (Twist(_stamp("sm"), np.zeros(3), np.zeros(3), "operator"), "twist"),
    ],
)
def test_stream_names_are_valid_topic_levels(sample: object, stream: str) -> None:
    name = device_stream(sample)  # type: ignore[arg-type]
    assert name == stream
    Topic("rig", "dev", name)  # raises on an invalid level


@pytest.mark.parametrize("name", shipped_rigs())
def test_every_node_of_a_shipped_rig_has_its_role(name: str) -> None:
    config = load_rig(shipped_rig_path(name))
    nodes = rig_nodes(config)
    for robot in config.robots:
        assert nodes.spec(robot.id, JOINT_SENT) is not None
    for device in config.devices:
        assert nodes.spec(device.id, "health") is not None
    for station in config.stations:
        assert nodes.spec(station.id, "clock_ping") is not None
    assert nodes.spec("not-a-node", JOINT_SENT) is None
