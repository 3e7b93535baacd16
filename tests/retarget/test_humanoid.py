"""Body skeleton → G1 upper body: keypoint profiles, anatomical scaling, IK residuals and flags."""

from __future__ import annotations

import math

import numpy as np
import pytest

from telerig.ir.types import BodySkeleton, Stamp
from telerig.retarget.humanoid import (
    KEYPOINTS,
    SKELETON_PROFILES,
    HumanoidIK,
    HumanoidMinkReference,
    HumanoidRetargeter,
    HumanoidTargets,
    KeypointMap,
)

pytestmark = pytest.mark.sim

_PELVIS = np.array([0.0, 0.0, 0.795])  # the G1 URDF standing on straight legs


@pytest.fixture(scope="module")
def ik() -> HumanoidIK:
    return HumanoidIK()


def _rz(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def fk_skeleton(
    ik: HumanoidIK,
    q: np.ndarray,
    *,
    profile: str = "mediapipe",
    scale: float = 1.4,
    yaw: float = 0.6,
    offset: tuple[float, float, float] = (1.0, -2.0, 0.1),
    prefix: str = "",
    seq: int = 0,
) -> BodySkeleton:
    """A skeleton drawn from the robot's own FK at ``q``, scaled, turned and moved (hips on the pelvis)."""
    points = ik.points(q)
    rows = [points[k] for k in KEYPOINTS[:6]]
    rows += [_PELVIS + np.array([0.0, -0.1, 0.0]), _PELVIS + np.array([0.0, 0.1, 0.0])]  # right, left hip
    world = ((np.array(rows) - _PELVIS) * scale) @ _rz(yaw).T + offset
    names = tuple(prefix + SKELETON_PROFILES[profile].joints[k] for k in KEYPOINTS)
    # Producers emit more joints than the retargeter reads, in their own order.
    names = ("nose", *reversed(names))
    positions = np.vstack([world.mean(axis=0), world[::-1]])
    return BodySkeleton(
        Stamp("test", seq, seq, seq), names, positions, np.tile([1.0, 0, 0, 0], (9, 1)), "operator"
    )


def _random_q(ik: HumanoidIK, rng: np.random.Generator) -> np.ndarray:
    q = np.clip(ik.home + rng.uniform(-0.5, 0.5, len(ik.joint_names)), ik.lower, ik.upper)
    # The retargeter steers the waist yaw only; the G1's waist roll and pitch hold home.
    for name in ("waist_roll_joint", "waist_pitch_joint"):
        q[ik.joint_names.index(name)] = ik.home[ik.joint_names.index(name)]
    return q


@pytest.mark.parametrize(("profile", "prefix"), [("mediapipe", ""), ("cmu", ""), ("motive", "Skeleton_")])
def test_skeleton_from_robot_fk_is_retargeted_with_small_residual(
    ik: HumanoidIK, profile: str, prefix: str
) -> None:
    rng = np.random.default_rng(7)
    for trial in range(4):
        q_true = _random_q(ik, rng)
        retargeter = HumanoidRetargeter(ik)
        skeleton = fk_skeleton(ik, q_true, profile=profile, prefix=prefix, seq=trial)
        q = np.array(ik.home)
        for _ in range(100):  # 1 s of 100 Hz control ticks from home, fed back
            command, result = retargeter(skeleton, q, 0.01)
            q = command.positions
        assert retargeter.keypoints.profile is not None
        assert retargeter.keypoints.profile.name == profile
        assert result.max_wrist_error < 0.005, f"trial {trial}: wrist errors {result.wrist_errors}"
        assert not result.flagged
        # The perfect answer's hands: the reached wrists are where the robot's own FK put them.
        reached, truth = ik.points(command.positions), ik.points(q_true)
        for side in ("right_wrist", "left_wrist", "right_elbow", "left_elbow"):
            assert np.linalg.norm(reached[side] - truth[side]) < 0.01, side


def test_each_step_is_the_qp_mink_solves(ik: HumanoidIK) -> None:
    # HumanoidIK builds mink's problem (the same tasks' residuals, ConfigurationLimit and
    # VelocityLimit as bounds) and hands it to DAQP itself; mink.solve_ik must find the same step:
    # from anywhere within the limits (on one too), targets near and far out of reach, a turned
    # waist, one or two sub-steps of 1-50 ms.
    reference = HumanoidMinkReference()
    rng = np.random.default_rng(11)
    home = ik.points(ik.home)
    for k in range(60):
        q = ik.lower + rng.uniform(0.0, 1.0, len(ik.joint_names)) * (ik.upper - ik.lower)
        if k % 4 == 0:
            joint = rng.integers(len(q))
            q[joint] = ik.upper[joint] if k % 8 == 0 else ik.lower[joint]
        spread = 0.15 if k % 3 else 1.0
        wrists = np.array([home["right_wrist"], home["left_wrist"]]) - home["torso"]
        elbows = np.array([home["right_elbow"], home["left_elbow"]]) - home["torso"]
        targets = HumanoidTargets(
            wrists + rng.normal(0.0, spread, (2, 3)),
            elbows + rng.normal(0.0, spread, (2, 3)),
            float(rng.uniform(-1.5, 1.5)),
            np.ones(4),
        )
        dt = float(rng.choice([0.001, 0.01, 0.05]))
        steps = 1 + k % 2
        expected = reference.solve(targets, q, dt, iterations=steps)
        got = ik.solve(targets, q, dt, iterations=steps)
        np.testing.assert_allclose(got.q, expected.q, atol=1e-8, err_msg=f"case {k}: q={q} dt={dt}")
        np.testing.assert_allclose(got.wrist_errors, expected.wrist_errors, atol=1e-7)
        np.testing.assert_allclose(got.elbow_errors, expected.elbow_errors, atol=1e-7)
        assert got.flagged == expected.flagged


def test_waist_follows_the_chest_yaw_relative_to_the_hips(ik: HumanoidIK) -> None:
    q_true = np.array(ik.home)
    q_true[0] = 0.4
    targets = HumanoidRetargeter(ik).targets(fk_skeleton(ik, q_true, yaw=-1.0))
    assert targets.waist_yaw == pytest.approx(0.4, abs=1e-6)


def test_segment_scale_is_the_robot_to_human_length_ratio(ik: HumanoidIK) -> None:
    targets = HumanoidRetargeter(ik).targets(fk_skeleton(ik, np.array(ik.home), scale=2.0))
    np.testing.assert_allclose(targets.scale, 0.5, rtol=0.02)


def test_joint_limits_are_never_exceeded(ik: HumanoidIK) -> None:
    rng = np.random.default_rng(3)
    retargeter = HumanoidRetargeter(ik)
    q = np.array(ik.home)
    for k in range(40):
        # Wild arm directions, many beyond what the robot can do.
        raw = fk_skeleton(ik, np.array(ik.home), seq=k)
        positions = np.array(raw.positions)
        positions[1:7] += rng.normal(0.0, 0.25, (6, 3))
        skeleton = BodySkeleton(raw.stamp, raw.joint_names, positions, raw.orientations, raw.frame_id)
        _, result = retargeter(skeleton, q, 0.05)
        assert np.all(result.q >= ik.lower), f"frame {k}"
        assert np.all(result.q <= ik.upper), f"frame {k}"
        q = result.q


def test_missing_joints_give_one_line_naming_them(ik: HumanoidIK) -> None:
    skeleton = fk_skeleton(ik, np.array(ik.home))
    keep = [i for i, n in enumerate(skeleton.joint_names) if n not in ("right_elbow", "left_wrist")]
    broken = BodySkeleton(
        skeleton.stamp,
        tuple(skeleton.joint_names[i] for i in keep),
        skeleton.positions[keep],
        skeleton.orientations[keep],
        skeleton.frame_id,
    )
    with pytest.raises(ValueError, match="lacks joints") as info:
        HumanoidRetargeter(ik).targets(broken)
    message = str(info.value)
    assert "\n" not in message
    assert "right_elbow" in message
    assert "left_wrist" in message
    assert "shoulder_" not in message  # only the missing ones are named


def test_hips_are_optional_and_hold_the_waist(ik: HumanoidIK) -> None:
    q_true = np.array(ik.home)
    q_true[0] = 0.4
    skeleton = fk_skeleton(ik, q_true)
    keep = [i for i, n in enumerate(skeleton.joint_names) if not n.endswith("_hip")]
    no_hips = BodySkeleton(
        skeleton.stamp,
        tuple(skeleton.joint_names[i] for i in keep),
        skeleton.positions[keep],
        skeleton.orientations[keep],
        skeleton.frame_id,
    )
    assert HumanoidRetargeter(ik).targets(no_hips).waist_yaw == 0.0


def test_unknown_profile_is_refused_with_the_valid_names() -> None:
    with pytest.raises(ValueError, match="mediapipe"):
        KeypointMap("kinect")


def test_hand_folded_onto_the_shoulder_is_flagged(ik: HumanoidIK) -> None:
    # Upper arm straight forward, forearm straight back: the hand on the shoulder. The G1's elbow
    # bends about 105 degrees at most, so this is out of reach.
    skeleton = fk_skeleton(ik, np.array(ik.home), yaw=0.0, offset=(0.0, 0.0, 0.0), scale=1.0)
    positions = np.array(skeleton.positions)
    rows = {n: i for i, n in enumerate(skeleton.joint_names)}
    shoulder = positions[rows["right_shoulder"]]
    positions[rows["right_elbow"]] = shoulder + np.array([0.28, 0.0, 0.0])
    positions[rows["right_wrist"]] = shoulder + np.array([0.03, 0.0, 0.0])
    folded = BodySkeleton(skeleton.stamp, skeleton.joint_names, positions, skeleton.orientations, "operator")
    _, result = HumanoidRetargeter(ik)(folded, ik.home, 2.0)
    assert result.flagged
    assert result.wrist_errors[0] > 0.05
    assert result.wrist_errors[1] < 0.05  # the left hand is fine


def test_command_carries_the_skeleton_stamp(ik: HumanoidIK) -> None:
    skeleton = fk_skeleton(ik, np.array(ik.home), seq=42)
    command, _ = HumanoidRetargeter(ik)(skeleton, ik.home, 0.01)
    assert command.stamp == skeleton.stamp
    assert command.names == ik.joint_names
