"""VrFrame datagrams: decoding, frame conversion, hand mapping, rejection of bad input, sequencing."""

from __future__ import annotations

import math

import numpy as np
import pytest

from telerig.devices.scripted import POINTING_DOWN
from telerig.devices.udp_vr.fake import FakeVrSender, typical_payload
from telerig.devices.udp_vr.protocol import (
    MAX_DATAGRAM_BYTES,
    OPENXR_HAND_JOINTS,
    OPENXR_TO_MEDIAPIPE,
    SequenceFilter,
    VrDatagram,
    datagram_samples,
    decode_datagram,
)
from telerig.errors import WireError
from telerig.ir._pb import vr_stream_pb2 as pb
from telerig.ir.frames import (
    openxr_to_operator_body_quat,
    openxr_to_operator_points,
    quat_angle,
    quat_from_axis_angle,
    quat_rotate,
)
from telerig.ir.types import ControllerState, HandPose, Pose, Sample, Stamp

S = math.sqrt(0.5)


def samples_of(data: bytes) -> list[Sample]:
    return datagram_samples(decode_datagram(data), lambda src, conf: Stamp(f"vr0/{src}", 0, 0, 0, 0, conf))


def frame(**fields: object) -> pb.VrFrame:
    msg = pb.VrFrame(format_version=1, stream_id=7, seq=1, device_time_ns=1)
    for key, value in fields.items():
        setattr(msg, key, value)
    return msg


def controller_frame(q_xyzw: tuple[float, float, float, float], **controller: object) -> bytes:
    msg = frame()
    msg.right.tracked = True
    msg.right.grip.py = 1.0
    msg.right.grip.qx, msg.right.grip.qy, msg.right.grip.qz, msg.right.grip.qw = q_xyzw
    for key, value in controller.items():
        setattr(msg.right, key, value)
    return msg.SerializeToString()


def xyzw(q_wxyz: np.ndarray) -> tuple[float, float, float, float]:
    return (float(q_wxyz[1]), float(q_wxyz[2]), float(q_wxyz[3]), float(q_wxyz[0]))


def test_typical_payload_yields_head_both_controllers_and_both_hands() -> None:
    samples = samples_of(typical_payload())
    assert [(type(s).__name__, s.stamp.source_id) for s in samples] == [
        ("Pose", "vr0/head"),
        ("ControllerState", "vr0/left"),
        ("ControllerState", "vr0/right"),
        ("HandPose", "vr0/left_hand"),
        ("HandPose", "vr0/right_hand"),
    ]
    assert all(s.frame_id == "operator" for s in samples)  # type: ignore[union-attr]


def test_typical_payload_fits_the_size_limit() -> None:
    assert 1000 < len(typical_payload()) <= MAX_DATAGRAM_BYTES


def test_head_at_stage_height_lands_at_operator_height() -> None:
    head = samples_of(typical_payload())[0]
    assert isinstance(head, Pose)
    np.testing.assert_allclose(head.position, [0.0, 0.0, 1.6], atol=1e-6)


def test_head_orientation_matches_the_frames_module() -> None:
    msg = pb.VrFrame.FromString(typical_payload())
    h = msg.head
    head = samples_of(typical_payload())[0]
    assert isinstance(head, Pose)
    expected = openxr_to_operator_body_quat((h.qx, h.qy, h.qz, h.qw))
    assert quat_angle(head.orientation, expected / np.linalg.norm(expected)) < 1e-6


def test_controller_at_openxr_rest_points_forward_with_top_up() -> None:
    (state,) = samples_of(controller_frame((0.0, 0.0, 0.0, 1.0)))
    assert isinstance(state, ControllerState)
    np.testing.assert_allclose(
        quat_rotate(state.orientation, np.array([0.0, 0.0, 1.0])), [1, 0, 0], atol=1e-9
    )
    np.testing.assert_allclose(
        quat_rotate(state.orientation, np.array([1.0, 0.0, 0.0])), [0, 0, 1], atol=1e-9
    )


def test_controller_pointing_down_matches_the_scripted_convention() -> None:
    # Grip -z (pointing) down and +y (top) forward: -90 degrees about stage x.
    (state,) = samples_of(controller_frame((-S, 0.0, 0.0, S)))
    assert isinstance(state, ControllerState)
    assert quat_angle(state.orientation, np.array(POINTING_DOWN)) < 1e-6


def test_controller_position_is_converted_to_operator_axes() -> None:
    msg = pb.VrFrame.FromString(controller_frame((0.0, 0.0, 0.0, 1.0)))
    msg.right.grip.px, msg.right.grip.py, msg.right.grip.pz = 0.2, 1.1, -0.4
    (state,) = samples_of(msg.SerializeToString())
    assert isinstance(state, ControllerState)
    np.testing.assert_allclose(state.position, openxr_to_operator_points([0.2, 1.1, -0.4]), atol=1e-6)
    np.testing.assert_allclose(state.position, [0.4, -0.2, 1.1], atol=1e-6)


