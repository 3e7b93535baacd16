"""Tests for the data glove family: wire format, resync, hand model, gestures, device vs fake bridge."""

from __future__ import annotations

import dataclasses
import threading

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from telerig.devices.base import Device
from telerig.devices.glove.config import GloveConfig
from telerig.devices.glove.device import GloveDevice
from telerig.devices.glove.fake import GESTURE_KEYFRAMES, FakeGloveBridge, typical_payload
from telerig.devices.glove.gesture import Gesture, GestureTracker, classify
from telerig.devices.glove.kinematics import FUZZ_TARGET, HandModel, glove_hand_pose
from telerig.devices.glove.protocol import (
    GloveFrame,
    GloveStreamDecoder,
    GloveWireError,
    decode_frame,
    encode_frame,
)
from telerig.errors import WireError
from telerig.ir.frames import quat_rotate
from telerig.ir.types import HandPose, Sample, Stamp
from telerig.registry import DEVICES

STAMP = Stamp("t", 0, 0, 0)


def make_frame(**changes: object) -> GloveFrame:
    frame = FakeGloveBridge(wrist=True).frame_at(0.3, seq=7, device_ns=123_456_789)
    return dataclasses.replace(frame, **changes)


def pose_of(gesture: Gesture, hand: str = "right") -> HandPose:
    frame = make_frame(
        finger_angles=np.array(GESTURE_KEYFRAMES[gesture]),
        fingertips_mm=None,
        wrist_angles=None,
        handedness=hand,
    )
    return glove_hand_pose(frame, HandModel.default(), STAMP)


def test_roundtrip_preserves_every_field() -> None:
    frame = make_frame()
    out = decode_frame(encode_frame(frame))
    assert (out.seq, out.device_ns, out.handedness) == (7, 123_456_789, "right")
    np.testing.assert_allclose(out.finger_angles, frame.finger_angles, atol=1e-6)
    assert out.wrist_angles is not None
    assert frame.wrist_angles is not None
    np.testing.assert_allclose(out.wrist_angles, frame.wrist_angles, atol=1e-6)
    assert out.fingertips_mm is not None
    assert frame.fingertips_mm is not None
    np.testing.assert_allclose(out.fingertips_mm, frame.fingertips_mm, atol=1e-3)
    np.testing.assert_allclose(out.confidence, frame.confidence, atol=1 / 255)


def test_typical_payload_is_a_valid_frame() -> None:
    assert decode_frame(typical_payload()).handedness == "right"


@pytest.mark.parametrize(
    ("mutate", "reason"),
    [
        (lambda b: b[:-1] + bytes([b[-1] ^ 1]), "crc"),
        (lambda b: b[:10], "header"),
        (lambda b: b"XGLV" + b[4:], "header"),
    ],
)
def test_decode_rejects_damaged_frames_with_a_reason(mutate: object, reason: str) -> None:
    with pytest.raises(GloveWireError) as info:
        decode_frame(mutate(encode_frame(make_frame())))  # type: ignore[operator]
    assert info.value.reason == reason


def test_decode_rejects_out_of_range_angle() -> None:
    angles = np.zeros((5, 4))
    angles[2, 1] = 4.0
    with pytest.raises(GloveWireError, match="middle_mcp_flex") as info:
        decode_frame(encode_frame(make_frame(finger_angles=angles)))
    assert info.value.reason == "values"


def test_stream_decoder_resyncs_after_garbage_in_any_chunking() -> None:
    rng = np.random.default_rng(1)
    frames = [encode_frame(make_frame(seq=i)) for i in range(20)]
    stream = bytearray()
    for i, f in enumerate(frames):
        stream += f
        if i % 3 == 0:
            stream += rng.integers(0, 256, 37, dtype=np.uint8).tobytes() + b"TGL"
        if i % 7 == 0:
            bad = bytearray(f)
            bad[30] ^= 0xFF
            stream += bad  # a CRC-failing copy
    decoder = GloveStreamDecoder()
    got: list[GloveFrame] = []
    pos = 0
    while pos < len(stream):
        n = int(rng.integers(1, 200))
        got += decoder.feed(bytes(stream[pos : pos + n]))
        pos += n
    assert [f.seq for f in got] == list(range(20))
    assert decoder.stats["crc"] == 3
    assert decoder.stats["garbage_bytes"] > 0


