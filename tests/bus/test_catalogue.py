"""The stream catalogue: one vocabulary for every stream, its payload kind, QoS and publisher role."""

from __future__ import annotations

import numpy as np
import pytest

from telerig.bus import catalogue
from telerig.bus.catalogue import (
    CATALOGUE,
    DEVICE_SAMPLE,
    NodeRole,
    PayloadKind,
    RigNodes,
    device_stream,
    qos_for,
    spec_by_name,
    stream_spec,
)
from telerig.ir.types import (
    BodySkeleton,
    CameraFrame,
    ControllerState,
    GripperCommand,
    JointCommand,
    JointState,
    Pose,
    Stamp,
    Twist,
)


def _stamp(source: str) -> Stamp:
    return Stamp(source, 0, 0, 0)


def test_every_stream_name_used_by_a_node_is_catalogued() -> None:
    """The modules that publish keep constants for their streams: each must be in the catalogue."""
    from telerig.cameras.preview import PREVIEW_STREAM
    from telerig.retarget.fixtures import FixtureSet
    from telerig.retarget.scaling import ScaleKnob
    from telerig.retarget.whole_body import WholeBodySwitches
    from telerig.runtime import device_node, session, streams
    from telerig.safety import alerts, commands

    used = {
        (NodeRole.CAMERA, PREVIEW_STREAM),
        (NodeRole.DEVICE, device_node.HEALTH),
        (NodeRole.SAFETY, commands.HALT),
        (NodeRole.SAFETY, commands.COMMAND),
        (NodeRole.SAFETY, alerts.ALERTS),
        (NodeRole.SAFETY, alerts.EVENTS),
        (NodeRole.COORDINATOR, session.SESSION),
        (NodeRole.COORDINATOR, session.COMMAND),
        (NodeRole.STATION, session.SESSION),
        *((NodeRole.ROBOT, aid.stream) for aid in (ScaleKnob, FixtureSet, WholeBodySwitches)),
        *((NodeRole.ROBOT, f"{aid.stream}_command") for aid in (ScaleKnob, FixtureSet, WholeBodySwitches)),
        *((NodeRole.ROBOT, getattr(streams, n)) for n in ("JOINT_SENT", "RESIDUAL", "STATUS")),
    }
    missing = [(role.value, name) for role, name in used if stream_spec(role, name) is None]
    assert missing == []


def test_names_are_unique_per_role_and_valid_topic_levels() -> None:
    keys = [(s.role, s.name) for s in CATALOGUE]
    assert len(keys) == len(set(keys))
    assert all(s.name == DEVICE_SAMPLE or s.name.replace("_", "").isalnum() for s in CATALOGUE)


def test_qos_is_kept_for_the_state_streams() -> None:
    for state in ("session", "status", "alerts", "health", "motion_scale", "fixture"):
        assert qos_for(state) == (1, True), state
    assert qos_for("right_controller") == (0, False)
    assert qos_for(catalogue.JOINT_SENT) == (0, False)


def test_only_the_requested_commands_carry_an_inputs_seq_that_counts_no_loss() -> None:
    # A requested command keeps the stamp of the input it answers; the loop may act on a newer
    # input in place of an older one, so its seq skips without a loss. Every other stream's own seq
    # counts its losses (the recorder and the health monitor both ask loss_seq).
    by_input = {s.name for s in CATALOGUE if s.stamped_by_input}
    assert by_input == {catalogue.JOINT_REQUESTED, catalogue.GRIPPER_REQUESTED, catalogue.BASE_REQUESTED}
    for spec in CATALOGUE:
        assert spec.loss_seq(7) == (None if spec.name in by_input else 7)