def test_controller_analogs_and_buttons_are_carried() -> None:
    data = controller_frame(
        (0.0, 0.0, 0.0, 1.0),
        buttons=(1 << pb.VR_BUTTON_BIT_A) | (1 << pb.VR_BUTTON_BIT_THUMBSTICK) | (1 << 30),
        trigger=0.25,
        squeeze=1.0,
        thumbstick_x=-0.5,
        thumbstick_y=1.0,
    )
    (state,) = samples_of(data)
    assert isinstance(state, ControllerState)
    assert state.buttons == {"a", "thumbstick"}  # the unknown bit 30 is ignored
    assert (state.trigger, state.grip) == (0.25, 1.0)
    np.testing.assert_allclose(state.joystick, [-0.5, 1.0])


def test_controller_analog_float_noise_is_clipped() -> None:
    (state,) = samples_of(controller_frame((0.0, 0.0, 0.0, 1.0), trigger=1.0004, thumbstick_x=-1.0004))
    assert isinstance(state, ControllerState)
    assert state.trigger == 1.0
    assert state.joystick[0] == -1.0


def test_mediapipe_mapping_picks_the_named_openxr_joints() -> None:
    names = [OPENXR_HAND_JOINTS[j] for j in OPENXR_TO_MEDIAPIPE]
    assert len(names) == 21
    assert names[0] == "wrist"
    assert names[1:5] == ["thumb_metacarpal", "thumb_proximal", "thumb_distal", "thumb_tip"]
    assert names[5:9] == ["index_proximal", "index_intermediate", "index_distal", "index_tip"]
    assert names[20] == "little_tip"
    assert len(OPENXR_HAND_JOINTS) == 26


def test_hand_keypoints_are_the_mapped_joints_in_operator_axes() -> None:
    msg = pb.VrFrame.FromString(typical_payload())
    joints = np.array(msg.right_hand.joint_positions).reshape(26, 3)
    hand = samples_of(typical_payload())[-1]
    assert isinstance(hand, HandPose)
    assert hand.handedness == "right"
    np.testing.assert_allclose(hand.keypoints, openxr_to_operator_points(joints[list(OPENXR_TO_MEDIAPIPE)]))
    np.testing.assert_allclose(hand.wrist_position, hand.keypoints[0])
    q = msg.right_hand.joint_orientations[4:8]
    expected = openxr_to_operator_body_quat(q)
    assert quat_angle(hand.wrist_orientation, expected / np.linalg.norm(expected)) < 1e-6


def test_right_thumb_is_left_of_the_little_finger_with_palm_down() -> None:
    hand = samples_of(typical_payload())[-1]
    assert isinstance(hand, HandPose)
    assert hand.keypoints[4, 1] > hand.keypoints[20, 1]  # operator y is left
    assert hand.keypoints[12, 0] > hand.keypoints[0, 0]  # fingers point forward


def test_invalid_joints_get_zero_confidence() -> None:
    msg = pb.VrFrame.FromString(typical_payload())
    msg.left_hand.joint_invalid_mask = (1 << 10) | (1 << 0)  # index tip, palm (unmapped)
    hand = samples_of(msg.SerializeToString())[3]
    assert isinstance(hand, HandPose)
    assert hand.keypoint_confidence[8] == 0.0
    assert hand.keypoint_confidence.sum() == 20.0
    assert hand.stamp.confidence == pytest.approx(20 / 21)


def test_untracked_parts_yield_no_samples() -> None:
    msg = pb.VrFrame.FromString(typical_payload())
    msg.head_tracked = False
    msg.left.tracked = False
    msg.right_hand.tracked = False
    del msg.right_hand.joint_positions[:]  # an untracked hand may omit its arrays
    sources = [s.stamp.source_id for s in samples_of(msg.SerializeToString())]
    assert sources == ["vr0/right", "vr0/left_hand"]


def test_datagram_without_device_time_decodes_with_zero() -> None:
    datagram = decode_datagram(frame(device_time_ns=0).SerializeToString())
    assert isinstance(datagram, VrDatagram)
    assert (datagram.device_ns, datagram.head, datagram.controllers, datagram.hands) == (0, None, (), ())


def _mutate(path: str, value: object) -> bytes:
    msg = pb.VrFrame.FromString(typical_payload())
    *parents, leaf = path.split(".")
    target: object = msg
    for name in parents:
        target = getattr(target, name)
    if leaf.endswith("]"):
        name, index = leaf[:-1].split("[")
        getattr(target, name)[int(index)] = value
    elif isinstance(value, list):
        container = getattr(target, leaf)
        del container[:]
        container.extend(value)
    else:
        setattr(target, leaf, value)
    return msg.SerializeToString()


