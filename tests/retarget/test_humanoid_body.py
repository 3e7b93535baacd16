"""The humanoid_body retargeter as the control loop sees it: binding, joint order, step timing, bad input."""

from __future__ import annotations

import dataclasses
import logging
import typing
from collections.abc import Iterator

import numpy as np
import pytest

from telerig.devices.mocap.fake import sample_bvh_path
from telerig.errors import ConfigError
from telerig.ir.types import BodySkeleton, FloatArray
from telerig.retarget.binding import BindContext, Bound
from telerig.retarget.config import HumanoidBodyConfig, KeypointFilterConfig
from telerig.retarget.humanoid import (
    SKELETON_PROFILES,
    HumanoidBodyRetargeter,
    HumanoidIK,
    HumanoidIKResult,
    HumanoidRetargeter,
)
from telerig.retarget.keypoint_filter import OneEuroPointFilter
from telerig.retarget.offline import load_skeletons
from telerig.robots.base import RobotDriver
from telerig.robots.models.g1 import HUMANOID_VELOCITY_LIMIT
from telerig.robots.sim.humanoid import MujocoHumanoid

pytestmark = pytest.mark.sim


@pytest.fixture(scope="module")
def robot() -> Iterator[MujocoHumanoid]:
    driver = MujocoHumanoid(realtime=False)
    yield driver
    driver.close()


@pytest.fixture(scope="module")
def ik() -> HumanoidIK:
    return HumanoidIK()


@pytest.fixture(scope="module")
def frames() -> list[BodySkeleton]:
    return load_skeletons(sample_bvh_path())


def _context(robot: RobotDriver, target: str = "body") -> BindContext:
    return BindContext("rig", "g1", robot, target, "mocap0", "body", ("mocap0",))


def _bind(robot: RobotDriver, config: HumanoidBodyConfig | None = None) -> HumanoidBodyRetargeter:
    bound = (config or HumanoidBodyConfig()).bind(_context(robot))
    assert isinstance(bound, Bound)
    assert isinstance(bound.joints, HumanoidBodyRetargeter)
    return bound.joints


def _at(frame: BodySkeleton, t_s: float) -> BodySkeleton:
    """``frame`` captured at ``t_s`` [s]."""
    ns = round(t_s * 1e9)
    return dataclasses.replace(frame, stamp=dataclasses.replace(frame.stamp, capture_ns=ns))


def _run(
    retargeter: HumanoidBodyRetargeter, frames: list[BodySkeleton], q: FloatArray
) -> list[HumanoidIKResult]:
    results = []
    for k, frame in enumerate(frames):
        command, result = retargeter(_at(frame, k / 60.0), q, 0.01)
        assert command is not None
        assert isinstance(result, HumanoidIKResult)
        q = command.positions
        results.append(result)
    return results


def test_bound_retargeter_commands_the_driver_joints_with_the_skeleton_stamp(
    robot: MujocoHumanoid, frames: list[BodySkeleton]
) -> None:
    retargeter = _bind(robot)
    assert retargeter.accepts == (BodySkeleton,)
    command, result = retargeter(frames[0], robot.scene.home, 0.01)
    assert command is not None
    assert result is not None
    assert command.names == robot.joint_names
    assert command.stamp == frames[0].stamp
    assert set(result.metrics()) == {
        "right_wrist_error_m",
        "left_wrist_error_m",
        "right_elbow_error_m",
        "left_elbow_error_m",
        "ik_time_s",
    }


def test_bound_retargeter_tracks_the_shipped_clip_without_flags_after_settling(
    robot: MujocoHumanoid, frames: list[BodySkeleton]
) -> None:
    retargeter = _bind(robot)
    results = _run(retargeter, frames + frames, np.array(robot.scene.home))
    settled = results[len(frames) :]  # the first pass starts from home, far from the performer
    assert not any(r.flagged for r in settled)
    assert max(r.max_wrist_error for r in settled) < 0.02


def test_commands_are_in_the_driver_joint_order(ik: HumanoidIK, frames: list[BodySkeleton]) -> None:
    driver_order = tuple(reversed(ik.joint_names))
    reference = HumanoidRetargeter(ik)
    permuted = HumanoidBodyRetargeter(HumanoidRetargeter(ik), driver_order)
    home = np.array(ik.home)
    _, expected = reference(frames[90], home, 0.05)
    command, _ = permuted(_at(frames[90], 0.0), home[::-1].copy(), 0.05)
    assert command is not None
    assert command.names == driver_order
    np.testing.assert_allclose(command.positions, expected.q[::-1], atol=1e-12)


