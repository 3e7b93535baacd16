"""BVH: parsing, forward kinematics (rotation order, bone lengths, units, axes), playback and fuzz."""

from __future__ import annotations

import contextlib
import itertools
import math
import threading
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from telerig.devices.base import Device
from telerig.devices.mocap import BvhPlayer
from telerig.devices.mocap._axes import MountTransform
from telerig.devices.mocap.bvh import BVH_FUZZ_TARGET, detect_scale, parse_bvh
from telerig.devices.mocap.fake import reaching_bvh, sample_bvh_path
from telerig.devices.validate import SampleValidator
from telerig.errors import DeviceError, WireError
from telerig.ir.types import BodySkeleton, Sample


def two_joint_bvh(channels: str, angles: str, offset: str = "0 10 0") -> str:
    return f"""HIERARCHY
ROOT Root
{{
  OFFSET 0 0 0
  CHANNELS 3 {channels}
  JOINT Child
  {{
    OFFSET {offset}
    CHANNELS 0
    End Site
    {{
      OFFSET 0 0 1
    }}
  }}
}}
MOTION
Frames: 1
Frame Time: 0.01
{angles}
"""


def rot(axis: str, deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return {
        "X": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "Y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        "Z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[axis]


def test_shipped_clip_is_the_synthesized_reach() -> None:
    assert sample_bvh_path().read_text() == reaching_bvh()


def test_shipped_clip_parses_with_cmu_names_and_timing() -> None:
    clip = parse_bvh(sample_bvh_path().read_text())
    names = [j.name for j in clip.joints if not j.end_site]
    assert len(names) == 21
    assert names[0] == "Hips"
    assert {"Spine", "RightShoulder", "RightArm", "RightForeArm", "RightHand"} <= set(names)
    assert clip.num_frames == 180
    assert clip.frame_time_s == pytest.approx(1 / 60, abs=1e-6)
    assert clip.motion.shape == (180, 6 + 20 * 3)


@pytest.mark.parametrize(
    ("channels", "order"),
    [
        ("Xrotation Yrotation Zrotation", "XYZ"),
        ("Zrotation Xrotation Yrotation", "ZXY"),
        ("Yrotation Zrotation Xrotation", "YZX"),
    ],
)
def test_rotation_channels_compose_in_file_order(channels: str, order: str) -> None:
    angles = {"X": 30.0, "Y": 45.0, "Z": 60.0}
    values = " ".join(str(angles[c[0]]) for c in channels.split())
    clip = parse_bvh(two_joint_bvh(channels, values))
    pos, rots = clip.forward_kinematics()
    expected = (
        rot(order[0], angles[order[0]]) @ rot(order[1], angles[order[1]]) @ rot(order[2], angles[order[2]])
    )
    np.testing.assert_allclose(rots[0, 0], expected, atol=1e-12)
    np.testing.assert_allclose(pos[0, 1], expected @ [0, 10, 0], atol=1e-12)


def test_bone_lengths_are_preserved_in_every_frame() -> None:
    clip = parse_bvh(sample_bvh_path().read_text())
    pos, _ = clip.forward_kinematics()
    for j, joint in enumerate(clip.joints):
        if joint.parent >= 0:
            lengths = np.linalg.norm(pos[:, j] - pos[:, joint.parent], axis=1)
            np.testing.assert_allclose(lengths, np.linalg.norm(joint.offset), atol=1e-9)


def test_rotations_stay_orthonormal() -> None:
    _, rots = parse_bvh(sample_bvh_path().read_text()).forward_kinematics()
    eye = np.einsum("fjik,fjlk->fjil", rots, rots)
    np.testing.assert_allclose(eye, np.broadcast_to(np.eye(3), eye.shape), atol=1e-9)


def test_position_channels_replace_the_offset() -> None:
    clip = parse_bvh(two_joint_bvh("Xposition Yposition Zposition", "1 2 3"))
    pos, _ = clip.forward_kinematics()
    np.testing.assert_allclose(pos[0, 0], [1, 2, 3])
    np.testing.assert_allclose(pos[0, 1], [1, 12, 3])


def test_scale_detects_centimetres_from_hip_height() -> None:
    clip = parse_bvh(sample_bvh_path().read_text())
    assert detect_scale(clip) == 0.01


def test_scale_keeps_metres() -> None:
    text = two_joint_bvh("Xposition Yposition Zposition", "0 0.9 0", offset="0 -0.9 0")
    assert detect_scale(parse_bvh(text)) == 1.0


def test_skeleton_frames_are_in_operator_axes_and_metres() -> None:
    frames = BvhPlayer(sample_bvh_path()).frames()
    names = frames[0].joint_names
    assert names[0] == "Hips"
    assert "RightHand_end" in names
    hips = frames[0].positions[0]
    assert hips[2] == pytest.approx(0.92)  # Y up -> z up, cm -> m
    left_hip = frames[0].positions[names.index("LeftUpLeg")]
    assert left_hip[1] > 0.05  # the performer's left is +y
    hand = np.array([f.positions[names.index("RightHand")] for f in frames])
    assert hand[:, 0].max() - hand[0, 0] > 0.3  # the reach goes forward (+x) by > 30 cm
    np.testing.assert_allclose(np.linalg.norm(frames[50].orientations, axis=1), 1.0, atol=1e-9)


def test_player_emits_every_frame_in_order_with_file_timing() -> None:
    player = BvhPlayer(sample_bvh_path(), id="b", speed=20.0)
    got: list[Sample] = []
    player.start(got.append)
    assert player.wait(10.0)
    player.stop()
    assert len(got) == 180
    assert all(isinstance(s, BodySkeleton) and s.stamp.source_id == "b/body" for s in got)
    assert [s.stamp.seq for s in got] == list(range(180))
    frame_time = player.clip().frame_time_s
    assert got[60].stamp.device_ns == round(60 * frame_time * 1e9)
    assert all(b.stamp.capture_ns >= a.stamp.capture_ns for a, b in itertools.pairwise(got))


def test_a_stalled_player_stamps_each_frame_when_it_fell_due() -> None:
    """A sink that blocks for 0.25 s makes the player late (as a stalled host would); the frames it
    then owes go out back to back, each stamped with its due time, so capture times keep the file's
    spacing and the default validator drops none of them (no jump, no gap)."""
    speed = 2.0
    player = BvhPlayer(sample_bvh_path(), id="b", speed=speed)
    got: list[Sample] = []
    at: list[float] = []

    def sink(s: Sample) -> None:
        got.append(s)
        at.append(time.perf_counter())
        if len(got) == 10:
            time.sleep(0.25)

    player.start(sink)
    assert player.wait(10.0)
    player.stop()
    period_s = player.clip().frame_time_s / speed
    assert at[15] - at[10] < period_s  # late: the owed frames were emitted together
    steps_s = np.diff([s.stamp.capture_ns for s in got]) / 1e9
    np.testing.assert_allclose(steps_s, period_s, rtol=0.1)
    validator = SampleValidator.default()
    assert [validator.validate(s) for s in got] == [None] * len(got)


def test_looping_player_keeps_device_time_increasing() -> None:
    player = BvhPlayer(sample_bvh_path(), speed=50.0, loop=True)
    got: list[Sample] = []
    enough = threading.Event()

    def sink(s: Sample) -> None:
        got.append(s)
        if len(got) >= 200:
            enough.set()

    player.start(sink)
    try:
        assert enough.wait(10.0)
    finally:
        player.stop()
    device = [s.stamp.device_ns for s in got]
    assert all(b > a for a, b in itertools.pairwise(device))
    assert isinstance(player, Device)


def test_player_names_missing_and_invalid_files(tmp_path: object) -> None:
    from pathlib import Path

    base = Path(str(tmp_path))
    with pytest.raises(DeviceError, match="does not exist"):
        BvhPlayer(base / "nope.bvh")
    bad = base / "bad.bvh"
    bad.write_text("HIERARCHY\nROOT Hips\n{\n OFFSET 0 0\n")
    with pytest.raises(DeviceError, match=r"bad\.bvh"):
        BvhPlayer(bad).start(lambda s: None)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", "expected 'HIERARCHY'"),
        (two_joint_bvh("Wrotation Xrotation Yrotation", "1 2 3"), "unknown channel"),
        (two_joint_bvh("Xrotation Yrotation Zrotation", "1 2"), "needs 3"),
        (two_joint_bvh("Xrotation Yrotation Zrotation", "1 2 nan"), "finite"),
        (two_joint_bvh("Xrotation Yrotation Zrotation", "1 2 3").replace("0.01", "0"), "Frame Time"),
    ],
)
def test_malformed_bvh_raises_wire_error_saying_what(text: str, message: str) -> None:
    with pytest.raises(WireError, match=message):
        parse_bvh(text)