def test_right_thumb_is_on_the_left_and_left_hand_mirrors() -> None:
    right, left = pose_of(Gesture.OPEN, "right"), pose_of(Gesture.OPEN, "left")
    assert right.keypoints[4, 1] > 0.03
    assert left.keypoints[4, 1] < -0.03
    np.testing.assert_allclose(left.keypoints * [1, -1, 1], right.keypoints, atol=1e-12)
    assert right.frame_id == "right_glove"
    np.testing.assert_allclose(right.wrist_orientation, [1, 0, 0, 0])


def test_open_hand_points_along_x_with_adult_length() -> None:
    kp = pose_of(Gesture.OPEN).keypoints
    assert 0.17 < kp[12, 0] < 0.21  # wrist to middle fingertip of an adult hand [m]
    assert abs(kp[12, 2]) < 0.02


def test_wrist_orientation_matches_rotated_keypoints() -> None:
    frame = make_frame(fingertips_mm=None, wrist_angles=np.array([0.4, -0.2]))
    pose = glove_hand_pose(frame, HandModel.default(), STAMP)
    flat = HandModel.default().keypoints(frame.finger_angles, "right")
    for i in (4, 8, 20):
        np.testing.assert_allclose(
            quat_rotate(pose.wrist_orientation, flat[i]), pose.keypoints[i], atol=1e-12
        )


def test_measured_tips_replace_model_tips() -> None:
    tips = np.full((5, 3), 50.0)
    frame = make_frame(fingertips_mm=tips, wrist_angles=None)
    pose = glove_hand_pose(frame, HandModel.default(), STAMP)
    np.testing.assert_allclose(pose.keypoints[[4, 8, 12, 16, 20]], tips / 1000)
    model_pose = glove_hand_pose(frame, HandModel.default(), STAMP, use_measured_tips=False)
    assert not np.allclose(model_pose.keypoints[8], 0.05)


@pytest.mark.parametrize("hand", ["left", "right"])
@pytest.mark.parametrize("gesture", [Gesture.OPEN, Gesture.FIST, Gesture.POINT, Gesture.PINCH])
def test_classify_recognizes_each_synthetic_gesture(gesture: Gesture, hand: str) -> None:
    assert classify(pose_of(gesture, hand)) == gesture


def test_classify_is_scale_invariant() -> None:
    frame = make_frame(finger_angles=np.array(GESTURE_KEYFRAMES[Gesture.PINCH]), fingertips_mm=None)
    small = glove_hand_pose(frame, HandModel(scale=0.7), STAMP)
    assert classify(small) == Gesture.PINCH


def test_tracker_debounces_and_holds_inside_the_hysteresis_band() -> None:
    tracker = GestureTracker(hold_samples=3)
    open_pose = pose_of(Gesture.OPEN)
    assert [tracker.update(open_pose) for _ in range(3)] == [Gesture.NONE, Gesture.NONE, Gesture.OPEN]
    assert tracker.changed
    # Fingers bent to a curl between the extend enter (0.9) and exit (1.3) thresholds: still open.
    bent = np.array(GESTURE_KEYFRAMES[Gesture.OPEN])
    bent[1:, 1:] = 0.36
    pose = glove_hand_pose(
        make_frame(finger_angles=bent, fingertips_mm=None, wrist_angles=None), HandModel(), STAMP
    )
    assert classify(pose) == Gesture.NONE
    assert all(tracker.update(pose) == Gesture.OPEN for _ in range(10))
    fist = pose_of(Gesture.FIST)
    assert [tracker.update(fist) for _ in range(3)][-1] == Gesture.FIST