def test_each_step_covers_the_time_since_the_previous_skeleton(
    ik: HumanoidIK, frames: list[BodySkeleton]
) -> None:
    retargeter = HumanoidBodyRetargeter(HumanoidRetargeter(ik), ik.joint_names, max_step_s=0.1)
    home = np.array(ik.home)
    far = frames[90]  # arm reached forward: far from home
    retargeter(_at(far, 0.0), home, 0.01)  # first sample: one control period
    command, _ = retargeter(_at(far, 1 / 60), home, 0.01)
    assert command is not None
    step = float(np.max(np.abs(command.positions - home)))
    assert HUMANOID_VELOCITY_LIMIT * 0.01 < step <= HUMANOID_VELOCITY_LIMIT / 60 + 1e-8  # stamps in ns
    command, _ = retargeter(_at(far, 10.0), home, 0.01)  # after a pause: capped at max_step_s
    assert command is not None
    assert float(np.max(np.abs(command.positions - home))) <= HUMANOID_VELOCITY_LIMIT * 0.1 + 1e-9


def test_a_skeleton_without_arms_is_skipped_with_one_warning(
    ik: HumanoidIK, frames: list[BodySkeleton], caplog: pytest.LogCaptureFixture
) -> None:
    retargeter = HumanoidBodyRetargeter(HumanoidRetargeter(ik), ik.joint_names)
    legs = [i for i, n in enumerate(frames[0].joint_names) if "Arm" not in n and "Hand" not in n]
    armless = BodySkeleton(
        frames[0].stamp,
        tuple(frames[0].joint_names[i] for i in legs),
        frames[0].positions[legs],
        frames[0].orientations[legs],
        frames[0].frame_id,
    )
    with caplog.at_level(logging.WARNING):
        assert retargeter(armless, np.array(ik.home), 0.01) == (None, None)
        assert retargeter(armless, np.array(ik.home), 0.01) == (None, None)
    assert retargeter.rejected == 2
    assert len([r for r in caplog.records if "lacks joints" in r.getMessage()]) == 1


def test_reset_forgets_the_step_clock_and_the_filter(ik: HumanoidIK, frames: list[BodySkeleton]) -> None:
    flt = OneEuroPointFilter()
    retargeter = HumanoidBodyRetargeter(HumanoidRetargeter(ik, keypoint_filter=flt), ik.joint_names)
    home = np.array(ik.home)
    retargeter(_at(frames[0], 0.0), home, 0.01)
    retargeter.reset()
    # After a reset the filter passes the first sample through: the targets equal the unfiltered ones.
    targets = retargeter.retargeter.targets(_at(frames[90], 0.02))
    reference = HumanoidRetargeter(ik).targets(frames[90])
    np.testing.assert_allclose(targets.wrists, reference.wrists, atol=1e-12)


def test_filter_config_builds_a_keypoint_filter(robot: MujocoHumanoid) -> None:
    retargeter = _bind(robot, HumanoidBodyConfig(filter=KeypointFilterConfig(min_cutoff_hz=1.5)))
    assert isinstance(retargeter.retargeter.keypoint_filter, OneEuroPointFilter)
    assert _bind(robot).retargeter.keypoint_filter is None


def test_profile_choices_are_the_shipped_skeleton_profiles() -> None:
    field = HumanoidBodyConfig.model_fields["profile"].annotation
    names = {a for arg in typing.get_args(field) for a in typing.get_args(arg)}
    assert names == set(SKELETON_PROFILES)


def test_a_target_other_than_body_is_one_line(robot: MujocoHumanoid) -> None:
    with pytest.raises(ConfigError, match=r"cannot drive target 'arm'\. Valid: body$") as info:
        HumanoidBodyConfig().bind(_context(robot, target="arm"))
    assert "\n" not in str(info.value)


def test_a_robot_that_is_not_a_humanoid_is_one_line() -> None:
    from telerig.robots.sim.arm import MujocoArm
    from telerig.robots.sim.scene import build_arm_scene

    arm = MujocoArm(build_arm_scene(), realtime=False)
    try:
        with pytest.raises(ConfigError, match=r"is a MujocoArm, use a mujoco_humanoid robot$") as info:
            HumanoidBodyConfig().bind(_context(arm))
    finally:
        arm.close()
    assert "\n" not in str(info.value)


def test_a_real_g1_binds_with_all_its_upper_body_joints_and_a_subset_is_one_line_naming_them() -> None:
    from telerig.robots.unitree.config import UnitreeG1Config

    g1 = UnitreeG1Config(id="g1", network_interface="lo").build()  # not connected: no DDS traffic
    assert _bind(g1).joint_names == g1.joint_names
    arms_only = UnitreeG1Config(id="g1", joints=g1.joint_names[3:]).build()
    refused = r"commands 14 of the G1's 17 upper-body joints; add waist_yaw_joint"
    with pytest.raises(ConfigError, match=refused) as info:
        HumanoidBodyConfig().bind(_context(arms_only))
    assert "\n" not in str(info.value)