@pytest.mark.parametrize(
    ("path", "value", "message"),
    [
        ("format_version", 2, "format_version must be 1"),
        ("format_version", 0, "format_version must be 1"),
        ("device_time_ns", -1, "device_time_ns must be >= 0"),
        ("head.px", math.nan, "head position must be finite"),
        ("head.py", 51.0, "head position must be finite"),
        ("left.grip.pz", -math.inf, "left controller position"),
        ("right.grip.qw", 0.0, "right controller orientation must be a unit quaternion"),
        ("head.qw", math.nan, "head orientation must be a unit quaternion"),
        ("right.trigger", 1.5, "right controller trigger must be in [0, 1]"),
        ("left.squeeze", -0.1, "left controller squeeze must be in [0, 1]"),
        ("left.thumbstick_y", math.nan, "thumbstick_y must be in [-1, 1]"),
        ("left_hand.joint_positions[10]", math.inf, "left_hand joint thumb_proximal position"),
        ("right_hand.joint_positions[77]", -60.0, "right_hand joint little_tip position"),
        ("right_hand.joint_orientations[7]", 3.0, "right_hand wrist orientation"),
        ("left_hand.joint_positions", [0.0] * 75, "must carry 26 joints"),
        ("left_hand.joint_radii", [], "must carry 26 joints"),
    ],
)
def test_bad_field_is_rejected_with_a_message_naming_it(path: str, value: object, message: str) -> None:
    with pytest.raises(WireError, match=message.replace("[", r"\[").replace("]", r"\]")):
        decode_datagram(_mutate(path, value))


def test_oversize_datagram_is_rejected() -> None:
    with pytest.raises(WireError, match="at most 4096"):
        decode_datagram(b"\x00" * (MAX_DATAGRAM_BYTES + 1))


@pytest.mark.parametrize("data", [b"\xff\xff\xff", b"\x0a\x05ab", typical_payload()[:-7]])
def test_garbage_bytes_are_rejected(data: bytes) -> None:
    with pytest.raises(WireError):
        decode_datagram(data)


def test_empty_datagram_is_rejected_as_missing_version() -> None:
    with pytest.raises(WireError, match="0 means the field is missing"):
        decode_datagram(b"")


def test_frame_at_rest_is_deterministic() -> None:
    sender = FakeVrSender(9, stream_id=1)
    assert sender.datagram(1.25, 3) == sender.datagram(1.25, 3)


# --- sequencing -----------------------------------------------------------------------------------


def feed(f: SequenceFilter, seqs: list[int], stream: int = 1) -> list[str]:
    return [f.accept(stream, s) for s in seqs]


def test_in_order_stream_is_accepted_without_loss() -> None:
    f = SequenceFilter()
    assert feed(f, [5, 6, 7, 8]) == ["accepted"] * 4
    assert f.counts == {"lost": 0, "duplicate": 0, "reordered": 0, "stale": 0, "restart": 0}


def test_gap_counts_as_loss() -> None:
    f = SequenceFilter()
    feed(f, [0, 1, 5])
    assert f.counts["lost"] == 3


def test_duplicate_is_dropped() -> None:
    f = SequenceFilter()
    assert feed(f, [0, 1, 1, 0]) == ["accepted", "accepted", "duplicate", "duplicate"]
    assert f.counts["duplicate"] == 2


def test_late_datagram_is_dropped_as_reordered_and_not_counted_lost() -> None:
    f = SequenceFilter()
    assert feed(f, [0, 2, 1, 3]) == ["accepted", "accepted", "reordered", "accepted"]
    assert (f.counts["lost"], f.counts["reordered"]) == (0, 1)


def test_repeated_late_datagram_counts_once_as_reordered() -> None:
    f = SequenceFilter()
    assert feed(f, [0, 2, 1, 1]) == ["accepted", "accepted", "reordered", "duplicate"]


def test_new_stream_id_restarts_the_sequence() -> None:
    f = SequenceFilter()
    feed(f, [100, 101])
    assert f.accept(2, 0) == "restart"
    assert f.accept(2, 1) == "accepted"
    assert f.counts["lost"] == 0


def test_sender_restart_without_stream_id_recovers_after_a_few_datagrams() -> None:
    f = SequenceFilter(window=16, restart_after=3)
    feed(f, list(range(100, 200)))
    assert feed(f, [0, 1, 2, 3]) == ["stale", "stale", "restart", "accepted"]


def test_isolated_very_old_datagram_is_stale_not_a_restart() -> None:
    f = SequenceFilter(window=16)
    feed(f, list(range(100)))
    assert feed(f, [3, 100]) == ["stale", "accepted"]
    assert f.counts["restart"] == 0


def test_huge_forward_jump_restarts() -> None:
    f = SequenceFilter(window=16, max_gap=1000)
    feed(f, [0, 1])
    assert f.accept(1, 5000) == "restart"
    assert f.counts["lost"] == 0


def test_missing_set_stays_bounded_under_heavy_loss() -> None:
    f = SequenceFilter(window=8)
    feed(f, list(range(0, 100_000, 3)))
    assert len(f._missing) <= 2 * 8 + 8
    assert f.counts["lost"] == 2 * (len(range(0, 100_000, 3)) - 1)


def test_rotation_helpers_agree() -> None:
    q = quat_from_axis_angle(np.array([0.3, -1.0, 0.2]), 0.8)
    body = openxr_to_operator_body_quat(xyzw(q))
    np.testing.assert_allclose(
        quat_rotate(body, np.array([1.0, 0.0, 0.0])),
        openxr_to_operator_points(quat_rotate(q, np.array([0.0, 0.0, -1.0]))),
        atol=1e-12,
    )
