"""Tests for the Leap Motion family: v6 JSON parsing, mounting transform, device vs fake service."""

from __future__ import annotations

import json
import socket
import threading
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from telerig.devices.base import Device
from telerig.devices.leap.config import LeapConfig
from telerig.devices.leap.device import LeapDevice
from telerig.devices.leap.fake import FakeLeapService, synthetic_frame, typical_payload
from telerig.devices.leap.protocol import (
    DESK_MOUNT,
    FUZZ_TARGET,
    LeapEvent,
    LeapFrame,
    Mounting,
    ServiceVersion,
    hand_pose,
    parse_message,
)
from telerig.errors import ConfigError, DeviceError, WireError
from telerig.ir.frames import quat_rotate
from telerig.ir.types import HandPose, Sample, Stamp
from telerig.registry import DEVICES

STAMP = Stamp("t", 0, 0, 0)


def frame_dict() -> dict[str, Any]:
    return synthetic_frame(0.5, 42, 1_000_000)


def test_parses_version_event_and_frame() -> None:
    assert parse_message('{"serviceVersion": "2.3.1+33747", "version": 6}') == ServiceVersion(
        "2.3.1+33747", 6
    )
    assert parse_message('{"event": {"type": "deviceEvent", "state": {}}}') == LeapEvent("deviceEvent")
    frame = parse_message(typical_payload())
    assert isinstance(frame, LeapFrame)
    assert frame.id == 187
    assert frame.timestamp_us == 1_234_567_890
    assert [h.handedness for h in frame.hands] == ["left", "right"]


def test_keypoints_follow_mediapipe_order_from_leap_joints() -> None:
    raw = frame_dict()
    frame = parse_message(json.dumps(raw))
    assert isinstance(frame, LeapFrame)
    hand = frame.hands[1]
    index = next(p for p in raw["pointables"] if p["handId"] == hand.id and p["type"] == 1)
    thumb = next(p for p in raw["pointables"] if p["handId"] == hand.id and p["type"] == 0)
    np.testing.assert_allclose(hand.keypoints_mm[0], raw["hands"][1]["wrist"])
    np.testing.assert_allclose(hand.keypoints_mm[1], thumb["mcpPosition"])
    np.testing.assert_allclose(
        hand.keypoints_mm[5:9],
        [index[k] for k in ("mcpPosition", "pipPosition", "dipPosition", "btipPosition")],
    )


def test_missing_wrist_falls_back_to_mean_carpal_position() -> None:
    raw = frame_dict()
    del raw["hands"][0]["wrist"]
    frame = parse_message(json.dumps(raw))
    assert isinstance(frame, LeapFrame)
    carps = [
        p["carpPosition"] for p in raw["pointables"] if p["handId"] == frame.hands[0].id and p["type"] > 0
    ]
    np.testing.assert_allclose(frame.hands[0].keypoints_mm[0], np.mean(carps, axis=0))


def test_hand_without_all_fingers_is_counted_incomplete() -> None:
    raw = frame_dict()
    raw["pointables"] = [p for p in raw["pointables"] if not (p["handId"] == 100 and p["type"] == 3)]
    frame = parse_message(json.dumps(raw))
    assert isinstance(frame, LeapFrame)
    assert len(frame.hands) == 1
    assert frame.incomplete_hands == 1


@pytest.mark.parametrize(
    "text",
    [
        "{nope",
        '{"id": 1, "timestamp": NaN, "hands": []}',
        '{"id": 1, "timestamp": 1, "hands": [{"id": 1, "type": "middle"}]}',
        '{"id": -1, "timestamp": 1, "hands": []}',
        "[]",
        "[" * 5000,
    ],
)
def test_malformed_messages_raise_wire_error(text: str) -> None:
    with pytest.raises(WireError):
        parse_message(text)


def test_desk_mount_maps_leap_axes_to_operator_axes() -> None:
    # Leap +z (toward the user) -> operator -x; Leap +x (user's right) -> operator -y; Leap +y -> +z.
    pts = DESK_MOUNT.points(np.array([[0.0, 0.0, 1000.0], [1000.0, 0.0, 0.0], [0.0, 1000.0, 0.0]]))
    np.testing.assert_allclose(pts - DESK_MOUNT.position_m, [[-1, 0, 0], [0, -1, 0], [0, 0, 1]], atol=1e-12)


def test_palm_down_hand_pointing_away_has_identity_orientation() -> None:
    raw = synthetic_frame(0.0, 1, 1, hands=("right",))
    frame = parse_message(json.dumps(raw))
    assert isinstance(frame, LeapFrame)
    pose = hand_pose(frame.hands[0], STAMP)
    # At t = 0 the fake hand is flat, palm down, fingers away from the user: operator +x.
    np.testing.assert_allclose(pose.wrist_orientation, [1, 0, 0, 0], atol=1e-3)
    middle_dir = pose.keypoints[9] - pose.keypoints[0]
    assert middle_dir[0] > 0.08
    np.testing.assert_allclose(
        quat_rotate(pose.wrist_orientation, np.array([1.0, 0, 0])), [1, 0, 0], atol=2e-3
    )
    assert pose.keypoints[4, 1] > pose.keypoints[20, 1]  # right thumb on the operator's left


