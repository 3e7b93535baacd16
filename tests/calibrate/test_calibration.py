"""Operator calibration on synthetic holds: rotation, arm length, scale, rejections, profiles."""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest

from telerig.calibrate import (
    FORWARD_TOP_UP,
    CalibrationError,
    CalibrationProfile,
    CalibrationSettings,
    alignment_for,
    calibrate_from_device,
    cube_rotations,
    load_profile,
    profile_path,
    role_from_source,
    run_calibration,
    save_profile,
)
from telerig.calibrate.rotations import matrix_from_quat, mean_quaternion, quat_from_matrix
from telerig.config.schema import AlignmentConfig
from telerig.devices.base import SampleSink
from telerig.errors import ConfigError
from telerig.ir.frames import quat_angle, quat_from_axis_angle, quat_multiply
from telerig.ir.types import (
    BodySkeleton,
    ControllerState,
    FloatArray,
    Handedness,
    HandPose,
    Pose,
    Sample,
    Stamp,
)
from telerig.retarget.alignment import Alignment

T0 = 1_700_000_000_000_000_000
HEAD = np.array([0.0, 0.0, 1.65])
ARM = 0.65
# Shoulders as the default anthropometric model places them from HEAD (forward = +x, up = +z).
SHOULDERS = {"left": np.array([-0.09, 0.19, 1.44]), "right": np.array([-0.09, -0.19, 1.44])}
NEUTRAL = {h: s + np.array([ARM, 0.0, 0.0]) for h, s in SHOULDERS.items()}


def hold(
    *,
    duration_s: float = 30.0,
    rate_hz: float = 50.0,
    frame: FloatArray | None = None,
    hand_turn: FloatArray | None = None,
    wobble_m: float = 0.0,
    head: bool = True,
    hands: tuple[Handedness, ...] = ("left", "right"),
    noise: float = 0.002,
    start_s: float = 0.0,
    kind: str = "controller",
) -> list[Sample]:
    """Samples of a hands-forward hold, in a device frame rotated by ``frame`` (w, x, y, z) from the
    operator frame; ``hand_turn`` rotates the hands' orientation (operator frame)."""
    rng = np.random.default_rng(0)
    r = np.eye(3) if frame is None else matrix_from_quat(frame)
    q_frame = np.array([1.0, 0, 0, 0]) if frame is None else frame
    q_hand = np.array(FORWARD_TOP_UP)
    if hand_turn is not None:
        q_hand = quat_multiply(hand_turn, q_hand)
    out: list[Sample] = []
    n = int(duration_s * rate_hz)
    for i in range(n):
        t = T0 + int((start_s + i / rate_hz) * 1e9)
        for hand in hands:
            p = NEUTRAL[hand] + rng.normal(0.0, noise, 3)
            if hand == "right":
                p = p + np.array([0.0, 0.0, wobble_m * math.sin(i / rate_hz * 2.0)])
            tilt = quat_from_axis_angle(rng.normal(size=3), math.radians(rng.normal(0.0, 1.0)))
            q = quat_multiply(q_frame, quat_multiply(tilt, q_hand))
            stamp = Stamp(f"vr0/{hand}", i, t, t)
            if kind == "controller":
                out.append(ControllerState(stamp, hand, r @ p, q, "device"))
            elif kind == "hand":
                kp = np.tile(r @ p, (21, 1))
                out.append(HandPose(stamp, hand, r @ p, q, kp, np.ones(21), "device"))
            else:
                out.append(Pose(stamp, r @ p, q, "device"))
        if head:
            out.append(Pose(Stamp("vr0/head", i, t, t), r @ HEAD, q_frame, "device"))
    return out


def calibrate(samples: list[Sample], **settings: object) -> CalibrationProfile:
    return run_calibration(samples, operator="ada", settings=CalibrationSettings(**settings))  # type: ignore[arg-type]


def test_axis_aligned_hold_gives_identity_rotation() -> None:
    profile = calibrate(hold())
    assert np.allclose(profile.rotation, (1.0, 0.0, 0.0, 0.0))
    assert profile.residual_deg < 5.0


