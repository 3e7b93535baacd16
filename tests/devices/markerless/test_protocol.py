"""Markerless wire v1: round trips through the fake encoder, frame conventions and a parser fuzz."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from telerig.devices.markerless import protocol, tracker
from telerig.devices.markerless.fake import FakeTracker, operator_to_mediapipe, typical_hand, typical_pose
from telerig.errors import WireError
from telerig.ir.frames import quat_rotate
from telerig.ir.types import BodySkeleton, HandPose, Stamp

_NOWHERE = ("127.0.0.1", 9)


@pytest.mark.parametrize("mirrored", [False, True])
@pytest.mark.parametrize("hand", ["left", "right"])
def test_hand_round_trip_keeps_handedness_and_keypoints(mirrored: bool, hand: str) -> None:
    with FakeTracker(_NOWHERE, mirrored=mirrored) as fake:
        msg = protocol.decode(fake.hand_bytes(7, hand))  # type: ignore[arg-type]
    assert isinstance(msg, protocol.HandMessage)
    assert msg.handedness == hand
    assert msg.header.frame == 7
    assert msg.header.mirrored is mirrored
    np.testing.assert_allclose(msg.keypoints, typical_hand(hand), atol=1e-6)  # type: ignore[arg-type]


def test_unmirrored_mediapipe_left_label_is_the_operators_right_hand() -> None:
    world = operator_to_mediapipe(typical_hand("right"))
    head = tracker.encode_header(
        tracker.KIND_HAND, capture_ns=1, device_ns=0, frame=0, width=4, height=4, mirrored=False
    )
    msg = protocol.decode(tracker.encode_hand(head, 0, 0, 0.9, world, np.full(21, 0.9)))
    assert isinstance(msg, protocol.HandMessage)
    assert msg.handedness == "right"


def test_mediapipe_axes_map_to_operator_axes() -> None:
    # A point toward the camera (-z_mp), image-right (+x_mp) and image-up (-y_mp) of the hand centre
    # is forward, left (the operator's left appears on the image's right) and up.
    world = np.zeros((21, 3))
    world[:, :] = operator_to_mediapipe(typical_hand("right"))
    world[20] = (0.01, -0.02, -0.03)
    head = tracker.encode_header(
        tracker.KIND_HAND, capture_ns=1, device_ns=0, frame=0, width=4, height=4, mirrored=False
    )
    msg = protocol.decode(tracker.encode_hand(head, 0, 0, 0.9, world, np.full(21, 0.9)))
    assert isinstance(msg, protocol.HandMessage)
    np.testing.assert_allclose(msg.keypoints[20], (0.03, 0.01, 0.02), atol=1e-7)


@pytest.mark.parametrize("hand", ["left", "right"])
def test_wrist_frame_of_flat_palm_down_hand_has_z_up_and_x_forward(hand: str) -> None:
    kp = typical_hand(hand)  # type: ignore[arg-type]
    q = protocol.wrist_orientation(kp, hand)  # type: ignore[arg-type]
    assert np.dot(quat_rotate(q, np.array([0.0, 0.0, 1.0])), (0, 0, 1)) > 0.95
    assert np.dot(quat_rotate(q, np.array([1.0, 0.0, 0.0])), (1, 0, 0)) > 0.95
    assert abs(np.linalg.norm(q) - 1.0) < 1e-12


def test_degenerate_hand_is_a_wire_error() -> None:
    with pytest.raises(WireError, match="degenerate"):
        protocol.wrist_orientation(np.zeros((21, 3)), "right")


@pytest.mark.parametrize("mirrored", [False, True])
def test_pose_round_trip_keeps_the_persons_sides(mirrored: bool) -> None:
    with FakeTracker(_NOWHERE, mirrored=mirrored) as fake:
        msg = protocol.decode(fake.pose_bytes(3))
    assert isinstance(msg, protocol.PoseMessage)
    rows = typical_pose()
    np.testing.assert_allclose(msg.positions, rows[:, :3], atol=1e-6)
    left = protocol.POSE_JOINTS.index("left_shoulder")
    assert msg.positions[left, 1] > 0.0  # the person's left is +y in operator axes
    skeleton = protocol.body_skeleton(msg, Stamp("cam0/body", 0, 0, 1), "hips")
    assert isinstance(skeleton, BodySkeleton)
    assert skeleton.joint_names == protocol.POSE_JOINTS
    assert len(skeleton.joint_names) == 33
    np.testing.assert_array_equal(skeleton.orientations[:, 0], 1.0)
    assert protocol.body_confidence(msg) == pytest.approx(0.98, abs=1e-6)


def test_frame_and_event_messages_decode() -> None:
    with FakeTracker(_NOWHERE) as fake:
        frame = protocol.decode(tracker.encode_frame(fake.header(tracker.KIND_FRAME, 4), 2, 1, 11.5))
        event = protocol.decode(
            tracker.encode_event(fake.header(tracker.KIND_EVENT, 0), tracker.EVENT_END, "end of x.mp4")
        )
    assert isinstance(frame, protocol.FrameMessage)
    assert (frame.hands, frame.poses, frame.processing_ms) == (2, 1, 11.5)
    assert isinstance(event, protocol.EventMessage)
    assert (event.code, event.text) == ("end", "end of x.mp4")


@pytest.mark.parametrize(
    ("mutate", "reason"),
    [
        (lambda b: b[:20], "at least 32"),
        (lambda b: b"XXXX" + b[4:], "bad magic"),
        (lambda b: b[:4] + bytes([9]) + b[5:], "version 9"),
        (lambda b: b[:5] + bytes([42]) + b[6:], "unknown message kind"),
        (lambda b: b[:-4], "must be 376 bytes"),
        (lambda b: b[:40] + struct.pack("<f", float("nan")) + b[44:], "finite"),
        (lambda b: b[:40] + struct.pack("<f", 5.0) + b[44:], "within 1.0 m"),
        (lambda b: b[:-4] + struct.pack("<f", 1.5), r"\[0, 1\]"),
    ],
)
def test_malformed_hand_datagram_is_rejected_with_reason(mutate: object, reason: str) -> None:
    with FakeTracker(_NOWHERE) as fake:
        good = fake.hand_bytes(1)
    with pytest.raises(WireError, match=reason):
        protocol.decode(mutate(good))  # type: ignore[operator]


def _check_ir(out: object) -> None:
    if isinstance(out, HandPose):
        arrays = [out.keypoints, out.wrist_position, out.wrist_orientation, out.keypoint_confidence]
        assert np.abs(out.keypoints).max() <= protocol.HAND_LIMIT_M
        assert out.keypoint_confidence.min() >= 0.0
        assert out.keypoint_confidence.max() <= 1.0
        assert abs(np.linalg.norm(out.wrist_orientation) - 1.0) < 1e-9
        assert 0.0 <= out.stamp.confidence <= 1.0
    elif isinstance(out, BodySkeleton):
        arrays = [out.positions, out.orientations]
        assert np.abs(out.positions).max() <= protocol.POSE_LIMIT_M
    else:
        return
    for arr in arrays:
        assert np.all(np.isfinite(arr))


def _seeds() -> list[bytes]:
    with FakeTracker(_NOWHERE) as fake:
        return [
            fake.hand_bytes(1),
            fake.pose_bytes(1),
            tracker.encode_frame(fake.header(tracker.KIND_FRAME, 1), 1, 1, 3.0),
            tracker.encode_event(fake.header(tracker.KIND_EVENT, 0), 0, "started"),
        ]


_SEEDS = _seeds()


@st.composite
def _datagrams(draw: st.DrawFn) -> bytes:
    base = bytearray(draw(st.sampled_from(_SEEDS)))
    for _ in range(draw(st.integers(0, 6))):
        op = draw(st.integers(0, 3))
        if op == 0 and base:
            base[draw(st.integers(0, len(base) - 1))] = draw(st.integers(0, 255))
        elif op == 1 and len(base) >= 4:
            at = draw(st.integers(0, (len(base) - 4) // 4)) * 4
            value = draw(st.floats(allow_nan=True, allow_infinity=True, width=32))
            base[at : at + 4] = struct.pack("<f", value)
        elif op == 2:
            base = base[: draw(st.integers(0, len(base)))]
        else:
            base += draw(st.binary(max_size=8))
    return bytes(base)


@settings(max_examples=300, deadline=None)
@given(st.one_of(_datagrams(), st.binary(max_size=800)))
def test_fuzzed_datagrams_raise_only_wire_error_and_never_leak_bad_values(data: bytes) -> None:
    try:
        out = protocol.FUZZ_TARGET(data)
    except WireError:
        return
    _check_ir(out)
