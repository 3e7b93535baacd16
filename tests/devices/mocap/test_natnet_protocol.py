"""NatNet packets: wire layout from the protocol description, version round trips, normalization, fuzz."""

from __future__ import annotations

import contextlib
import math
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from telerig.devices.mocap._axes import MountTransform
from telerig.devices.mocap.fake import RIGID_BODY_NAMES, FakeNatNetServer, typical_payload
from telerig.devices.mocap.protocol import (
    FUZZ_TARGET,
    NAT_FRAMEOFDATA,
    FrameNormalizer,
    MocapFrame,
    NatNetVersion,
    RigidBodyData,
    ServerInfo,
    SkeletonData,
    encode_frame,
    encode_model_definitions,
    encode_server_info,
    parse_frame,
    parse_message,
    parse_model_definitions,
    parse_server_info,
    split_packet,
)
from telerig.errors import WireError
from telerig.ir.types import BodySkeleton, Pose

VERSIONS = [
    NatNetVersion(3, 0),
    NatNetVersion(3, 1),
    NatNetVersion(4, 0),
    NatNetVersion(4, 1),
    NatNetVersion(4, 2),
]


def hand_built_frame_3_1() -> bytes:
    """A NatNet 3.1 frame written field by field from the SDK's description (not by our encoder)."""
    body = struct.pack("<i", 77)  # frame number
    body += struct.pack("<i", 0)  # marker sets
    body += struct.pack("<i", 1) + struct.pack("<3f", 0.5, 0.0, 0.5)  # one unlabeled marker
    body += struct.pack("<i", 1)  # one rigid body: id, pos, qx qy qz qw, error, params
    body += struct.pack("<i3f4ffh", 3, 0.1, 1.0, 0.5, 0.0, 0.0, 0.0, 1.0, 0.0002, 1)
    body += struct.pack("<i", 0)  # skeletons
    body += struct.pack("<i", 1) + struct.pack("<i3ffhf", 65537, 0.0, 1.0, 0.0, 0.014, 0, 0.0001)
    body += struct.pack("<i", 0) + struct.pack("<i", 0)  # force plates, devices
    body += struct.pack("<IIdQQQ", 0, 0, 12.5, 1000, 1100, 1200)  # timecode, sub, timestamp, 3 stamps
    body += struct.pack("<h", 0) + struct.pack("<i", 0)  # params, end of data
    return struct.pack("<HH", NAT_FRAMEOFDATA, len(body)) + body


def test_hand_built_3_1_frame_parses_field_by_field() -> None:
    msg = parse_message(hand_built_frame_3_1(), NatNetVersion(3, 1))
    assert isinstance(msg, MocapFrame)
    assert msg.frame_number == 77
    assert msg.unlabeled_markers == ((0.5, 0.0, 0.5),)
    (rb,) = msg.rigid_bodies
    assert rb.id == 3
    assert rb.tracking_valid
    assert rb.position == pytest.approx((0.1, 1.0, 0.5))
    assert rb.orientation == (0.0, 0.0, 0.0, 1.0)
    assert msg.labeled_markers[0].id == 65537
    assert (msg.timestamp, msg.stamp_camera_mid_exposure, msg.stamp_transmit) == (12.5, 1000, 1200)


@pytest.mark.parametrize("version", VERSIONS, ids=str)
def test_frame_round_trips_in_every_version(version: NatNetVersion) -> None:
    frame = FakeNatNetServer(version=str(version)).frame_at(7)
    message_id, payload = split_packet(encode_frame(frame, version))
    parsed = parse_frame(payload, version)
    assert message_id == NAT_FRAMEOFDATA
    assert parsed.frame_number == 7
    assert len(parsed.rigid_bodies) == 5
    assert len(parsed.skeletons[0].bones) == 21
    assert parsed.rigid_bodies[2].position == pytest.approx(frame.rigid_bodies[2].position, abs=1e-6)
    assert parsed.stamp_camera_mid_exposure == frame.stamp_camera_mid_exposure
    assert parsed.labeled_markers[0].id == frame.labeled_markers[0].id


@pytest.mark.parametrize("version", VERSIONS, ids=str)
def test_model_definitions_round_trip_in_every_version(version: NatNetVersion) -> None:
    models = FakeNatNetServer().models
    _, payload = split_packet(encode_model_definitions(models, version))
    parsed = parse_model_definitions(payload, version)
    assert tuple(b.name for b in parsed.rigid_bodies) == RIGID_BODY_NAMES
    (skeleton,) = parsed.skeletons
    assert skeleton.name == "operator"
    assert len(skeleton.bones) == 21
    assert skeleton.bones[18].name == "RightArm"
    assert parsed.marker_sets[0].marker_names == ("m1", "m2")