def test_every_stream_has_a_kind_a_size_limit_and_ir_types_only_when_ir() -> None:
    for spec in CATALOGUE:
        assert spec.max_bytes > 0
        assert (spec.kind is PayloadKind.IR) == bool(spec.ir_types)
    assert stream_spec(NodeRole.ROBOT, catalogue.JOINT_STATE).ir_types == (JointState,)  # type: ignore[union-attr]
    assert stream_spec(NodeRole.CAMERA, catalogue.CAMERA_FRAMES).ir_types == (CameraFrame,)  # type: ignore[union-attr]


def test_a_device_publishes_any_part_stream_but_not_a_robots() -> None:
    spec = stream_spec(NodeRole.DEVICE, "wand")
    assert spec is not None
    assert spec.name == DEVICE_SAMPLE
    # A device may publish joint targets on its own streams (a policy's action, issue 16), never
    # a measured state; a robot's streams are the robot node's (the broker's ACL keeps devices off).
    assert JointCommand in spec.ir_types
    assert JointState not in spec.ir_types
    assert stream_spec(NodeRole.DEVICE, "health") is not None
    assert stream_spec(NodeRole.CAMERA, "right_controller") is None


def test_rig_nodes_resolve_roles_and_refuse_strangers() -> None:
    nodes = RigNodes.of(devices=["vr0"], robots=["arm0"], cameras=["cam0"], stations=["st0"])
    assert nodes.spec("arm0", catalogue.JOINT_SENT) is not None
    assert nodes.spec("intruder", catalogue.JOINT_SENT) is None
    assert nodes.spec("vr0", catalogue.JOINT_SENT).role is NodeRole.DEVICE  # type: ignore[union-attr]
    assert nodes.spec("safety-arm0", "halt") is not None
    assert nodes.spec("recorder-st1", "alerts") is not None
    assert nodes.spec("st0", "clock_ping") is not None
    assert nodes.spec("coordinator", "joint_state") is None


def test_by_name_without_nodes() -> None:
    assert spec_by_name("wbc_mode").kind is PayloadKind.JSON  # type: ignore[union-attr]
    assert spec_by_name("status").kind is PayloadKind.TEXT  # type: ignore[union-attr]
    assert spec_by_name("preview").recorded is False  # type: ignore[union-attr]
    assert spec_by_name("head").role is NodeRole.DEVICE  # type: ignore[union-attr]


@pytest.mark.parametrize(
    ("sample", "stream"),
    [
        (
            ControllerState(_stamp("vr0/r"), "right", np.zeros(3), np.array([1.0, 0, 0, 0]), "w"),
            "right_controller",
        ),
        (Pose(_stamp("quest/head"), np.zeros(3), np.array([1.0, 0, 0, 0]), "w"), "head"),
        (Pose(_stamp("mocap/Rigid Body 1"), np.zeros(3), np.array([1.0, 0, 0, 0]), "w"), "Rigid_Body_1"),
        (Pose(_stamp("solo"), np.zeros(3), np.array([1.0, 0, 0, 0]), "w"), "pose"),
        (Twist(_stamp("sm0"), np.zeros(3), np.zeros(3), "w"), "twist"),
        (
            BodySkeleton(
                _stamp("bvh0/body"), ("hips",), np.zeros((1, 3)), np.tile([1.0, 0, 0, 0], (1, 1)), "w"
            ),
            "body",
        ),
    ],
)
def test_device_stream_names(sample: object, stream: str) -> None:
    assert device_stream(sample) == stream  # type: ignore[arg-type]


def test_device_stream_refuses_robot_samples() -> None:
    with pytest.raises(ValueError, match="not a device sample"):
        device_stream(JointState(_stamp("arm0"), ("j",), np.zeros(1), np.zeros(1)))


def test_a_policy_device_streams_its_joint_targets_and_gripper() -> None:
    assert device_stream(JointCommand(_stamp("pi0/joints"), ("j",), np.zeros(1))) == "joints"
    assert device_stream(JointCommand(_stamp("pi0"), ("j",), np.zeros(1))) == "joints"
    assert device_stream(GripperCommand(_stamp("pi0"), 0.5)) == "gripper"
