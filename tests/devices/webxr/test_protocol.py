"""WebXR wire format: decoding, frame conversion to the operator frame, validation, clock offset, fuzz."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from telerig.devices.scripted import POINTING_DOWN
from telerig.devices.webxr.fake import (
    XRControllerInput,
    XRHandInput,
    encode_frame,
    encode_pong,
    typical_payload,
)
from telerig.devices.webxr.protocol import (
    FUZZ_TARGET,
    MEDIAPIPE_FROM_WEBXR,
    ClockOffset,
    Pong,
    XRFrame,
    decode,
    frame_samples,
)
from telerig.errors import WireError
from telerig.ir.frames import quat_rotate
from telerig.ir.types import ControllerState, HandPose, Pose, Sample

T_MS = 1.7e12
S = math.sqrt(0.5)


def frame(data: bytes) -> XRFrame:
    msg = decode(data)
    assert isinstance(msg, XRFrame)
    return msg


def samples(data: bytes) -> list[Sample]:
    seqs: dict[str, int] = {}

    def next_seq(sid: str) -> int:
        seqs[sid] = seqs.get(sid, -1) + 1
        return seqs[sid]

    return frame_samples(frame(data), "xr0", 123, next_seq)


def test_typical_payload_yields_head_controllers_and_hands() -> None:
    out = samples(typical_payload())
    assert [(type(s), s.stamp.source_id) for s in out] == [
        (Pose, "xr0/head"),
        (ControllerState, "xr0/left"),
        (ControllerState, "xr0/right"),
        (HandPose, "xr0/left_hand"),
        (HandPose, "xr0/right_hand"),
    ]
    assert all(s.stamp.capture_ns == 123 and s.stamp.device_ns == round(T_MS * 1e6 + 0.5e6) for s in out)


def test_position_maps_webxr_axes_to_operator_axes() -> None:
    msg = frame(encode_frame(0, T_MS, right=XRControllerInput(position=(0.2, 1.0, -0.3))))
    np.testing.assert_allclose(msg.controllers[0].position, [0.3, -0.2, 1.0], atol=1e-6)


def test_identity_grip_points_forward_with_top_up() -> None:
    q = frame(encode_frame(0, T_MS, right=XRControllerInput())).controllers[0].orientation
    np.testing.assert_allclose(quat_rotate(q, np.array([0.0, 0.0, 1.0])), [1, 0, 0], atol=1e-9)
    np.testing.assert_allclose(quat_rotate(q, np.array([1.0, 0.0, 0.0])), [0, 0, 1], atol=1e-9)


def test_grip_pitched_down_is_pointing_down() -> None:
    c = XRControllerInput(orientation=(-S, 0.0, 0.0, S))  # -90 deg about WebXR x
    q = frame(encode_frame(0, T_MS, right=c)).controllers[0].orientation
    np.testing.assert_allclose(q, POINTING_DOWN, atol=1e-6)


def test_head_turned_left_yaws_left_about_operator_z() -> None:
    head = ((0.0, 1.6, 0.0), (0.0, S, 0.0, S))  # +90 deg about WebXR y: looking left
    q = frame(encode_frame(0, T_MS, head=head)).head
    assert q is not None
    np.testing.assert_allclose(q[0], [0, 0, 1.6], atol=1e-6)
    np.testing.assert_allclose(quat_rotate(q[1], np.array([1.0, 0.0, 0.0])), [0, 1, 0], atol=1e-6)


def test_buttons_name_per_hand_and_joystick_forward_is_positive() -> None:
    c = XRControllerInput(thumbstick=(0.5, -1.0), buttons=0b110011)
    msg = frame(encode_frame(0, T_MS, left=c, right=c))
    left, right = msg.controllers
    assert left.buttons == {"trigger", "grip", "x", "y"}
    assert right.buttons == {"trigger", "grip", "a", "b"}
    np.testing.assert_allclose(right.joystick, [0.5, 1.0])


def test_hand_joints_map_to_mediapipe_keypoints() -> None:
    hand = XRHandInput.flat(wrist=(0.0, 1.0, 0.0), spacing_m=0.02)
    h = frame(encode_frame(0, T_MS, right_hand=hand)).hands[0]
    expected = np.array([(-p[2], -p[0], p[1]) for p in hand.positions])[list(MEDIAPIPE_FROM_WEBXR)]
    np.testing.assert_allclose(h.keypoints, expected, atol=1e-6)
    np.testing.assert_allclose(h.keypoints[8], [0.10, 0.02, 1.0], atol=1e-6)  # index tip, 5th joint
    assert h.keypoint_confidence.tolist() == [1.0] * 21


def test_untracked_joints_sit_at_the_wrist_with_zero_confidence() -> None:
    hand = XRHandInput.flat()
    radii = [0.01] * 25
    radii[9] = 0.0  # index-finger-tip = MediaPipe 8
    h = frame(encode_frame(0, T_MS, left_hand=XRHandInput(hand.positions, radii=radii))).hands[0]
    assert h.keypoint_confidence[8] == 0.0
    np.testing.assert_allclose(h.keypoints[8], h.wrist_position)


def test_pong_decodes() -> None:
    assert decode(encode_pong(7, T_MS)) == Pong(7, round(T_MS * 1e6))


def _with(data: bytes, offset: int, fmt: str, value: float) -> bytes:
    out = bytearray(data)
    struct.pack_into(fmt, out, offset, value)
    return bytes(out)


@pytest.mark.parametrize(
    ("data", "reason"),
    [
        (b"TX", "size"),
        (b"XX\x01\x01" + bytes(16), "magic"),
        (b"TX\x02\x01" + bytes(16), "version"),
        (b"TX\x01\x09" + bytes(16), "kind"),
        (encode_frame(0, T_MS, right=XRControllerInput())[:-1], "size"),
        (encode_frame(0, 0.0), "timestamp"),
        (_with(encode_frame(0, T_MS), 17, "<B", 0x20), "flags"),
        (_with(encode_frame(0, T_MS), 16, "<B", 7), "mode"),
        (_with(encode_frame(0, T_MS, right=XRControllerInput()), 20, "<f", math.nan), "position"),
        (_with(encode_frame(0, T_MS, right=XRControllerInput()), 20, "<f", 1e6), "position"),
        (_with(encode_frame(0, T_MS, right=XRControllerInput()), 44, "<f", 2.0), "orientation"),
        (_with(encode_frame(0, T_MS, right=XRControllerInput()), 48, "<f", 1.5), "analog"),
        (_with(encode_frame(0, T_MS, right=XRControllerInput()), 56, "<f", math.inf), "analog"),
        (
            _with(encode_frame(0, T_MS, left_hand=XRHandInput.flat()), 20 + 8 * 4 + 4, "<f", math.nan),
            "position",
        ),
        (_with(encode_frame(0, T_MS, left_hand=XRHandInput.flat()), 20 + 7 * 4, "<f", 0.0), "untracked"),
        (_with(encode_frame(0, T_MS, left_hand=XRHandInput.flat()), 20 + 7 * 4, "<f", 0.5), "range"),
    ],
)
def test_malformed_message_raises_wire_error_with_reason(data: bytes, reason: str) -> None:
    with pytest.raises(WireError) as info:
        decode(data)
    assert getattr(info.value, "reason", None) == reason


def test_clock_offset_prefers_the_pong_with_the_smallest_round_trip() -> None:
    clock = ClockOffset()
    clock.observe_frame(client_ns=1_000, receive_ns=6_000)
    assert clock.offset_ns == 5_000  # frame fallback until a pong
    clock.observe_pong(sent_ns=10_000, client_ns=7_000, receive_ns=10_400)  # rtt 400, offset 3_200
    clock.observe_pong(sent_ns=20_000, client_ns=14_000, receive_ns=26_000)  # rtt 6_000, offset 9_000
    assert clock.offset_ns == 3_200
    assert clock.round_trip_ns == 400


def test_capture_is_never_after_receive() -> None:
    clock = ClockOffset()
    clock.observe_pong(sent_ns=0, client_ns=0, receive_ns=100)
    assert clock.capture_ns(client_ns=1_000, receive_ns=500) == 500
    assert ClockOffset().capture_ns(client_ns=1, receive_ns=42) == 42


def _assert_clean(out: object) -> None:
    if isinstance(out, Pong):
        return
    assert isinstance(out, list)
    for s in out:
        arrays: list[np.ndarray] = []
        if isinstance(s, Pose):
            arrays = [s.position, s.orientation]
        elif isinstance(s, ControllerState):
            arrays = [s.position, s.orientation, s.joystick]
            assert 0.0 <= s.trigger <= 1.0
            assert 0.0 <= s.grip <= 1.0
            assert np.all(np.abs(s.joystick) <= 1.0)
        elif isinstance(s, HandPose):
            arrays = [s.wrist_position, s.wrist_orientation, s.keypoints, s.keypoint_confidence]
            assert np.all((s.keypoint_confidence >= 0) & (s.keypoint_confidence <= 1))
        for a in arrays:
            assert np.all(np.isfinite(a))
        if hasattr(s, "orientation"):
            assert abs(float(np.linalg.norm(s.orientation)) - 1.0) < 1e-9  # type: ignore[union-attr]
        assert 0.0 <= s.stamp.confidence <= 1.0


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=2048))
def test_fuzz_random_bytes_only_raise_wire_error(data: bytes) -> None:
    try:
        out = FUZZ_TARGET(data)
    except WireError:
        return
    _assert_clean(out)


_FULL = typical_payload()


@settings(max_examples=300, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.integers(0, len(_FULL) // 4 - 1), st.floats(width=32, allow_nan=True, allow_infinity=True)
        ),
        max_size=8,
    )
)
def test_fuzz_float_mutations_of_a_real_frame_never_reach_the_ir_unclean(
    edits: list[tuple[int, float]],
) -> None:
    data = bytearray(_FULL)
    for word, value in edits:
        struct.pack_into("<f", data, word * 4, value)
    try:
        out = FUZZ_TARGET(bytes(data))
    except WireError:
        return
    _assert_clean(out)