def test_arm_length_and_scale_from_the_head_pose() -> None:
    profile = calibrate(hold(), robot_reach_m=0.85)
    assert profile.arm_length_source == "head"
    assert profile.arm_length_m == pytest.approx(ARM, abs=0.005)
    assert profile.scale == pytest.approx(0.85 / ARM, rel=0.01)
    for hand in ("left", "right"):
        assert np.allclose(profile.shoulders[hand], SHOULDERS[hand], atol=0.005)  # type: ignore[index]


def test_neutral_positions_are_the_mean_hand_positions() -> None:
    profile = calibrate(hold())
    for hand in ("left", "right"):
        assert np.allclose(profile.neutral_positions[hand], NEUTRAL[hand], atol=0.002)  # type: ignore[index]


@pytest.mark.parametrize("yaw_deg", [90, 180, -90])
def test_operator_turned_in_the_device_frame_is_rotated_back(yaw_deg: int) -> None:
    q_frame = quat_from_axis_angle(np.array([0.0, 0.0, 1.0]), math.radians(yaw_deg))
    profile = calibrate(hold(frame=q_frame))
    expected = quat_from_axis_angle(np.array([0.0, 0.0, 1.0]), math.radians(-yaw_deg))
    assert quat_angle(np.array(profile.rotation), expected) < 1e-6
    assert profile.arm_length_m == pytest.approx(ARM, abs=0.005)


def test_y_up_device_frame_is_found_among_the_24_rotations() -> None:
    # OpenXR-like world: operator forward = -z, left = -x, up = +y.
    r = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])
    profile = calibrate(hold(frame=quat_from_matrix(r)), up=(0.0, 1.0, 0.0))
    assert np.allclose(matrix_from_quat(np.array(profile.rotation)), r.T, atol=1e-9)
    assert profile.arm_length_m == pytest.approx(ARM, abs=0.005)


def test_robot_neutral_pointing_down_rotates_forward_onto_down() -> None:
    down = (0.0, 1.0, 0.0, 0.0)  # tool z -> base -z, top forward
    profile = calibrate(hold(), robot_neutral_orientation=down)
    r = matrix_from_quat(np.array(profile.rotation))
    assert np.allclose(r @ np.array([1.0, 0.0, 0.0]), [0.0, 0.0, -1.0])


def test_slightly_tilted_hands_still_snap_to_the_nearest_axis() -> None:
    tilt = quat_from_axis_angle(np.array([0.0, 1.0, 0.0]), math.radians(20))
    profile = calibrate(hold(hand_turn=tilt))
    assert np.allclose(profile.rotation, (1.0, 0.0, 0.0, 0.0))
    assert profile.residual_deg == pytest.approx(20.0, abs=2.0)


def test_hands_between_two_axes_are_rejected() -> None:
    turn = quat_from_axis_angle(np.array([0.0, 0.0, 1.0]), math.radians(45))
    with pytest.raises(CalibrationError, match="axis-aligned"):
        calibrate(hold(hand_turn=turn))


def test_moving_hand_is_rejected_with_one_line_reason() -> None:
    with pytest.raises(CalibrationError, match="right hand moved") as info:
        calibrate(hold(wobble_m=0.10))
    assert "\n" not in str(info.value)


def test_hands_at_different_heights_are_rejected() -> None:
    samples = [
        ControllerState(s.stamp, s.hand, s.position + np.array([0.0, 0.0, 0.3]), s.orientation, s.frame_id)
        if isinstance(s, ControllerState) and s.hand == "left"
        else s
        for s in hold()
    ]
    with pytest.raises(CalibrationError, match="level"):
        calibrate(samples)


def test_short_hold_is_rejected() -> None:
    with pytest.raises(CalibrationError, match=r"tracked for 10\.0 s of the 30\.0 s"):
        calibrate(hold(duration_s=10.0))


def test_missing_hand_is_rejected() -> None:
    with pytest.raises(CalibrationError, match="no valid left hand samples"):
        calibrate(hold(hands=("right",)))


def test_one_handed_calibration_when_asked() -> None:
    profile = calibrate(hold(hands=("right",)), hands=("right",))
    assert set(profile.neutral_positions) == {"right"}


def test_without_head_or_skeleton_the_arm_cannot_be_measured() -> None:
    with pytest.raises(CalibrationError, match="arm_length_m"):
        calibrate(hold(head=False))