def test_device_streams_hand_poses_and_gestures_through_garbage() -> None:
    seen: set[Gesture] = set()
    got: list[Sample] = []
    done = threading.Event()

    def on_gesture(hand: str, gesture: Gesture) -> None:
        seen.add(gesture)
        if {Gesture.OPEN, Gesture.FIST, Gesture.POINT, Gesture.PINCH} <= seen:
            done.set()

    with FakeGloveBridge(
        rate_hz=240, dwell_s=0.25, transition_s=0.1, garbage_every=4, corrupt_every=9
    ) as fake:
        device = GloveDevice("g", port=fake.port, hand="right", on_gesture=on_gesture)
        assert isinstance(device, Device)
        device.start(got.append)
        try:
            assert done.wait(10.0), f"gestures seen: {seen}"
        finally:
            device.stop()
            device.stop()
    stats = device.stats
    assert stats["drop_crc"] > 0
    assert stats["garbage_bytes"] > 0
    assert stats["samples"] == len(got) > 50
    sample = got[-1]
    assert isinstance(sample, HandPose)
    assert sample.stamp.source_id == "g/right"
    assert sample.frame_id == "right_glove"
    assert [s.stamp.seq for s in got] == list(range(len(got)))
    assert all(s.stamp.capture_ns <= s.stamp.arrival_ns for s in got)
    assert np.all(np.isfinite(sample.keypoints))


def test_device_reconnects_after_the_bridge_drops_the_connection() -> None:
    got: list[Sample] = []
    reconnected = threading.Event()

    def sink(sample: Sample) -> None:
        got.append(sample)
        if len(got) > 25:
            reconnected.set()

    with FakeGloveBridge(rate_hz=240, disconnect_after=10) as fake:
        device = GloveDevice(port=fake.port, reconnect_s=0.05)
        device.start(sink)
        try:
            assert reconnected.wait(10.0)
        finally:
            device.stop()
    assert device.stats["connects"] >= 3
    assert device.stats["disconnects"] >= 2


def test_device_counts_connect_failures_without_crashing() -> None:
    with FakeGloveBridge() as fake:
        port = fake.port
    device = GloveDevice(port=port, reconnect_s=0.02, connect_timeout_s=0.2)
    device.start(lambda s: None)
    try:
        for _ in range(200):
            if device.stats["connect_failures"] >= 2:
                break
            threading.Event().wait(0.02)
    finally:
        device.stop()
    assert device.stats["connect_failures"] >= 2


def test_config_registers_and_builds_a_glove_device() -> None:
    cfg = DEVICES.parse_config(
        {"type": "glove", "id": "gl", "port": 47999, "hand": "left", "hand_scale": 0.9}, "d"
    )
    assert isinstance(cfg, GloveConfig)
    device = cfg.build()
    assert isinstance(device, GloveDevice)
    assert device.id == "gl"
    assert device.port == 47999
    assert device.model.scale == 0.9
    with pytest.raises(ValueError, match="hand_scale"):
        DEVICES.parse_config({"type": "glove", "id": "gl", "hand_scale": 3}, "d")


def _check_pose(out: object) -> None:
    assert isinstance(out, HandPose)
    for arr in (out.keypoints, out.wrist_orientation, out.keypoint_confidence):
        assert np.all(np.isfinite(arr))
    assert np.all(np.abs(out.keypoints) < 1.0)
    assert np.all((out.keypoint_confidence >= 0) & (out.keypoint_confidence <= 1))
    assert 0.0 <= out.stamp.confidence <= 1.0


_VALID = typical_payload()


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_fuzz_random_bytes_raise_only_wire_error(data: bytes) -> None:
    try:
        out = FUZZ_TARGET(data)
    except WireError:
        return
    _check_pose(out)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.integers(0, len(_VALID) - 5), st.integers(0, 255)), min_size=1, max_size=4))
def test_fuzz_mutated_frames_with_fixed_crc_raise_only_wire_error(edits: list[tuple[int, int]]) -> None:
    import zlib

    data = bytearray(_VALID)
    for pos, value in edits:
        data[pos] = value
    data[-4:] = zlib.crc32(data[:-4]).to_bytes(4, "little")
    try:
        out = FUZZ_TARGET(bytes(data))
    except WireError:
        return
    _check_pose(out)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.binary(max_size=64), max_size=8))
def test_fuzz_stream_decoder_never_raises(chunks: list[bytes]) -> None:
    decoder = GloveStreamDecoder()
    for chunk in [*chunks, _VALID]:
        decoder.feed(chunk)
    assert decoder.buffered <= 2 * 1024