def test_frame_parsed_with_the_wrong_version_is_rejected_or_differs() -> None:
    data = encode_frame(FakeNatNetServer().frame_at(1), NatNetVersion(4, 1))
    with pytest.raises(WireError):
        parse_message(data, NatNetVersion(3, 1))


def test_server_info_round_trips() -> None:
    info = ServerInfo("Motive", (3, 1, 0, 0), (4, 1, 0, 0), 10_000_000, 1511, True, "239.255.42.99")
    _, payload = split_packet(encode_server_info(info))
    assert parse_server_info(payload) == info
    assert info.version == NatNetVersion(4, 1)


@pytest.mark.parametrize("text", ["2.10", "5.0", "four"])
def test_unsupported_version_names_the_valid_range(text: str) -> None:
    with pytest.raises(WireError, match=r"4\.1|3\.0"):
        NatNetVersion.parse(text)


def test_truncated_frame_raises_wire_error() -> None:
    data = typical_payload()
    with pytest.raises(WireError):
        parse_message(data[: len(data) // 2], NatNetVersion(4, 1))


def test_declared_size_beyond_datagram_raises_wire_error() -> None:
    with pytest.raises(WireError, match="declares"):
        split_packet(struct.pack("<HH", NAT_FRAMEOFDATA, 500) + b"\0" * 10)


def frame_with(*bodies: RigidBodyData) -> MocapFrame:
    return MocapFrame(frame_number=1, rigid_bodies=bodies)


def test_motive_y_up_maps_to_x_forward_y_left_z_up() -> None:
    norm = FrameNormalizer("m")
    half = math.radians(30.0)
    about_y = (0.0, math.sin(half), 0.0, math.cos(half))  # 60 deg about Motive's up axis
    samples, drops = norm.normalize(frame_with(RigidBodyData(1, (0.1, 1.0, 0.5), about_y)), 5, 6)
    (pose,) = samples
    assert isinstance(pose, Pose)
    assert not drops
    np.testing.assert_allclose(pose.position, [0.5, 0.1, 1.0], atol=1e-6)  # forward, left, up
    np.testing.assert_allclose(pose.orientation, [math.cos(half), 0.0, 0.0, math.sin(half)], atol=1e-6)
    assert (pose.stamp.source_id, pose.stamp.device_ns, pose.stamp.capture_ns) == ("m/rb1", 5, 6)


def test_mount_yaw_and_offset_apply_in_the_output_frame() -> None:
    mount = MountTransform(yaw_deg=90.0, offset=(1.0, 0.0, 0.0))
    (pose,), _ = FrameNormalizer("m", mount=mount).normalize(
        frame_with(RigidBodyData(1, (0.0, 0.0, 1.0), (0.0, 0.0, 0.0, 1.0))), 0, 0
    )
    np.testing.assert_allclose(pose.position, [1.0, 1.0, 0.0], atol=1e-9)  # forward 1 m turned left


@pytest.mark.parametrize(
    ("body", "reason"),
    [
        (RigidBodyData(1, (0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0), params=0), "tracking_invalid"),
        (RigidBodyData(1, (math.nan, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0)), "non_finite"),
        (RigidBodyData(1, (0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 0.0)), "bad_quaternion"),
        (RigidBodyData(1, (0.0, 1e6, 0.0), (0.0, 0.0, 0.0, 1.0)), "out_of_range"),
    ],
)
def test_bad_rigid_body_is_dropped_and_counted(body: RigidBodyData, reason: str) -> None:
    good = RigidBodyData(2, (0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    samples, drops = FrameNormalizer("m").normalize(frame_with(body, good), 0, 0)
    assert [s.stamp.source_id for s in samples] == ["m/rb2"]
    assert drops == {reason: 1}


def test_names_come_from_model_definitions() -> None:
    server = FakeNatNetServer()
    norm = FrameNormalizer("mc")
    norm.set_models(server.models)
    samples, _ = norm.normalize(server.frame_at(3), 0, 0)
    assert [s.stamp.source_id for s in samples] == [f"mc/{n}" for n in RIGID_BODY_NAMES] + ["mc/operator"]
    skeleton = samples[-1]
    assert isinstance(skeleton, BodySkeleton)
    assert skeleton.joint_names[0] == "Hips"
    assert skeleton.joint_names[-1] == "RightHand"
    assert skeleton.stamp.confidence == 1.0


def test_local_skeleton_coordinates_compose_to_the_global_pose() -> None:
    server = FakeNatNetServer()
    frame = server.frame_at(50)
    bones = frame.skeletons[0].bones
    index = {b.id & 0xFFFF: b for b in bones}
    local = []
    for desc, bone in zip(server.models.skeletons[0].bones, bones, strict=True):
        parent = index.get(desc.parent_id)
        if parent is None:
            local.append(bone)
            continue
        pq = np.array([parent.orientation[3], *parent.orientation[:3]])
        r_parent = _matrix(pq)
        p = r_parent.T @ (np.array(bone.position) - np.array(parent.position))
        q = _quat(r_parent.T @ _matrix(np.array([bone.orientation[3], *bone.orientation[:3]])))
        local.append(RigidBodyData(bone.id, tuple(p), (q[1], q[2], q[3], q[0])))
    local_frame = MocapFrame(frame_number=50, skeletons=(SkeletonData(1, tuple(local)),))
    glob = FrameNormalizer("m", skeleton_coordinates="global")
    loc = FrameNormalizer("m", skeleton_coordinates="local")
    glob.set_models(server.models)
    loc.set_models(server.models)
    (a,), _ = glob.normalize(MocapFrame(frame_number=50, skeletons=frame.skeletons), 0, 0)
    (b,), _ = loc.normalize(local_frame, 0, 0)
    assert isinstance(a, BodySkeleton)
    assert isinstance(b, BodySkeleton)
    np.testing.assert_allclose(b.positions, a.positions, atol=1e-5)
    np.testing.assert_allclose(np.abs(np.sum(a.orientations * b.orientations, axis=1)), 1.0, atol=1e-5)


def _matrix(q: np.ndarray) -> np.ndarray:
    from telerig.devices.mocap._axes import quat_matrix

    return quat_matrix(q)


def _quat(m: np.ndarray) -> np.ndarray:
    from telerig.devices.mocap._axes import matrix_to_quat

    return matrix_to_quat(m)


def _check_output(out: object) -> None:
    for item in out if isinstance(out, list) else []:
        if isinstance(item, Pose):
            assert np.isfinite(item.position).all()
            assert np.all(np.abs(item.position) <= 100.0)
            assert abs(np.linalg.norm(item.orientation) - 1.0) < 1e-6
        if isinstance(item, BodySkeleton):
            assert np.isfinite(item.positions).all()
            assert np.all(np.abs(item.positions) <= 100.0)
            np.testing.assert_allclose(np.linalg.norm(item.orientations, axis=1), 1.0, atol=1e-6)
            assert 0.0 <= item.stamp.confidence <= 1.0


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=2048))
def test_fuzz_random_bytes_raise_only_wire_error(data: bytes) -> None:
    with contextlib.suppress(WireError):
        _check_output(FUZZ_TARGET(data))


@settings(max_examples=300, deadline=None)
@given(st.data())
def test_fuzz_mutated_frames_raise_only_wire_error(data: st.DataObject) -> None:
    packet = bytearray(typical_payload())
    for _ in range(data.draw(st.integers(1, 8))):
        i = data.draw(st.integers(0, len(packet) - 1))
        packet[i] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(4, len(packet)))
    with contextlib.suppress(WireError):
        _check_output(FUZZ_TARGET(bytes(packet[:cut])))


@settings(max_examples=300, deadline=None)
@given(
    st.tuples(*[st.floats(width=32, allow_nan=True, allow_infinity=True)] * 7),
    st.integers(-(2**15), 2**15 - 1),
)
def test_fuzz_rigid_body_values_never_reach_the_ir_invalid(values: tuple[float, ...], params: int) -> None:
    body = RigidBodyData(1, values[:3], values[3:], 0.0, params)  # type: ignore[arg-type]
    version = NatNetVersion(4, 1)
    frame = parse_message(encode_frame(frame_with(body), version), version)
    assert isinstance(frame, MocapFrame)
    samples, drops = FrameNormalizer("m").normalize(frame, 0, 0)
    _check_output(samples)
    assert len(samples) + sum(drops.values()) == 1