def test_given_arm_length_is_used() -> None:
    profile = calibrate(hold(head=False), arm_length_m=0.7, robot_reach_m=0.7)
    assert profile.arm_length_source == "given"
    assert profile.scale == pytest.approx(1.0)


def test_skeleton_shoulders_are_preferred_to_the_head_model() -> None:
    samples = hold()
    shoulders = [SHOULDERS["left"] + [0, 0.05, 0], SHOULDERS["right"] - [0, 0.05, 0]]
    for i in range(0, 1500, 5):
        t = T0 + int(i / 50 * 1e9)
        samples.append(
            BodySkeleton(
                Stamp("mocap", i, t, t), ("LeftArm", "RightArm"), shoulders, [[1, 0, 0, 0]] * 2, "device"
            )
        )
    profile = calibrate(samples)
    assert profile.arm_length_source == "skeleton"
    assert profile.arm_length_m == pytest.approx(math.hypot(ARM, 0.05), abs=0.005)


def test_implausible_arm_length_is_rejected() -> None:
    with pytest.raises(CalibrationError, match="not plausible"):
        calibrate(hold(), shoulder_back_m=-0.5, shoulder_drop_m=0.0)  # shoulders 22 cm from hands


def test_only_the_last_window_is_used() -> None:
    moving = hold(duration_s=5.0, wobble_m=0.2)
    still = hold(start_s=5.0)
    profile = calibrate(moving + still)
    assert profile.duration_s == pytest.approx(30.0, abs=0.05)


def test_invalid_samples_are_ignored() -> None:
    samples = hold()
    bad = ControllerState(
        Stamp("vr0/right", 99_999, T0 + 1, T0 + 1), "right", [math.nan, 0, 0], FORWARD_TOP_UP, "device"
    )
    profile = calibrate([bad, *samples])
    assert profile.samples == 3000


@pytest.mark.parametrize("kind", ["hand", "pose"])
def test_hand_poses_and_plain_poses_work_too(kind: str) -> None:
    profile = calibrate(hold(kind=kind))
    assert np.allclose(profile.rotation, (1.0, 0.0, 0.0, 0.0))
    assert profile.arm_length_m == pytest.approx(ARM, abs=0.005)


def test_mixed_frames_are_rejected() -> None:
    samples = hold()
    samples.append(Pose(Stamp("x/head", 0, T0, T0), HEAD, (1.0, 0, 0, 0), "other"))
    with pytest.raises(CalibrationError, match="different frames"):
        calibrate(samples)


def test_role_from_source_names() -> None:
    assert role_from_source("quest/head") == "head"
    assert role_from_source("mocap/LeftHand") == "left"
    assert role_from_source("tracker-right") == "right"
    assert role_from_source("tracker3") is None


def test_alignment_maps_the_neutral_hand_onto_the_robot_neutral() -> None:
    q_frame = quat_from_axis_angle(np.array([0.0, 0.0, 1.0]), math.radians(90))
    samples = hold(frame=q_frame)
    profile = calibrate(samples)
    config = alignment_for(profile, hand="right", base=AlignmentConfig(robot_origin=(0.49, 0.13, 0.35)))
    assert config.robot_origin == (0.49, 0.13, 0.35)
    assert config.scale == profile.scale
    p, q = Alignment.from_config(config).apply(
        np.array(profile.neutral_positions["right"]), np.array(profile.neutral_orientations["right"])
    )
    assert np.allclose(p, [0.49, 0.13, 0.35])
    assert quat_angle(q, np.array(FORWARD_TOP_UP)) < math.radians(2.0)
    # Moving the hand forward 10 cm (device frame: +y) moves the robot forward by 10 cm x scale.
    forward = np.array(profile.neutral_positions["right"]) + np.array([0.0, 0.1, 0.0])
    p2, _ = Alignment.from_config(config).apply(forward, np.array(profile.neutral_orientations["right"]))
    assert np.allclose(p2 - p, [0.1 * profile.scale, 0.0, 0.0])


def test_alignment_for_a_hand_not_calibrated_names_the_calibrated_ones() -> None:
    profile = calibrate(hold(hands=("right",)), hands=("right",))
    with pytest.raises(ConfigError, match="calibrated hands: right"):
        alignment_for(profile, hand="left")


