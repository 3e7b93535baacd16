"""Tests of the per-model arm scenes: the Panda (7 DoF) next to the UR5e, and IK on the 7-DoF arm."""

from __future__ import annotations

import mink
import numpy as np
import pytest

from telerig.errors import ConfigError
from telerig.ir.types import GripperCommand, JointCommand, Stamp
from telerig.retarget.arm_ik import ArmIK
from telerig.robots.models.arm import ArmScene, build_arm_kinematics
from telerig.robots.models.arms import ARM_MODELS, PANDA
from telerig.robots.sim.arm import MujocoArm
from telerig.robots.sim.scene import build_arm_scene

pytestmark = pytest.mark.sim


@pytest.fixture(scope="module")
def panda_scene() -> ArmScene:
    return build_arm_scene("panda")


def _fingers(arm: MujocoArm) -> np.ndarray:
    with arm.locked() as (model, data):
        return np.array([data.qpos[model.joint(j).qposadr[0]] for j in arm.scene.gripper_joints])


@pytest.mark.parametrize("name", sorted(ARM_MODELS))
def test_every_model_builds_with_its_joints_and_limits(name: str) -> None:
    scene = build_arm_scene(name, with_cube=False)
    model = ARM_MODELS[name]
    assert scene.arm_joints == model.joints
    assert len(scene.arm_actuators) == len(model.joints)
    np.testing.assert_array_equal(scene.velocity_limit, model.velocity)
    assert scene.model.site(scene.ee_site).id >= 0
    assert build_arm_kinematics(scene.arm_model).arm_joints == scene.arm_joints


def test_unknown_model_names_the_available_ones() -> None:
    with pytest.raises(ConfigError, match="Available: ur5e_robotiq85, panda"):
        build_arm_scene("kuka")


def test_panda_driver_exposes_datasheet_limits(panda_scene: ArmScene) -> None:
    arm = MujocoArm(panda_scene, realtime=False)
    assert len(arm.joint_names) == 7
    np.testing.assert_allclose(arm.limits.velocity, PANDA.velocity)
    np.testing.assert_allclose(arm.limits.acceleration, PANDA.acceleration)
    assert arm.limits.upper[3] < 0  # the Panda's elbow only bends one way


def test_panda_home_holds_gripper_above_table_pointing_down(panda_scene: ArmScene) -> None:
    with MujocoArm(panda_scene, realtime=False) as arm:
        arm.step(500)
        np.testing.assert_allclose(arm.read_state().positions, panda_scene.home, atol=2e-3)
        with arm.locked() as (_, data):
            site = data.site(panda_scene.ee_site)
            assert site.xpos[2] - 0.8 == pytest.approx(0.3, abs=0.01)
            assert site.xmat.reshape(3, 3)[:, 2] @ np.array([0.0, 0.0, -1.0]) > 0.999


def test_panda_tracks_position_targets(panda_scene: ArmScene) -> None:
    with MujocoArm(panda_scene, realtime=False) as arm:
        target = panda_scene.home + np.array([0.3, -0.2, 0.2, 0.1, -0.1, 0.3, 0.2])
        arm.send(JointCommand(Stamp.now("test", 0), arm.joint_names, target))
        arm.step(1000)
        np.testing.assert_allclose(arm.read_state().positions, target, atol=2e-3)


def test_panda_hand_opens_at_connect_and_closes(panda_scene: ArmScene) -> None:
    with MujocoArm(panda_scene, realtime=False) as arm:
        arm.step(500)
        opened = _fingers(arm)
        arm.send_gripper(GripperCommand(Stamp.now("test", 0), opening=0.0))
        arm.step(500)
        closed = _fingers(arm)
        np.testing.assert_allclose(np.abs(opened), 0.04, atol=1e-3)
        np.testing.assert_allclose(closed, 0.0, atol=2e-3)


def test_ik_reaches_a_target_with_the_7_dof_arm() -> None:
    ik = ArmIK(build_arm_kinematics("panda"), velocity_limit=PANDA.velocity)
    home_pos, home_quat = ik.forward(ik.home)
    target_pos = home_pos + np.array([0.1, -0.15, -0.2])
    target_quat = np.asarray((mink.SO3(home_quat) @ mink.SO3.exp(np.array([0.0, 0.0, 0.4]))).wxyz)
    q = np.array(ik.home)
    for _ in range(200):
        result = ik.solve(target_pos, target_quat, q, dt=0.01)
        q = result.q
    assert result.position_error < 1e-3
    assert result.orientation_error < 0.01
    assert not result.flagged


def test_panda_kinematics_match_the_scene(panda_scene: ArmScene) -> None:
    ik = ArmIK(build_arm_kinematics("panda"))
    position, _ = ik.forward(panda_scene.home)
    with MujocoArm(panda_scene, realtime=False) as arm, arm.locked() as (_, data):
        base = data.body(panda_scene.base_body).xpos
        np.testing.assert_allclose(data.site(panda_scene.ee_site).xpos - base, position, atol=1e-6)