def test_mounting_rejects_non_unit_quaternion() -> None:
    with pytest.raises(ConfigError, match="unit quaternion"):
        Mounting((1.0, 1.0, 0.0, 0.0), (0.0, 0.0, 0.0))


def test_device_streams_both_hands_and_sends_client_options() -> None:
    got: list[Sample] = []
    enough = threading.Event()

    def sink(sample: Sample) -> None:
        got.append(sample)
        if len(got) >= 60:
            enough.set()

    with FakeLeapService(rate_hz=200, garbage_every=5) as fake:
        device = LeapDevice("lp", url=fake.url)
        assert isinstance(device, Device)
        device.start(sink)
        try:
            assert enough.wait(10.0)
        finally:
            device.stop()
            device.stop()
        received = list(fake.received)
    assert {"enableGestures": False} in received
    assert {"background": True} in received
    stats = device.stats
    assert stats["drop_malformed"] > 0
    assert stats["samples"] == len(got)
    assert device.service_version == ServiceVersion("2.3.1+33747", 6)
    by_source: dict[str, list[int]] = {}
    for s in got:
        assert isinstance(s, HandPose)
        assert s.frame_id == "operator"
        assert s.stamp.capture_ns <= s.stamp.arrival_ns
        by_source.setdefault(s.stamp.source_id, []).append(s.stamp.seq)
    assert set(by_source) == {"lp/left", "lp/right"}
    assert all(seqs == list(range(len(seqs))) for seqs in by_source.values())
    left = next(s for s in got if isinstance(s, HandPose) and s.handedness == "left")
    assert left.wrist_position[1] > 0.0  # the left hand is on the operator's left


def test_device_reconnects_after_the_service_closes() -> None:
    enough = threading.Event()
    got: list[Sample] = []

    def sink(sample: Sample) -> None:
        got.append(sample)
        if len(got) >= 30:
            enough.set()

    with FakeLeapService(rate_hz=200, hands=("right",), disconnect_after=10) as fake:
        device = LeapDevice(url=fake.url, reconnect_s=0.05, hands=("right",))
        device.start(sink)
        try:
            assert enough.wait(10.0)
        finally:
            device.stop()
    assert device.stats["connects"] >= 3


def test_config_registers_and_builds_a_leap_device() -> None:
    cfg = DEVICES.parse_config({"type": "leap", "id": "lp", "mount_position_m": [0.3, 0.0, 0.7]}, "d")
    assert isinstance(cfg, LeapConfig)
    device = cfg.build()
    assert isinstance(device, LeapDevice)
    assert device.id == "lp"
    np.testing.assert_allclose(device.mounting.position_m, [0.3, 0.0, 0.7])
    with pytest.raises(ValueError, match="mount_orientation"):
        DEVICES.parse_config({"type": "leap", "id": "lp", "mount_orientation": [1, 1, 0, 0]}, "d")


def _check(out: object) -> None:
    if not isinstance(out, list):
        return
    for pose in out:
        assert isinstance(pose, HandPose)
        for arr in (pose.keypoints, pose.wrist_position, pose.wrist_orientation, pose.keypoint_confidence):
            assert np.all(np.isfinite(arr))
        assert abs(float(np.linalg.norm(pose.wrist_orientation)) - 1.0) < 1e-9
        assert np.all(np.abs(pose.keypoints) < 10.0)
        assert np.all((pose.keypoint_confidence >= 0) & (pose.keypoint_confidence <= 1))


_json = st.recursive(
    st.none()
    | st.booleans()
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.integers()
    | st.text(max_size=8),
    lambda kids: st.lists(kids, max_size=4) | st.dictionaries(st.text(max_size=12), kids, max_size=4),
    max_leaves=20,
)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=200) | _json.map(lambda v: json.dumps(v).encode()))
def test_fuzz_arbitrary_messages_raise_only_wire_error(data: bytes) -> None:
    try:
        out = FUZZ_TARGET(data)
    except WireError:
        return
    _check(out)


_KEYS = ("wrist", "palmNormal", "direction", "confidence", "type", "id", "palmPosition")
_PKEYS = ("mcpPosition", "pipPosition", "dipPosition", "btipPosition", "carpPosition", "type", "handId")


@settings(max_examples=300, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.booleans(), st.integers(0, 9), st.sampled_from(_KEYS + _PKEYS), _json | st.just([1e308, 0, 0])
        ),
        min_size=1,
        max_size=4,
    )
)
def test_fuzz_mutated_frames_raise_only_wire_error(edits: list[tuple[bool, int, str, Any]]) -> None:
    raw = frame_dict()
    for in_hand, i, key, value in edits:
        target = raw["hands"][i % 2] if in_hand else raw["pointables"][i]
        target[key] = value
    try:
        out = FUZZ_TARGET(json.dumps(raw).encode())
    except WireError:
        return
    _check(out)


def test_fake_service_on_a_taken_port_fails_to_start_with_one_device_error() -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        fake = FakeLeapService(port=taken.getsockname()[1])
        with pytest.raises(DeviceError, match="fake Leap service failed to start"):
            fake.start()
        fake.stop()  # idempotent after a failed start
