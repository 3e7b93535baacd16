"""One G1 model for the IK, the simulated humanoid and the real robot: joint names, order and limits."""

from __future__ import annotations

import numpy as np
import pytest

from telerig.robots.models.g1 import UPPER_BODY_JOINTS, build_humanoid_kinematics, g1_urdf
from telerig.robots.sim.humanoid import build_humanoid_scene
from telerig.robots.unitree.config import UnitreeG1Config
from telerig.robots.unitree.joints import G1_UPPER_BODY_NAMES

pytestmark = pytest.mark.sim


def test_the_model_is_example_robot_datas_29_dof_g1_urdf() -> None:
    path = g1_urdf()
    assert path.name == "g1_29dof_rev_1_0.urdf"
    assert path.parent.parent.name == "g1_description"


def test_the_ik_and_the_simulated_g1_command_the_real_g1s_arm_sdk_joints_in_motor_order() -> None:
    assert UPPER_BODY_JOINTS == G1_UPPER_BODY_NAMES
    kinematic = build_humanoid_kinematics()
    assert tuple(kinematic.model.joint(i).name for i in range(kinematic.model.njnt)) == UPPER_BODY_JOINTS
    assert build_humanoid_scene().joints == UPPER_BODY_JOINTS


def test_the_simulated_and_the_real_g1_have_the_same_position_limits() -> None:
    real = UnitreeG1Config(id="g1").joint_limits()
    for scene in (build_humanoid_kinematics(), build_humanoid_scene(support="harness")):
        model = scene.model
        ranges = np.array([model.jnt_range[model.joint(j).id] for j in scene.joints])
        np.testing.assert_allclose(ranges[:, 0], real.lower, atol=1e-9)
        np.testing.assert_allclose(ranges[:, 1], real.upper, atol=1e-9)