def _check(out: object) -> None:
    for s in out if isinstance(out, list) else []:
        assert isinstance(s, BodySkeleton)
        assert np.isfinite(s.positions).all()
        assert np.all(np.abs(s.positions) <= 1e4)
        np.testing.assert_allclose(np.linalg.norm(s.orientations, axis=1), 1.0, atol=1e-6)


@settings(max_examples=300, deadline=None)
@given(st.text(max_size=400))
def test_fuzz_random_text_raises_only_wire_error(text: str) -> None:
    with contextlib.suppress(WireError):
        _check(BVH_FUZZ_TARGET(text.encode()))


_SMALL = two_joint_bvh(
    "Xposition Yposition Zposition Zrotation Xrotation Yrotation", "0 90 0 10 20 30"
).split()
_TOKENS = st.sampled_from(
    [
        "{",
        "}",
        "JOINT",
        "End",
        "Site",
        "OFFSET",
        "CHANNELS",
        "3",
        "6",
        "Xrotation",
        "Yposition",
        "1e308",
        "-0",
        "nan",
        "inf",
        "MOTION",
        "Frames:",
        "Frame",
        "Time:",
        "0.5",
        "999999",
        "A",
    ]
)


@settings(max_examples=300, deadline=None)
@given(st.data())
def test_fuzz_mutated_bvh_raises_only_wire_error(data: st.DataObject) -> None:
    tokens = list(_SMALL)
    for _ in range(data.draw(st.integers(1, 4))):
        i = data.draw(st.integers(0, len(tokens) - 1))
        action = data.draw(st.integers(0, 2))
        if action == 0:
            tokens[i] = data.draw(_TOKENS)
        elif action == 1:
            del tokens[i]
        else:
            tokens.insert(i, data.draw(_TOKENS))
    with contextlib.suppress(WireError):
        _check(BVH_FUZZ_TARGET(" ".join(tokens).encode()))


def test_mount_transform_keeps_rotations_proper() -> None:
    mount = MountTransform(up="+z", forward="-y", yaw_deg=33.0)
    assert np.linalg.det(mount.rotation) == pytest.approx(1.0)