# --- profiles ----------------------------------------------------------------------------------


@pytest.fixture
def profile() -> CalibrationProfile:
    return run_calibration(hold(), operator="ada", created=datetime(2025, 1, 2, tzinfo=UTC))


def test_profile_round_trips_through_json(tmp_path: Path, profile: CalibrationProfile) -> None:
    path = save_profile(profile, data_root=tmp_path)
    assert path == tmp_path / "operators" / "ada.json"
    assert load_profile("ada", data_root=tmp_path) == profile
    assert not list(path.parent.glob("*.tmp"))


def test_missing_profile_says_how_to_make_one(tmp_path: Path, profile: CalibrationProfile) -> None:
    save_profile(profile, data_root=tmp_path)
    with pytest.raises(ConfigError, match=r"telerig calibrate --operator bob`\. Available: ada"):
        load_profile("bob", data_root=tmp_path)


def test_corrupt_profile_is_a_config_error(tmp_path: Path, profile: CalibrationProfile) -> None:
    path = save_profile(profile, data_root=tmp_path)
    path.write_text(path.read_text().replace('"version": 1', '"version": 7'))
    with pytest.raises(ConfigError, match="invalid"):
        load_profile("ada", data_root=tmp_path)


@pytest.mark.parametrize("name", ["../etc", "", "a/b", ".."])
def test_operator_name_cannot_escape_the_operators_folder(name: str) -> None:
    with pytest.raises(ConfigError, match="operator name"):
        profile_path(name)


# --- the cube group and quaternion helpers -------------------------------------------------------


def test_cube_rotations_are_the_24_element_group() -> None:
    mats = [m for m, _ in cube_rotations()]
    keys = {tuple(m.astype(int).ravel()) for m in mats}
    assert len(keys) == 24
    for a in mats:
        assert np.isclose(np.linalg.det(a), 1.0)
        for b in mats:
            assert tuple((a @ b).astype(int).ravel()) in keys


def test_cube_quaternions_match_their_matrices() -> None:
    for m, q in cube_rotations():
        assert np.allclose(matrix_from_quat(q), m)


def test_quaternion_matrix_round_trip() -> None:
    rng = np.random.default_rng(1)
    for _ in range(50):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q = -q if q[0] < 0 else q
        assert np.allclose(quat_from_matrix(matrix_from_quat(q)), q)


def test_mean_quaternion_ignores_the_sign() -> None:
    q = quat_from_axis_angle(np.array([1.0, 2.0, 3.0]), 0.7)
    assert np.allclose(mean_quaternion(np.array([q, -q, q])), q)


# --- collecting from a device --------------------------------------------------------------------


class HoldDevice:
    """Delivers a whole synthetic hold from ``start`` (synchronously)."""

    def __init__(self, samples: list[Sample]) -> None:
        self.samples = samples
        self.stopped = False

    @property
    def id(self) -> str:
        return "vr0"

    def start(self, sink: SampleSink) -> None:
        for s in self.samples:
            sink(s)

    def stop(self) -> None:
        self.stopped = True


def fake_time() -> tuple[Callable[[], float], Callable[[float], None]]:
    now = [0.0]

    def clock() -> float:
        return now[0]

    def sleep(s: float) -> None:
        now[0] += s

    return clock, sleep


def test_calibrate_from_device_runs_the_window_and_reports_progress() -> None:
    device = HoldDevice(hold())
    clock, sleep = fake_time()
    seen: list[tuple[float, float]] = []
    profile = calibrate_from_device(
        device,
        30.0,
        operator="ada",
        settle_s=2.0,
        progress=lambda e, t: seen.append((e, t)),
        clock=clock,
        sleep=sleep,
    )
    assert device.stopped
    assert profile.operator == "ada"
    assert seen[0] == (0.0, 32.0)
    assert seen[-1] == (32.0, 32.0)
    assert all(b[0] >= a[0] for a, b in itertools.pairwise(seen))


def test_calibrate_from_device_stops_the_device_when_rejected() -> None:
    device = HoldDevice(hold(wobble_m=0.2))
    clock, sleep = fake_time()
    with pytest.raises(CalibrationError, match="moved"):
        calibrate_from_device(device, 30.0, clock=clock, sleep=sleep)
    assert device.stopped
